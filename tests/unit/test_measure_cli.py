"""``afmdrift measure`` on synthetic images with known shifts (ground truth built here)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import fourier_shift, gaussian_filter

from afmdrift.cli import main
from afmdrift.cli._measure import measurement_config
from afmdrift.errors import ConfigError
from afmdrift.registration import RegistrationConfig, measure_drift

SIZE = 256


def _texture(seed: int = 0, size: int = SIZE) -> np.ndarray:
    """Band-limited random surface, heights of a few nm."""
    rng = np.random.default_rng(seed)
    return 5.0 * gaussian_filter(rng.normal(size=(size, size)), 2.0, mode="wrap")


def _shifted(img: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """``img`` moved so that a feature at u appears at u + (dx, dy) (periodic)."""
    return np.fft.ifft2(fourier_shift(np.fft.fft2(img), (dy, dx))).real


def _save(path: Path, arr: np.ndarray) -> str:
    np.save(path, arr)
    return str(path)


def _json_lines(text: str) -> list[dict]:
    return [json.loads(line) for line in text.splitlines() if line.strip()]


def test_pair_json_recovers_subpixel_shift_in_px_and_nm(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    ref = _texture()
    a = _save(tmp_path / "a.npy", ref)
    b = _save(tmp_path / "b.npy", _shifted(ref, 1.37, -2.61))
    code = main(["measure", a, b, "--pixel-size-nm", "2", "3", "--json"])
    assert code == 0
    doc = json.loads(capsys.readouterr().out)
    for key in ("dx_px", "dy_px", "dx_nm", "dy_nm", "sigma_nm", "valid_blocks", "total_blocks"):
        assert key in doc
    assert doc["valid"] is True
    assert doc["dx_px"] == pytest.approx(1.37, abs=0.05)
    assert doc["dy_px"] == pytest.approx(-2.61, abs=0.05)
    assert doc["dx_nm"] == pytest.approx(2 * doc["dx_px"])
    assert doc["dy_nm"] == pytest.approx(3 * doc["dy_px"])
    assert doc["pixel_size_nm"] == [2.0, 3.0]
    assert doc["valid_blocks"] >= 3


def test_large_shift_found_through_coarse_prealignment(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Regression: a 40 px drift is beyond the ±32 px block search of 64/128 blocks;
    the whole-image pre-alignment centres the search on it."""
    ref = _texture(seed=1)
    a = _save(tmp_path / "a.npy", ref)
    b = _save(tmp_path / "b.npy", _shifted(ref, -40.4, 12.2))
    assert main(["measure", a, b, "--pixel-size-nm", "1", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["prior_px"] == [-40.0, 12.0]
    assert doc["prior"].startswith("coarse")
    assert doc["dx_px"] == pytest.approx(-40.4, abs=0.05)
    assert doc["dy_px"] == pytest.approx(12.2, abs=0.05)


def test_text_output_and_plot(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    ref = _texture(seed=2)
    a = _save(tmp_path / "a.npy", ref)
    b = _save(tmp_path / "b.npy", _shifted(ref, 0.5, 0.25))
    png = tmp_path / "field.png"
    assert main(["measure", a, b, "--pixel-size-nm", "1.5", "--plot", str(png)]) == 0
    out = capsys.readouterr().out
    found = re.search(r"dx = ([-+][\d.]+) px, dy = ([-+][\d.]+) px", out)
    assert found is not None, out
    assert float(found.group(1)) == pytest.approx(0.5, abs=0.02)
    assert float(found.group(2)) == pytest.approx(0.25, abs=0.02)
    blocks = re.search(r"blocks +(\d+) of (\d+) valid", out)
    assert blocks is not None
    assert 3 <= int(blocks.group(1)) <= int(blocks.group(2))
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_stack_json_lines_increments_and_cumulative(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    base = _texture(seed=3)
    truth = np.array([[0.0, 0.0], [0.4, -0.3], [1.1, -0.2], [0.9, 0.7]])
    stack = np.stack([_shifted(base, dx, dy) for dx, dy in truth])
    path = _save(tmp_path / "stack.npy", stack)
    png = tmp_path / "track.png"
    assert main(["measure", path, "--pixel-size-nm", "2", "--plot", str(png)]) == 0
    lines = _json_lines(capsys.readouterr().out)
    # measured against the keyframe (frame 0), as the daemon does
    assert [(d["ref_frame"], d["cur_frame"]) for d in lines] == [(0, 1), (0, 2), (0, 3)]
    for k, d in enumerate(lines, start=1):
        step = truth[k] - truth[k - 1]
        assert d["valid"] is True
        assert d["dx_px"] == pytest.approx(step[0], abs=0.05)
        assert d["dy_px"] == pytest.approx(step[1], abs=0.05)
        assert d["cumulative_dx_px"] == pytest.approx(truth[k, 0], abs=0.08)
        assert d["cumulative_dy_px"] == pytest.approx(truth[k, 1], abs=0.08)
        assert d["cumulative_dx_nm"] == pytest.approx(2 * d["cumulative_dx_px"])
    assert png.is_file()


def test_stack_blank_frame_is_reported_and_skipped(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Regression: a blank frame must give an error entry, not a number, and the
    next frame is measured against the last good one so the track continues."""
    base = _texture(seed=4)
    stack = np.stack(
        [base, _shifted(base, 0.5, 0.0), np.full_like(base, 3.0), _shifted(base, 1.0, 0.5)]
    )
    path = _save(tmp_path / "stack.npy", stack)
    assert main(["measure", path, "--pixel-size-nm", "1"]) == 1
    lines = _json_lines(capsys.readouterr().out)
    assert lines[1]["cur_frame"] == 2
    assert lines[1]["valid"] is False
    assert "constant" in lines[1]["error"] or "texture" in lines[1]["error"]
    assert (lines[2]["ref_frame"], lines[2]["cur_frame"]) == (0, 3)
    assert lines[2]["cumulative_dx_px"] == pytest.approx(1.0, abs=0.08)
    assert lines[2]["cumulative_dy_px"] == pytest.approx(0.5, abs=0.08)


@pytest.mark.parametrize(
    ("make_args", "message"),
    [
        (lambda a, b, small, missing: [a, missing, "--pixel-size-nm", "1"], "no such file"),
        (lambda a, b, small, missing: [a, b], "pixel_size_nm"),
        (lambda a, b, small, missing: [small, small, "--pixel-size-nm", "1"], "too small"),
        (lambda a, b, small, missing: [a, small, "--pixel-size-nm", "1"], "shape"),
        (lambda a, b, small, missing: [small, "--pixel-size-nm", "1"], "holds one image"),
        (lambda a, b, small, missing: [f"{a}:0", "--pixel-size-nm", "1"], "one frame"),
        (
            lambda a, b, small, missing: [a, b, "--pixel-size-nm", "1", "--block-size", "4"],
            "block_size",
        ),
        (
            lambda a, b, small, missing: [a, b, "--pixel-size-nm", "1", "--search-px", "80"],
            "block_search_px",
        ),
        (
            lambda a, b, small, missing: [a, b, "--pixel-size-nm", "1", "--max-shift-px", "-3"],
            "max_shift_px",
        ),
        (lambda a, b, small, missing: [a, b, "--pixel-size-nm", "1", "2", "3"], "PX or PX PY"),
    ],
)
def test_bad_input_is_one_clear_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], make_args: object, message: str
) -> None:
    a = _save(tmp_path / "a.npy", _texture(seed=5))
    b = _save(tmp_path / "b.npy", _texture(seed=5))
    small = _save(tmp_path / "small.npy", _texture(seed=6, size=32))
    args = make_args(a, b, small, str(tmp_path / "missing.npy"))  # type: ignore[operator]
    assert main(["measure", *args]) == 2
    err = capsys.readouterr().err
    assert message in err
    assert "Traceback" not in err


def test_unrelated_images_are_not_a_confident_drift(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Two unrelated textures have no drift between them: the coarse peak is not
    trusted (z below the cut-off), the result is refused with a reason and no
    drift, and the command exits 1 (a result printed, but invalid)."""
    a = _save(tmp_path / "a.npy", _texture(seed=7))
    b = _save(tmp_path / "b.npy", _texture(seed=8))
    code = main(["measure", a, b, "--pixel-size-nm", "1", "--json"])
    doc = json.loads(capsys.readouterr().out)
    assert "not used" in doc["prior"]
    assert doc["valid"] is False
    assert doc["reason"], doc
    assert (doc["dx_px"], doc["dy_px"], doc["sigma_nm"]) == (None, None, None)
    assert code == 1
    # The same refusal without --json: said in words, same exit status.
    assert main(["measure", a, b, "--pixel-size-nm", "1"]) == 1
    assert f"INVALID    {doc['reason']}" in capsys.readouterr().out


def test_measurement_config_overrides() -> None:
    base = RegistrationConfig()
    assert measurement_config(base) == base
    small = measurement_config(base, block_size=32, extended_size=48)
    assert (small.block_size, small.extended_size, small.auto_block_size) == (32, 48, False)
    narrow = measurement_config(base, search_px=3.0)
    assert (narrow.block_search_px, narrow.coarse_search_px) == (3.0, 3.0)
    assert narrow.max_shift_px is None  # the bound on the drift is another thing
    with pytest.raises(ConfigError, match="extended_size"):
        measurement_config(base, block_size=64, extended_size=32)


@pytest.mark.parametrize("extra", [[], ["--prior-px", "-38", "10"], ["--no-coarse"]])
def test_cli_and_api_give_the_same_numbers_for_the_same_pair(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], extra: list[str]
) -> None:
    """Regression (issue 13): the CLI once chose its own prior and narrowed the
    windows differently from measure_drift, 0.9 px apart on the same pair. Both
    now go through one registration path."""
    ref, cur = _texture(seed=21), _shifted(_texture(seed=21), -40.4, 12.2)
    a, b = _save(tmp_path / "a.npy", ref), _save(tmp_path / "b.npy", cur)
    main(["measure", a, b, "--pixel-size-nm", "1", "--json", *extra])
    doc = json.loads(capsys.readouterr().out)
    prior = (-38.0, 10.0) if "--prior-px" in extra else None
    config = RegistrationConfig(coarse="--no-coarse" not in extra)
    api = measure_drift(ref, cur, pixel_size_nm=1.0, config=config, prior_px=prior)
    assert doc["valid"] == api.valid
    assert doc["prior"] == api.prior
    if api.valid:
        assert (doc["dx_px"], doc["dy_px"]) == (api.dx_px, api.dy_px)


def test_stack_trajectory_samples_and_dewarped_frames(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A stack goes through the daemon's position component: every valid
    frame carries its drift trajectory samples (each block row at its scan
    time), and --dewarp writes the frames moved back into one geometry.

    The stack drifts continuously while it is scanned, as a real one does: a
    .npy has no timing, so frames are taken as 1 s each, back to back, and
    row r of frame k is scanned at t = k + (r + 1/2) / rows."""
    base = _texture(seed=6)
    rows = base.shape[0]
    v = np.array([2.4, -1.3])  # px per frame (per second here)
    stack = np.empty((4, *base.shape))
    for k in range(4):
        for r in range(rows):
            dx, dy = v * (k + (r + 0.5) / rows)
            stack[k, r] = _shifted(base, dx, dy)[r]
    path = _save(tmp_path / "stack.npy", stack)
    out = tmp_path / "dewarped"
    assert main(["measure", path, "--pixel-size-nm", "2", "--dewarp", str(out)]) == 0
    lines = _json_lines(capsys.readouterr().out)
    assert len(lines) == 3
    for d in lines:
        samples = d["trajectory"]
        assert len(samples) >= 2
        t = np.array([s["t_s"] for s in samples])
        assert np.all(np.diff(t) > 0)
        want = 2.0 * v[None, :] * (t[:, None] - 0.5)  # p = 0 at frame 0's mid-scan
        got = np.array([[s["x_nm"], s["y_nm"]] for s in samples])
        np.testing.assert_allclose(got, want, atol=0.3)
    frames = np.load(out / "frames.npy")
    assert frames.shape == stack.shape
    inner = (slice(24, -24), slice(24, -24))
    for k in range(1, len(stack)):
        diff = frames[k][inner] - frames[0][inner]
        assert np.nanmax(np.abs(diff)) < 0.1 * np.ptp(base)


def test_stack_takes_a_prior_for_its_first_increment_and_refuses_dewarp_of_a_pair(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    stack = np.stack([_texture(seed=7)] * 3)
    path = _save(tmp_path / "stack.npy", stack)
    assert main(["measure", path, "--pixel-size-nm", "1", "--prior-px", "1", "1"]) == 0
    docs = _json_lines(capsys.readouterr().out)
    assert docs[0]["prior"] == "given"
    assert docs[0]["expected_px"] == [1.0, 1.0]
    assert docs[1]["prior"] == "predicted"
    assert all(d["decided_by"] == "content" for d in docs)
    one = _save(tmp_path / "one.npy", stack[0])
    assert main(["measure", one, one, "--pixel-size-nm", "1", "--dewarp", "d"]) == 2
    assert "--dewarp applies to a stack" in capsys.readouterr().err


def test_a_stated_bound_or_equivalence_decides_a_lattice_on_the_command_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A perfect lattice (period 11.5 px) shifted (3.4, −1.2) px: refused
    alone (exit 1); ``--max-shift-px 4.5`` decides it (decided_by: bound,
    exit 0); shifted (13.4, −9.2) px, ``--lattice equivalent`` registers it
    (decided_by: equivalent, said in words, exit 0)."""
    from afmdrift.testing import TextureShifter, lattice_texture

    tex = lattice_texture((320, 320), rng=np.random.default_rng(5), vacancy_fraction=0.0)
    shifter = TextureShifter(tex)
    a = _save(tmp_path / "a.npy", shifter.crop((224, 224)))
    b = _save(tmp_path / "b.npy", shifter.crop((224, 224), dx_px=3.4, dy_px=-1.2))
    far = _save(tmp_path / "far.npy", shifter.crop((224, 224), dx_px=13.4, dy_px=-9.2))
    assert main(["measure", a, b, "--pixel-size-nm", "1", "--json"]) == 1
    assert json.loads(capsys.readouterr().out)["reason"].startswith("ambiguous")
    assert main(["measure", a, b, "--pixel-size-nm", "1", "--max-shift-px", "4.5", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["decided_by"] == "bound"
    assert (doc["dx_px"], doc["dy_px"]) == pytest.approx((3.4, -1.2), abs=0.1)
    assert main(["measure", a, far, "--pixel-size-nm", "1", "--lattice", "equivalent"]) == 0
    out = capsys.readouterr()
    assert "decided as asked (--lattice equivalent)" in out.out
    assert "warning" not in out.err


@pytest.mark.parametrize(
    "command",
    [
        ["measure", "a.npy", "b.npy"],
        ["replay", "SESSION", "--out", "RUN"],
        ["correct", "SESSION", "--out", "DIR"],
        ["batch", "IN", "--out", "DIR"],
        ["diagnose", "SESSION"],
        ["evaluate", "SESSION"],
        ["run"],
    ],
)
def test_every_registering_command_takes_the_bound_and_the_lattice_mode(command: list[str]) -> None:
    """One pair of options, one function applying them (the same validation)."""
    from afmdrift.cli import build_parser
    from afmdrift.cli._options import registration_options
    from afmdrift.config import AfmdriftConfig

    args = build_parser().parse_args([*command, "--max-shift-px", "7", "--lattice", "equivalent"])
    cfg = registration_options(args, AfmdriftConfig())
    assert (cfg.registration.max_shift_px, cfg.registration.lattice) == (7.0, "equivalent")
    bad = build_parser().parse_args([*command, "--max-shift-px", "0"])
    with pytest.raises(ConfigError, match="max_shift_px"):
        registration_options(bad, AfmdriftConfig())
