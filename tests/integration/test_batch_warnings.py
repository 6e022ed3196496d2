"""Every warning ``afmdrift batch`` prints names its recording: in an archive of
hundreds, "frame 2: registration failed" alone says nothing."""

from __future__ import annotations

import logging
import warnings
from pathlib import Path

import numpy as np
import pytest
from service_sim import run_afmdrift

from afmdrift.batch._jobs import named_warnings
from afmdrift.testing import rough_texture, shifted_crop


def test_a_job_s_logged_and_warned_warnings_start_with_its_recording(
    capsys: pytest.CaptureFixture[str],
) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("default")
        with named_warnings("arc/m1.npy"):
            logging.getLogger("afmdrift.pipeline").warning("frame %d: bad", 3)
            warnings.warn("an odd header", UserWarning, stacklevel=1)
    lines = capsys.readouterr().err.splitlines()
    assert lines[0] == "arc/m1.npy: frame 3: bad"
    assert lines[1].startswith("arc/m1.npy: ")
    assert "UserWarning: an odd header" in lines[1]
    # the package's logging is as it was once the job is done
    assert logging.getLogger("afmdrift").propagate
    assert not logging.getLogger("afmdrift").handlers


@pytest.mark.slow
def test_batch_names_the_recording_in_a_worker_s_warning(tmp_path: Path) -> None:
    """Regression: a worker's "frame 2 (instrument 2): registration failed"
    reached the terminal without the file it came from."""
    rng = np.random.default_rng(2)
    tex = rough_texture((300, 300), pixel_size_nm=1.0, rng=rng, correlation_length_nm=4.0)
    arc = tmp_path / "arc"
    arc.mkdir()
    for name, blank in (("blank.npy", 2), ("good.npy", None)):
        stack = np.stack([shifted_crop(tex, shape=(128, 128), dx_px=0.5 * k, dy_px=0.0)
                          for k in range(4)]).astype(np.float32)  # fmt: skip
        if blank is not None:
            stack[blank] = 0.0
        np.save(arc / name, stack)
    done = run_afmdrift("batch", "arc", "--out", "out", "--workers", "1",
                        "--pixel-size-nm", "2", cwd=tmp_path)  # fmt: skip
    assert done.returncode == 0, done.stderr
    lines = done.stderr.splitlines()
    assert lines[-1].startswith("2 done, 0 with no drift measured, 0 failed")
    warned = lines[:-1]
    assert any("registration failed" in line for line in warned), done.stderr
    for line in warned:
        assert line.startswith("arc/blank.npy: "), done.stderr
