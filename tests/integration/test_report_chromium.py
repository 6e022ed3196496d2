"""The diagnose HTML report loads in headless Chromium without console errors
and every figure renders (naturalWidth > 0)."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

from afmdrift.config import AfmdriftConfig, RegistrationConfig
from afmdrift.diagnostics import write_report
from afmdrift.diagnostics._run import diagnose_path

HIDDEN = Path(__file__).resolve().parents[2] / "config" / "scenarios" / "hidden"

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")

pytestmark = pytest.mark.skipif(
    CHROMIUM is None,
    reason="chromium is not installed (Debian: apt-get install chromium; .ci/run installs it)",
)

_CHECK = re.compile(r'id="figure-check"[^>]*data-total="(\d+)"[^>]*data-rendered="(\d+)"')


def _load(page: Path, tmp_path: Path) -> tuple[str, list[str]]:
    """DOM after load and the console messages Chromium logged."""
    assert CHROMIUM is not None
    profile = tmp_path / f"profile-{page.stem}"
    proc = subprocess.run(
        [
            CHROMIUM,
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            f"--user-data-dir={profile}",
            "--enable-logging=stderr",
            "--v=0",
            "--virtual-time-budget=5000",
            "--dump-dom",
            page.as_uri(),
        ],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    # Chromium logs every console message (console.error, uncaught exceptions)
    # as an INFO:CONSOLE line whatever its level; the report writes none, so
    # any such line is a failure.
    messages = [line for line in proc.stderr.splitlines() if ":CONSOLE" in line]
    return proc.stdout, messages


def _figure_check(dom: str) -> tuple[int, int]:
    m = _CHECK.search(dom)
    assert m is not None, "the page's figure check did not run"
    return int(m.group(1)), int(m.group(2))


def test_detector_catches_a_broken_figure_and_a_console_error(tmp_path: Path) -> None:
    """Guards the test itself: a page with a broken image and a console error must fail it."""
    page = tmp_path / "broken.html"
    page.write_text(
        "<!DOCTYPE html><html><body>"
        '<img class="figure" src="data:image/png;base64,AAAA">'
        "<script>console.error('deliberate failure');"
        "window.addEventListener('load',function(){var imgs=document.querySelectorAll"
        "('img.figure');var ok=0;imgs.forEach(function(i){if(i.complete&&i.naturalWidth>0)"
        "{ok++;}});var m=document.createElement('div');m.id='figure-check';"
        "m.setAttribute('data-total',imgs.length);m.setAttribute('data-rendered',ok);"
        "document.body.appendChild(m);});</script></body></html>",
        encoding="utf-8",
    )
    dom, errors = _load(page, tmp_path)
    total, rendered = _figure_check(dom)
    assert (total, rendered) == (1, 0)
    assert any("deliberate failure" in e for e in errors), errors


@pytest.mark.slow
def test_report_renders_every_figure_without_console_errors(tmp_path: Path) -> None:
    from afmdrift.drivers.sim._record import record_session

    session = tmp_path / "session"
    record_session(HIDDEN / "scan_direction.toml", session, seed=3, frames=40)
    config = AfmdriftConfig(registration=RegistrationConfig(block_size=32, extended_size=96))
    dg, data = diagnose_path(session, config=config, effects=["trend", "thermal_lag", "creep"])
    page = write_report(dg, data, tmp_path / "report.html", registration=config.registration)
    text = page.read_text(encoding="utf-8")
    assert "http://" not in text  # self-contained: no external resources
    assert "https://" not in text
    n_img = text.count('<img class="figure"')
    assert n_img >= 7  # compare, errors, ACF, x-corr, added-variable, before/after, field
    dom, errors = _load(page, tmp_path)
    assert errors == []
    total, rendered = _figure_check(dom)
    assert total == n_img
    assert rendered == total
