"""Scenario files: validation messages and the built-in scenarios."""

from __future__ import annotations

from pathlib import Path

import pytest

from afmdrift.drivers.sim import SCENARIO_DIR, load_scenario, parse_scenario
from afmdrift.errors import ConfigError

BUILT_IN = (
    "default",
    "graphite-paper",
    "gold-manipulation-8h",
    "quiet-lab-24h",
    "hsafm-movie",
    "heat-network-2h",
)


@pytest.mark.parametrize("name", BUILT_IN)
def test_built_in_scenarios_load(name: str) -> None:
    sc = load_scenario(name)
    assert sc.name == name
    assert (SCENARIO_DIR / f"{name}.toml").is_file()


def test_graphite_paper_matches_the_paper_timing() -> None:
    sc = load_scenario("graphite-paper")
    assert sc.scan.pixels == (512, 512)
    assert sc.scan.line_rate_hz == 4.0
    assert sc.scan.frame_period_s == 256.0
    assert sc.duration_s == 8 * 3600.0


def test_unknown_key_is_named_with_the_allowed_keys(tmp_path: Path) -> None:
    p = tmp_path / "bad.toml"
    p.write_text("[physics.thermal]\nenabled = true\nalpha = 3\n")
    with pytest.raises(ConfigError, match=r"unknown key 'physics\.thermal\.alpha'") as info:
        load_scenario(p)
    assert "alpha_nm_per_k" in str(info.value)
    assert str(p) in str(info.value)


def test_out_of_range_value_names_key_value_and_range() -> None:
    with pytest.raises(ConfigError) as info:
        parse_scenario({"physics": {"creep": {"gamma_per_decade": 2.0}}}, source="s.toml")
    msg = str(info.value)
    assert "s.toml: physics.creep.gamma_per_decade = 2.0" in msg
    assert ">= 0 and <= 0.5" in msg


def test_range_inside_an_array_of_tables_is_reported() -> None:
    with pytest.raises(ConfigError, match=r"offset_moves\.0\.t_s = -5.0.*>= 0"):
        parse_scenario({"offset_moves": [{"t_s": -5.0, "x_nm": 0.0, "y_nm": 0.0}]})


def test_scan_larger_than_half_the_sample_is_rejected() -> None:
    with pytest.raises(
        ConfigError, match=r"^<scenario>: Value error, scan.size_nm x = 5000.0 .*enlarge"
    ):
        parse_scenario({"scan": {"size_nm": [5000.0, 5000.0]}, "sample": {"map_px": 1024}})


def test_texture_kind_requires_a_texture_table() -> None:
    with pytest.raises(ConfigError, match=r"\[sample.texture\]"):
        parse_scenario({"sample": {"kind": "texture"}})


def test_missing_scenario_lists_the_built_in_ones() -> None:
    with pytest.raises(ConfigError, match="graphite-paper"):
        load_scenario("no-such-scenario")


def test_invalid_toml_is_reported_with_the_file(tmp_path: Path) -> None:
    p = tmp_path / "broken.toml"
    p.write_text("[scan\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_scenario(p)
