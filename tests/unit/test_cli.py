"""The command line: --version, --help on every subcommand, config check."""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import pytest

from afmdrift import __version__
from afmdrift.cli import build_parser, main
from afmdrift.config import DEFAULT_CONFIG_PATH


def _subcommand_paths(parser: argparse.ArgumentParser, prefix: tuple[str, ...] = ()):  # type: ignore[no-untyped-def]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield (*prefix, name)
                yield from _subcommand_paths(sub, (*prefix, name))


def test_version_flag(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main(["--version"])
    assert info.value.code == 0
    assert __version__ in capsys.readouterr().out


def test_every_subcommand_has_help(capsys: pytest.CaptureFixture[str]) -> None:
    paths = list(_subcommand_paths(build_parser()))
    assert ("config", "check") in paths
    for path in paths:
        with pytest.raises(SystemExit) as info:
            main([*path, "--help"])
        assert info.value.code == 0, path
        assert "usage:" in capsys.readouterr().out


def test_config_check_accepts_default(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["config", "check", str(DEFAULT_CONFIG_PATH)]) == 0
    assert "OK" in capsys.readouterr().out


def test_config_check_reports_bad_key_without_traceback(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[registration]\nblock_size = 4\n", encoding="utf-8")
    proc = subprocess.run(
        [sys.executable, "-m", "afmdrift", "config", "check", str(bad)],
        capture_output=True,
        text=True,
        check=False,
    )
    assert proc.returncode == 2
    assert "registration.block_size = 4" in proc.stderr
    assert ">= 8" in proc.stderr
    assert "Traceback" not in proc.stderr


@pytest.mark.parametrize("argv", [["config", "show"], ["--help"]])
def test_a_closed_pipe_ends_the_command_quietly(argv: list[str]) -> None:
    """Regression: ``afmdrift config show | head`` ended in a BrokenPipeError
    traceback. The reader is gone before the command writes (a real pipe whose
    read end is closed), as when ``head`` has had its lines. ``--help`` exits 0:
    argparse drops a failed write of its help itself."""
    from afmdrift.cli import EXIT_BROKEN_PIPE

    proc = subprocess.Popen(
        [sys.executable, "-m", "afmdrift", *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout is not None
    proc.stdout.close()
    _, err = proc.communicate(timeout=60)
    assert "Traceback" not in err
    assert "BrokenPipeError" not in err
    assert err == ""
    assert proc.returncode == (0 if argv == ["--help"] else EXIT_BROKEN_PIPE)
