"""``afmdrift measure``: drift between two image files, or along a stack or movie.

Two images: ``afmdrift measure REF CUR`` prints the drift of CUR relative to
REF (a feature at u in REF appears at u + d in CUR; x along columns, y along
rows), in px and nm, with its uncertainty and the valid block count. The
default ``--channel Height`` takes each file's height channel of whatever
name (``HeightRetrace``, ``ZSensor``, ``Z``, ``Topography``, ...); the channel
read is named on stderr when it is not the one asked for, and in the output
(``reference_channel``, ``current_channel``).

One stack or movie: ``afmdrift measure STACK`` streams the frames through
the daemon's position component (:class:`afmdrift.pipeline.DriftPositions`:
the keyframe policy of ``[registration] reference``, the drift trajectory with
each block row placed at its scan time) and prints one JSON object per frame
(JSON lines): the frame it was measured against, the increment since the
previous valid frame, the cumulative drift since frame 0 and the frame's
trajectory samples. A frame that cannot be registered (blank, too few valid
blocks) is reported with ``"valid": false`` and skipped; the next frame is
measured against the same reference, so one bad frame does not break the
track. ``--dewarp DIR`` also writes the frames with each row moved back by
the drift at its scan time.

A pair is measured by :func:`afmdrift.registration.measure_drift`, the
registration path the API and the daemon's tracker use (see
``docs/registration.md``, *One path, and no confident wrong answer*), so the
command and the API give the same numbers. Unless ``--no-coarse`` is given,
a whole-image alignment first finds the integer shift (wrap-around, lattice
translations and static structure handled); when it is trusted, the blocks
are measured within ``--search-px`` (default ``[registration]
coarse_search_px``, 6 px) around it, else around zero. ``--prior-px`` sets
the expected drift by hand (the block search is then the full
``(extended_size - block_size) / 2``, or ``--search-px``; on a periodic
sample, the lattice translation nearest it). The output says where the prior
came from (``prior_px``, ``prior``) and lists lattice translations the
images cannot tell apart (``lattice_px``); a pair whose translations tie
with no prior to decide is refused as ambiguous, naming them.
``--max-shift-px B`` states the largest drift possible (per axis): lattice
translations beyond it are excluded, so a bound under half a period decides,
and a result beyond it is refused. ``--lattice equivalent`` asks for the
frames registered rather than the drift tracked: among translations that fit
alike, the one nearest the prior (or zero) is taken.

A result is ``decided_by`` the content when no other shift fits the frames
as well; ``bound`` when lattice translations fit alike and only one lies
within ``--max-shift-px``; ``equivalent`` when they fit alike and
``--lattice equivalent`` took the nearest; and by the prior when they fit
alike and the expected drift alone picked the one nearest it: then its
``alternatives`` (with their distance from the prior) and ``ambiguity_px``
(the distance to the nearest) are printed, a warning goes to stderr and the
exit status is 3.

Exit status: 0 when every measurement is valid and decided by the content,
a stated bound or as asked (``equivalent``), 1 when one is invalid (the
result is still printed), 2 on an error (unreadable file, unusable image),
3 when all are valid but the prior alone decided one.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pydantic import ValidationError

from afmdrift.cli._import import add_file_options, pixel_size_option
from afmdrift.cli._options import (
    add_prior_option,
    add_registration_options,
    prior_option,
    registration_options,
)
from afmdrift.config import AfmdriftConfig, RegistrationConfig
from afmdrift.errors import ConfigError, InputError

if TYPE_CHECKING:
    from afmdrift.io import AfmImage
    from afmdrift.registration import DriftResult


def register(sub: Any) -> None:
    p = sub.add_parser(
        "measure",
        help="Measure drift between two AFM images, or along a stack or movie.",
        description="Measure the drift of CUR relative to REF by block phase correlation, "
        "or, with one STACK argument (an (N, rows, cols) .npy/.tif/.nc stack or an .asd "
        "movie), between successive frames (JSON lines with increment and cumulative "
        "drift). Files: .npy, .tif, NanoScope .spm/.000-.999, .gwy, .asd (FILE.asd:i "
        "selects frame i), .nc, .sxm, .ibw, .jpk, .h5-jpk, .stp. "
        "Exit 0: all valid; 1: some result invalid; 2: error; 3: valid, but the prior "
        "alone picked a shift among lattice translations (see decided_by).",
    )
    p.add_argument("ref", metavar="REF", help="reference image, or a stack/movie")
    p.add_argument("cur", metavar="CUR", nargs="?", help="current image")
    add_file_options(p)
    p.add_argument("--config", metavar="FILE", help="TOML config (default config/default.toml)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument(
        "--plot", metavar="PNG", help="draw the block vector field (or the stack's track)"
    )
    p.add_argument("--block-size", type=int, metavar="PX", help="override [registration]")
    p.add_argument("--extended-size", type=int, metavar="PX", help="override [registration]")
    add_prior_option(
        p,
        help="expected drift DX DY in px; the block search is centred on it (no coarse "
        "step, except on a periodic sample: the lattice translation nearest it is "
        "measured, and the result says decided_by: prior when the prior alone picked it); "
        "for a stack, the expected drift of the first frame after the first (later frames "
        "take the tracker's prediction)",
    )
    p.add_argument(
        "--search-px",
        type=float,
        metavar="R",
        help="half-width of the block search around the prior, px (sets coarse_search_px "
        "and block_search_px; default: 6 around the coarse alignment, "
        "(extended_size - block_size) / 2 around --prior-px)",
    )
    add_registration_options(p)
    p.add_argument(
        "--no-coarse",
        action="store_true",
        help="skip the whole-image integer pre-alignment (search around zero shift)",
    )
    p.add_argument(
        "--dewarp",
        metavar="DIR",
        help="stack or movie: also write its frames de-warped by the drift trajectory "
        "(DIR/frames.npy, NaN where a frame did not scan the first frame's area)",
    )
    p.set_defaults(handler=_run)


# --------------------------------------------------------------------------- handler


def _run(args: argparse.Namespace) -> int:
    from afmdrift.config import load_config
    from afmdrift.io import calibrated, load_image

    given = prior_option(args)
    if args.cur is None:
        return _run_stack(args, registration_options(args, load_config(args.config)))
    if args.dewarp:
        raise ConfigError("--dewarp applies to a stack or movie (one STACK argument)")
    config = measurement_config(
        registration_options(args, load_config(args.config).registration),
        block_size=args.block_size,
        extended_size=args.extended_size,
        search_px=args.search_px,
    )
    pixel = pixel_size_option(args.pixel_size_nm, override=args.override_pixel_size)
    coarse = not args.no_coarse

    def read_image(spec: str) -> AfmImage:
        image, note = calibrated(
            lambda px: load_image(
                spec, pixel_size_nm=px, channel=args.channel, height_unit=args.height_unit
            ),
            pixel,
            override=args.override_pixel_size,
            pixel_of=lambda im: im.pixel_size_nm,
        )
        if note is not None:
            print(f"afmdrift: {spec}: {note}", file=sys.stderr)
        return image

    ref = read_image(args.ref)
    cur = read_image(args.cur)
    report_channels([ref, cur], args.channel)
    result = measure_pair(ref, cur, config, prior_px=given, coarse=coarse)
    doc = {
        "reference": ref.source,
        "current": cur.source,
        "reference_channel": ref.channel,
        "current_channel": cur.channel,
        "pixel_size_nm": list(ref.pixel_size_nm),
        **result.to_dict(),
    }
    doc["given_prior_px"] = None if given is None else list(given)
    print(json.dumps(doc) if args.json else _describe(doc))
    if args.plot:
        _plot_field(ref, result, Path(args.plot))
    warn_if_prior_decided(result.to_dict(), what=f"{cur.source} against {ref.source}")
    return exit_status([result.to_dict()])


def warn_if_prior_decided(doc: dict[str, Any], *, what: str) -> None:
    """A warning on stderr when the prior alone picked ``doc``'s shift."""
    if doc.get("decided_by") != "prior":
        return
    print(
        f"afmdrift: warning: {what}: the prior alone picked this shift among "
        f"{len(doc['alternatives']) + 1} that fit the images alike (the nearest other is "
        f"{doc['ambiguity_px']:.1f} px away); it is right only if the prior is "
        "right to within half that",
        file=sys.stderr,
    )


def exit_status(docs: Sequence[dict[str, Any]]) -> int:
    """1 if any result is invalid, else 3 if the prior alone decided any, else 0."""
    if not all(d.get("valid") for d in docs):
        return 1
    return 3 if any(d.get("decided_by") == "prior" for d in docs) else 0


def measurement_config(
    base: RegistrationConfig,
    *,
    block_size: int | None = None,
    extended_size: int | None = None,
    search_px: float | None = None,
) -> RegistrationConfig:
    """``base`` with the command-line overrides applied and validated:
    ``--block-size``, ``--extended-size`` and ``--search-px``
    (``coarse_search_px``, the block search half-width around the coarse
    prior, and ``block_search_px``, that around a given prior). Explicit block
    sizes turn ``auto_block_size`` off.

    Raises
    ------
    ConfigError
        An override is out of range; the message names it and the range.
    """

    from afmdrift.config import RegistrationConfig, describe_validation_error

    overrides: dict[str, Any] = {
        k: v for k, v in (("block_size", block_size), ("extended_size", extended_size)) if v
    }
    if overrides:
        overrides["auto_block_size"] = False
    if search_px is not None:
        overrides["coarse_search_px"] = search_px
        overrides["block_search_px"] = search_px
    if not overrides:
        return base
    try:
        return RegistrationConfig.model_validate({**base.model_dump(), **overrides})
    except ValidationError as err:
        raise ConfigError(
            describe_validation_error(
                err, source="--block-size/--extended-size/--search-px", root=RegistrationConfig
            )
        ) from None


def measure_pair(
    ref: AfmImage,
    cur: AfmImage,
    config: RegistrationConfig,
    *,
    prior_px: tuple[float, float] | None = None,
    coarse: bool = True,
) -> DriftResult:
    """Drift of ``cur`` relative to ``ref`` as ``afmdrift measure`` computes it:
    :func:`afmdrift.registration.measure_drift` (the one registration path),
    with the files named in its errors.

    The block search is centred on ``prior_px`` if given, else on the coarse
    whole-image shift (:func:`afmdrift.registration.coarse_shift`) when
    ``coarse`` and it is trusted (:attr:`~afmdrift.registration.CoarseShift.trusted`),
    else on zero.

    Raises
    ------
    InputError
        Pixel sizes differ; or the engine's ``RegistrationError`` /
        ``InvalidFrameError`` (shapes differ, image too small, blank, NaN).
    """
    from afmdrift.registration import RegistrationError, measure_drift

    if not all(
        math.isclose(a, b, rel_tol=1e-6)
        for a, b in zip(ref.pixel_size_nm, cur.pixel_size_nm, strict=True)
    ):
        raise InputError(
            f"{cur.source}: pixel size {cur.pixel_size_nm} nm differs from {ref.source} "
            f"{ref.pixel_size_nm} nm (give --pixel-size-nm to override both)"
        )
    if not coarse and config.coarse:
        config = config.model_copy(update={"coarse": False})
    try:
        result = measure_drift(
            ref.heights_nm,
            cur.heights_nm,
            pixel_size_nm=ref.pixel_size_nm,
            config=config,
            prior_px=prior_px,
        )
    except RegistrationError as err:
        # Name the files: the engine only knows "reference" and "current".
        raise type(err)(f"reference {ref.source}, current {cur.source}: {err}") from None
    return result


def report_channels(images: Sequence[AfmImage], asked: str) -> None:
    """Say on stderr which channel was read where it is not the one asked for
    by name (the default ``Height`` takes each format's height channel:
    ``HeightRetrace``, ``ZSensor``, ``Z``, ``Topography``, ...; see
    :func:`afmdrift.io.pick_channel`)."""
    for img in images:
        if img.channel != asked:
            print(
                f"afmdrift: {img.source}: read channel {img.channel!r} for {asked!r}",
                file=sys.stderr,
            )


def _describe(doc: dict[str, Any]) -> str:
    def num(key: str, fmt: str = "+.3f") -> str:
        v = doc.get(key)
        return "n/a" if v is None else format(v, fmt)

    lines = [
        f"reference  {doc['reference']} (channel {doc['reference_channel']})",
        f"current    {doc['current']} (channel {doc['current_channel']})",
        f"drift      dx = {num('dx_px')} px, dy = {num('dy_px')} px",
        f"           dx = {num('dx_nm', '+.2f')} nm, dy = {num('dy_nm', '+.2f')} nm",
        f"sigma      x = {num('sigma_x_nm', '.2f')} nm, y = {num('sigma_y_nm', '.2f')} nm "
        f"(combined {num('sigma_nm', '.2f')} nm)",
        f"blocks     {doc['valid_blocks']} of {doc['total_blocks']} valid",
        "prior      "
        + (
            "none given"
            if doc.get("given_prior_px") is None
            else f"{doc['given_prior_px'][0]:+g}, {doc['given_prior_px'][1]:+g} px given"
        ),
        "search     "
        + (
            "around zero"
            if doc["prior_px"] is None
            else f"around {doc['prior_px'][0]:+g}, {doc['prior_px'][1]:+g} px"
        )
        + f" ({doc['prior']})",
    ]
    if doc.get("decided_by") == "prior":
        lines.append(
            f"DECIDED BY THE PRIOR: {len(doc['alternatives'])} other shifts fit as well, "
            f"the nearest {doc['ambiguity_px']:.1f} px away"
        )
    elif doc.get("decided_by") == "equivalent":
        lines.append(
            f"decided as asked (--lattice equivalent): {len(doc['alternatives'])} other "
            f"lattice translations fit as well, the nearest {doc['ambiguity_px']:.1f} px away; "
            "the frames are registered, the drift is not known"
        )
    elif doc.get("decided_by") == "bound":
        lines.append(
            f"decided by the bound: the only shift within --max-shift-px among "
            f"{len(doc['alternatives']) + 1} lattice translations that fit alike"
        )
    elif doc.get("decided_by"):
        lines.append(f"decided by {doc['decided_by']}")
    if not doc["valid"]:
        lines.append(f"INVALID    {doc['reason']}")
    return "\n".join(lines)


# --------------------------------------------------------------------------- stacks


def _run_stack(args: argparse.Namespace, base: AfmdriftConfig) -> int:
    """One STACK argument: track it through the daemon's position component."""
    from afmdrift.io import calibrated, load_stack, parse_spec

    if parse_spec(args.ref)[1] is not None:
        raise InputError(f"{args.ref}: one frame; give REF CUR, or the whole stack/movie")
    registration = measurement_config(
        base.registration,
        block_size=args.block_size,
        extended_size=args.extended_size,
        search_px=args.search_px,
    )
    if args.no_coarse:
        registration = registration.model_copy(update={"coarse": False})
    from afmdrift.runs import track_stack

    frames, note = calibrated(
        lambda px: load_stack(
            args.ref,
            pixel_size_nm=px,
            channel=args.channel,
            height_unit=args.height_unit,
            stream=True,
        ),
        pixel_size_option(args.pixel_size_nm, override=args.override_pixel_size),
        override=args.override_pixel_size,
        pixel_of=lambda stack: stack[0].pixel_size_nm,
    )
    if note is not None:
        print(f"afmdrift: {args.ref}: {note}", file=sys.stderr)
    report_channels(frames[:1], args.channel)
    if len(frames) < 2:
        raise InputError(f"{args.ref}: holds one image; give REF and CUR to measure a pair")
    docs: list[dict[str, Any]] = []
    track: list[tuple[int, float, float]] = [(0, 0.0, 0.0)]
    config = base.model_copy(update={"registration": registration})
    for doc in track_stack(
        frames,
        config,
        dewarp=Path(args.dewarp) if args.dewarp else None,
        prior_px=prior_option(args),
    ):
        print(json.dumps(doc), flush=True)
        docs.append({k: doc.get(k) for k in ("valid", "decided_by")})
        if doc["valid"]:
            track.append((doc["cur_frame"], doc["cumulative_dx_px"], doc["cumulative_dy_px"]))
        warn_if_prior_decided(doc, what=f"{args.ref} frame {doc['cur_frame']}")
    if args.plot:
        _plot_track(track, frames[0], Path(args.plot))
    return exit_status(docs)


# --------------------------------------------------------------------------- plots


def _plot_field(ref: AfmImage, result: DriftResult, path: Path) -> None:
    """Block vectors over the reference's x-gradient; rejected blocks marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    grad = np.diff(ref.heights_nm, axis=1)
    lo, hi = np.percentile(grad, [1, 99])
    f = result.field
    centres = np.asarray(f.centres_px, dtype=np.float64)
    vectors = np.asarray(f.vectors_px, dtype=np.float64)
    valid = np.asarray(f.valid, dtype=bool)
    measured = np.asarray(f.measured, dtype=bool)
    rejected = measured & ~valid
    lengths = np.hypot(*vectors[measured].T) if measured.any() else np.zeros(0)
    typical = float(np.median(lengths)) if lengths.size and np.median(lengths) > 0 else 1.0
    gain = max(1.0, 0.08 * min(ref.shape) / typical)
    fig, ax = plt.subplots(figsize=(7, 7))
    try:
        ax.imshow(grad, cmap="gray", origin="lower", vmin=lo, vmax=hi)
        for mask, colour, label in (
            (valid, "tab:green", "valid"),
            (rejected, "tab:red", "rejected"),
        ):
            if mask.any():
                ax.quiver(
                    centres[mask, 0],
                    centres[mask, 1],
                    vectors[mask, 0] * gain,
                    vectors[mask, 1] * gain,
                    color=colour,
                    angles="xy",
                    scale_units="xy",
                    scale=1.0,
                    width=0.004,
                    label=f"{label} ({int(mask.sum())})",
                )
        if rejected.any():
            ax.scatter(
                centres[rejected, 0], centres[rejected, 1], marker="x", color="tab:red", s=40
            )
        missing = ~measured
        if missing.any():
            ax.scatter(
                centres[missing, 0],
                centres[missing, 1],
                marker="o",
                facecolors="none",
                edgecolors="tab:orange",
                s=60,
                label=f"no peak ({int(missing.sum())})",
            )
        d = result.to_dict()
        title = (
            f"dx = {d['dx_px']:+.2f} px, dy = {d['dy_px']:+.2f} px, σ = {d['sigma_nm']:.2f} nm"
            if result.valid
            else f"invalid: {result.reason}"
        )
        ax.set_title(f"{title}\nvectors ×{gain:.3g}; x-gradient of {ref.path.name}", fontsize=9)
        ax.set_xlabel("x (px)")
        ax.set_ylabel("y (px)")
        ax.legend(loc="upper right", fontsize=8)
        fig.savefig(path, dpi=100)
    finally:
        plt.close(fig)


def _plot_track(track: list[tuple[int, float, float]], first: AfmImage, path: Path) -> None:
    """Cumulative drift of a stack (px) against frame index."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    idx = [t[0] for t in track]
    fig, ax = plt.subplots(figsize=(7, 4))
    try:
        ax.plot(idx, [t[1] for t in track], "o-", label="x")
        ax.plot(idx, [t[2] for t in track], "s-", label="y")
        ax.set_xlabel("frame")
        ax.set_ylabel("cumulative drift (px)")
        ax.set_title(f"{first.path.name}: drift since frame 0", fontsize=9)
        ax.legend()
        fig.savefig(path, dpi=100)
    finally:
        plt.close(fig)
