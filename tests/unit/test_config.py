"""Configuration loading: defaults, unknown keys and range errors name the key."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from afmdrift.config import DEFAULT_CONFIG_PATH, AfmdriftConfig, load_config, parse_config
from afmdrift.errors import ConfigError


def test_default_config_file_is_valid() -> None:
    cfg = load_config(DEFAULT_CONFIG_PATH)
    assert isinstance(cfg, AfmdriftConfig)
    assert cfg.registration.block_size == 64
    assert cfg.registration.extended_size == 128


def test_unknown_key_is_rejected_with_its_dotted_name() -> None:
    with pytest.raises(ConfigError) as info:
        parse_config({"registration": {"blok_size": 64}}, source="x.toml")
    msg = str(info.value)
    assert "unknown key 'registration.blok_size'" in msg
    assert "block_size" in msg  # the allowed keys are listed


def test_unknown_section_is_rejected() -> None:
    with pytest.raises(ConfigError, match="unknown key 'registraton'"):
        parse_config({"registraton": {}})


def test_out_of_range_value_names_key_value_and_range() -> None:
    with pytest.raises(ConfigError) as info:
        parse_config({"registration": {"peaks": 0}}, source="bad.toml")
    msg = str(info.value)
    assert "bad.toml" in msg
    assert "registration.peaks = 0" in msg
    assert ">= 1" in msg
    assert "<= 32" in msg


def test_literal_value_lists_choices() -> None:
    with pytest.raises(ConfigError) as info:
        parse_config({"registration": {"gradient": "diagonal"}})
    assert "registration.gradient = 'diagonal'" in str(info.value)
    assert "'x'" in str(info.value)
    assert "'both'" in str(info.value)


def test_inconsistent_block_sizes_are_rejected() -> None:
    with pytest.raises(ConfigError, match="extended_size"):
        parse_config({"registration": {"block_size": 128, "extended_size": 64}})


def test_bad_toml_and_missing_file_name_the_file(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[registration\n", encoding="utf-8")
    with pytest.raises(ConfigError, match=r"bad\.toml: not valid TOML"):
        load_config(bad)
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "absent.toml")


@pytest.mark.parametrize(
    ("toml", "message"),
    [
        ('[service]\narchive_frames = "yes"\n', "service.archive_frames = 'yes'"),
        ("[registration]\nthreads = true\n", "registration.threads = True"),
        ("[service]\nexpected_frame_interval_s = inf\n", "finite number"),
        ("[service]\noffset_rate_hz = nan\n", "finite number"),
        ('[service]\nrun_dir = ""\n', "service.run_dir = ''"),
        ('[service]\ncontrol_endpoint = "tcp://127.0.0.1:notaport"\n', "is not 1-65535"),
        ('[service]\npub_endpoint = "udp://127.0.0.1:5"\n', "use tcp://HOST:PORT"),
    ],
    ids=["bool_as_text", "int_as_bool", "inf", "nan", "empty_run_dir", "bad_port", "bad_scheme"],
)
def test_values_that_passed_silently_are_rejected(tmp_path: Path, toml: str, message: str) -> None:
    """Regression: these values passed validation (coerced, or taken as is)."""
    path = tmp_path / "c.toml"
    path.write_text(toml, encoding="utf-8")
    with pytest.raises(ConfigError, match=re.escape(message)):
        load_config(path)


def test_integers_are_still_accepted_for_floats(tmp_path: Path) -> None:
    path = tmp_path / "c.toml"
    path.write_text("[service]\noffset_rate_hz = 200\n", encoding="utf-8")
    assert load_config(path).service.offset_rate_hz == 200.0


@pytest.mark.parametrize(
    ("toml", "message"),
    [
        ('[model]\npredictor = "crystal_ball"\n', "unknown predictor 'crystal_ball'"),
        (
            '[model]\npredictor = "physics"\n[model.physics]\nterms = ["trend", "poltergeist"]\n',
            "unknown term(s) 'poltergeist'",
        ),
        (
            '[model]\npredictor = "physics"\n[model.physics]\nplugins = ["no_such_module_x:T"]\n',
            "cannot import 'no_such_module_x'",
        ),
    ],
    ids=["predictor", "term", "plugin"],
)
def test_config_check_rejects_what_run_rejects(tmp_path: Path, toml: str, message: str) -> None:
    """Regression: `config check` passed configurations that `run` then refused."""
    path = tmp_path / "c.toml"
    path.write_text(toml, encoding="utf-8")
    done = subprocess.run(
        [sys.executable, "-m", "afmdrift", "config", "check", str(path)],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 2, done.stdout
    assert message in done.stderr
    assert "Traceback" not in done.stderr
