"""FFTW plans and wisdom: the file is written, reused, and never fatal."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pyfftw
import pytest

from afmdrift.registration import RegistrationConfig, _fftw
from afmdrift.registration._fftw import BatchedRealFFT, default_wisdom_path, resolve_wisdom_path


@pytest.fixture(autouse=True)
def _fresh_wisdom_state(monkeypatch: pytest.MonkeyPatch) -> None:
    """Each test sees wisdom files as never loaded in this process, and FFTW
    with no wisdom in memory: wisdom loaded earlier in the process (e.g. the
    default file, which may hold this module's own shapes from an earlier
    run) would otherwise make planning add nothing, so nothing is written."""
    monkeypatch.setattr(_fftw, "_loaded", set())
    pyfftw.forget_wisdom()


def test_wisdom_path_precedence(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.delenv("AFMDRIFT_FFTW_WISDOM", raising=False)
    assert default_wisdom_path().parent == tmp_path / "cache" / "afmdrift"
    assert default_wisdom_path().name.startswith("fftw-wisdom-")
    assert resolve_wisdom_path(None) == default_wisdom_path()
    monkeypatch.setenv("AFMDRIFT_FFTW_WISDOM", str(tmp_path / "env.wis"))
    assert resolve_wisdom_path(None) == tmp_path / "env.wis"
    assert resolve_wisdom_path(str(tmp_path / "cfg.wis")) == tmp_path / "cfg.wis"
    assert resolve_wisdom_path("") is None


def test_new_plans_write_wisdom_that_a_later_run_reads(tmp_path: Path) -> None:
    path = tmp_path / "sub" / "wisdom"
    fft = BatchedRealFFT(3, (40, 36), planner="estimate", wisdom_path=path)
    fft = BatchedRealFFT(3, (42, 38), planner="measure", wisdom_path=path)
    assert path.is_file()
    data = path.read_bytes()
    assert data.startswith(b"afmdrift-fftw-wisdom 1\n")
    assert _fftw._decode(data) is not None
    # The transforms are right: forward then inverse returns rows·cols × input.
    x = np.random.default_rng(0).standard_normal(fft.real.shape).astype(np.float32)
    fft.real[:] = x
    fft.forward()
    np.testing.assert_allclose(fft.spectrum[1], np.fft.rfft2(x[1]), rtol=1e-4, atol=1e-3)
    fft.inverse()
    np.testing.assert_allclose(fft.real / (42 * 38), x, atol=1e-4)


def test_unwritable_wisdom_location_is_not_fatal(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a directory", encoding="utf-8")
    with caplog.at_level(logging.INFO, logger="afmdrift.registration._fftw"):
        fft = BatchedRealFFT(2, (44, 34), planner="measure", wisdom_path=blocker / "wisdom")
    assert fft.real.shape == (2, 44, 34)
    assert "cannot write FFTW wisdom" in caplog.text


def test_corrupt_wisdom_file_is_ignored_with_a_warning(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "wisdom"
    path.write_bytes(b"afmdrift-fftw-wisdom 1\n999\nshort")
    with caplog.at_level(logging.WARNING, logger="afmdrift.registration._fftw"):
        BatchedRealFFT(2, (46, 30), planner="estimate", wisdom_path=path)
    assert "malformed FFTW wisdom" in caplog.text


def test_config_setting_selects_the_wisdom_file(tmp_path: Path) -> None:
    from afmdrift.registration._engine import BlockEngine

    path = tmp_path / "engine.wis"
    BlockEngine((96, 130), RegistrationConfig(gradient="x", fftw_wisdom=str(path)))
    assert path.is_file()


def test_a_plan_freed_while_this_thread_plans_does_not_deadlock() -> None:
    """Plans are destroyed by a finalizer that takes the planner lock; garbage
    collection can run it on a thread that holds the lock (while it plans)."""
    import gc
    import threading

    def plan_while_an_old_plan_is_collected() -> None:
        old = BatchedRealFFT(2, (40, 36), planner="estimate", wisdom_path=None)
        with _fftw._lock:
            del old
            gc.collect()

    t = threading.Thread(target=plan_while_an_old_plan_is_collected, daemon=True)
    t.start()
    t.join(timeout=30)
    assert not t.is_alive(), "the plan finalizer deadlocked on the planner lock"


@pytest.mark.parametrize(
    ("top", "left"),
    [
        # a column of windows whose rows overlap (the engine's batches)
        ([3, 13, 24, 34], [7, 7, 7, 7]),
        # clamped windows at the same place, a gap, another column, a
        # window inside the previous one's rows
        ([0, 0, 40, 5, 5, 9], [7, 7, 7, 20, 0, 0]),
    ],
)
def test_forward_strips_equals_the_2d_transform_of_each_window(
    top: list[int], left: list[int]
) -> None:
    """The two-step forward transform (rows once per run of windows, then
    columns) gives each window's ``rfft2(block · wy ⊗ wx)``, whatever the
    runs, and in the batch's order of the blocks."""
    from afmdrift.registration import _spectra
    from afmdrift.registration._blocks import raised_cosine_axis
    from afmdrift.registration._constants import TransformConstants
    from afmdrift.registration._passes import Windows, thread_work

    rng = np.random.default_rng(5)
    ey, ex, nb = 32, 24, len(top)
    grad = rng.standard_normal((80, 60)).astype(np.float32)
    fft = BatchedRealFFT(nb, (ey, ex), planner="estimate", wisdom_path=None, strip_rows=nb * ey)
    # garbage in the strip's spare rows must not matter
    fft.strip[:] = np.nan
    wy = raised_cosine_axis(ey).astype(np.float32)
    wx = raised_cosine_axis(ex).astype(np.float32)
    order = rng.permutation(nb).astype(np.intp)
    tops = np.empty(nb, np.intp)
    lefts = np.empty(nb, np.intp)
    tops[order] = top  # batch entry k is block order[k]
    lefts[order] = left
    lib = _fftw.fftwf()
    execute = np.array([lib.execute_r2c, lib.execute_c2c], dtype=np.uint64)
    _spectra.forward_strips(
        TransformConstants(wy=wy, wx=wx, execute=execute), Windows(grad, tops, lefts), order,
        fft.plans, thread_work([fft], np.zeros((0, 1, 2), np.float32)),
    )  # fmt: skip
    for k, i in enumerate(order):
        block = grad[tops[i] : tops[i] + ey, lefts[i] : lefts[i] + ex].astype(np.float64)
        want = np.fft.rfft2(block * np.outer(wy, wx))
        np.testing.assert_allclose(fft.spectrum[k], want, rtol=0, atol=2e-5 * np.abs(want).max())


def test_a_shared_strip_must_be_large_enough() -> None:
    big = BatchedRealFFT(4, (16, 16), planner="estimate", wisdom_path=None, strip_rows=4 * 16)
    small = BatchedRealFFT(
        2, (16, 16), planner="estimate", wisdom_path=None, strip_rows=2 * 16, share=big
    )
    assert small.strip is big.strip
    assert small.plans.shape == (5,)
    assert small.pointers.shape == (5,)
    with pytest.raises(ValueError, match="as many blocks"):
        BatchedRealFFT(2, (16, 16), planner="estimate", wisdom_path=None, strip_rows=80, share=big)


def test_spectra_kept_by_a_measuring_pass_are_those_of_a_new_reference() -> None:
    """In consecutive mode the spectra a pass keeps become the next
    reference without a second FFT: the reference's own path computes the
    same transform, in the same batches, bit for bit."""
    from afmdrift.registration._engine import BlockEngine
    from afmdrift.testing import TextureShifter, particle_texture

    tex = particle_texture((400, 400), pixel_size_nm=2.0, rng=np.random.default_rng(2))
    shifter = TextureShifter(tex)
    a, b = (shifter.crop((300, 300), dx_px=d, dy_px=-d) for d in (0.0, 1.3))
    cfg = RegistrationConfig(gradient="x", reference="consecutive")
    engine = BlockEngine((300, 300), cfg)
    ref = engine.reference(engine.gradient(a))
    grad = engine.gradient(b)
    _, top, left = engine.measure(ref, grad)
    kept = engine.current_as_reference(grad, top, left)
    again = engine.reference(grad)
    np.testing.assert_array_equal(kept.conj_spectra, again.conj_spectra)
    np.testing.assert_array_equal(kept.band_mag, again.band_mag)
