"""Configuration loading: defaults, unknown keys and range errors name the key."""

from __future__ import annotations

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
