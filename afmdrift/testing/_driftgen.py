"""A second drift-log generator, different on purpose from the simulator.

``afmdrift diagnose`` must hold its claims on data that afmdrift's own
simulator (:mod:`afmdrift.drivers.sim`) did not make. This generator writes
drift logs (``docs/session-format.md``, *Drift logs*) whose every part is
chosen apart from the simulator's:

* **Unlogged drift**: a random walk, a 1/f ("pink") process summed from
  first-order processes one octave apart, or an oscillating AR(2) process,
  0.5–2 nm, instead of the simulator's random walk only.
* **Logged channels**: temperature with a slow ramp, an air-conditioning
  cycle (20–40 min, a clipped sine) and AR(1) noise; humidity with a daily
  swing; barometric pressure as a random walk.
* **Effects, each its own shape**: a thermal response through a first-order
  lag (5–20 min); creep after offset moves as a stretched exponential
  ``1 − exp(−(t/τ)^β)``, β 0.3–0.6 (the library's is logarithmic); humidity
  through a 10 min lag; a scan-direction bias of 1–4 nm with direction
  changes in runs; a warm-up with two time constants (20–40 min and 2–3 h);
  and three outside the library: pressure, a heat pulse after each
  ``approach`` event (difference of exponentials), and a second, slow
  thermal path (1–2 h).
* **Shapes nothing logged drives** (:data:`DRIFTGEN_SHAPES`): a cycle (a sine
  or a thermostat's on/off), a slip (within a frame or over two) and a
  change of the drift rate, each added to a control.
* **Timing**: a frame every 240 s scanned in 120 s, 7.5 h.

Positions are the mean of the true drift over each frame's scan window (as
registration of a raster frame measures it), relative to frame 0, plus
measurement noise (σ 0.05–0.15 nm) and, with ``scan_direction``, the bias of
each frame's direction. ``answer.json`` says what the drift is made of, as in
``../shared/validation/drift-logs``. The controls (``none``) hold a trend
and an instant thermal response; nothing else drives them.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

__all__ = [
    "DRIFTGEN_EFFECTS",
    "DRIFTGEN_SHAPES",
    "GeneratedLog",
    "generate_drift_log",
    "write_drift_log",
]

FloatArray = npt.NDArray[np.float64]

#: Hidden effects the generator makes (``none``: a control).
DRIFTGEN_EFFECTS: tuple[str, ...] = (
    "none",
    "thermal_lag",
    "creep",
    "humidity",
    "scan_direction",
    "warmup",
    "pressure",
    "approach_heat",
    "thermal_two",
)

#: Hidden shapes of the drift that nothing logged drives, for what ``afmdrift
#: diagnose`` must find in the drift itself: a cycle (an air handler, 20-40
#: min, 2-5 nm: a sine, or a thermostat's on/off square wave through a 2 min
#: lag), a slip of 8-20 nm at an unknown time (within one frame's scan, or
#: spread over two frame periods), and a change of the drift rate by 20-60
#: nm/h (a door closed, a chiller switched).
DRIFTGEN_SHAPES: tuple[str, ...] = (
    "cycle",
    "thermostat",
    "slip",
    "slip_two_frames",
    "rate_change",
)

#: What should name each hidden effect: a library term, or the driver of one outside it.
_NAMED_BY: dict[str, str] = {
    "none": "",
    "thermal_lag": "thermal_lag",
    "creep": "creep",
    "humidity": "humidity",
    "scan_direction": "scan_direction",
    "warmup": "warmup",
    "pressure": "channel pressure_hpa",
    "approach_heat": "event approach",
    "thermal_two": "channel temperature_c (a second, slow thermal path)",
    "cycle": "discovered periodic",
    "thermostat": "discovered periodic",
    "slip": "discovered jump",
    "slip_two_frames": "discovered jump",
    "rate_change": "discovered rate_change",
}
_IN_LIBRARY = {"thermal_lag", "creep", "humidity", "scan_direction", "warmup"}

_CHANNEL_STEP_S = 10.0


@dataclass(frozen=True, slots=True)
class GeneratedLog:
    """A generated drift log, in memory (see :func:`write_drift_log`)."""

    effect: str
    seed: int
    frame_times: FloatArray  # (n, 2)
    directions: list[str]
    t_s: FloatArray  # (n,) mid-scan
    xy_nm: FloatArray  # (n, 2) measured positions
    sigma_nm: float
    channel_t_s: FloatArray
    channels: dict[str, FloatArray]
    events: list[tuple[float, str, float, float]]
    truth_t_s: FloatArray
    truth_nm: FloatArray  # (m, 2)
    answer: dict[str, Any]


def _first_order(x: FloatArray, dt: float, tau_s: float) -> FloatArray:
    """``x`` through a first-order lag of time constant ``tau_s`` (exact for steps)."""
    a = math.exp(-dt / tau_s)
    out = np.empty_like(x)
    out[0] = x[0]
    for k in range(1, x.size):
        out[k] = a * out[k - 1] + (1.0 - a) * x[k]
    return out


def _ar1(rng: np.random.Generator, n: int, dt: float, tau_s: float, sd: float) -> FloatArray:
    a = math.exp(-dt / tau_s)
    e = rng.normal(0.0, sd * math.sqrt(1.0 - a * a), size=n)
    out = np.empty(n)
    out[0] = rng.normal(0.0, sd)
    for k in range(1, n):
        out[k] = a * out[k - 1] + e[k]
    return out


def _unlogged(rng: np.random.Generator, t: FloatArray, kind: str, amp_nm: float) -> FloatArray:
    """Smooth drift no channel explains, (m, 2)."""
    dt = float(t[1] - t[0])
    out = np.zeros((t.size, 2))
    for axis in (0, 1):
        if kind == "walk":
            steps = rng.normal(0.0, 1.0, size=t.size) * math.sqrt(dt)
            x = np.cumsum(steps)
            x = _first_order(x, dt, 600.0)  # smooth at the frame scale
        elif kind == "pink":
            x = np.sum([_ar1(rng, t.size, dt, 300.0 * 2.0**j, 1.0) for j in range(6)], axis=0)
        else:  # "ar2": a damped oscillation of 1-2 h
            period = rng.uniform(3600.0, 7200.0)
            r = math.exp(-dt / 5400.0)
            c = 2.0 * r * math.cos(2.0 * math.pi * dt / period)
            e = rng.normal(0.0, 1.0, size=t.size)
            x = np.zeros(t.size)
            for k in range(2, t.size):
                x[k] = c * x[k - 1] - r * r * x[k - 2] + e[k]
            x = _first_order(x, dt, 300.0)
        x = x - x[0]
        scale = float(np.std(x)) or 1.0
        out[:, axis] = amp_nm * x / scale
    return out


def generate_drift_log(effect: str, seed: int, *, hours: float = 7.5) -> GeneratedLog:
    """Generate one drift log with hidden ``effect`` (one of :data:`DRIFTGEN_EFFECTS`).

    ``effect`` may also be one of :data:`DRIFTGEN_SHAPES`; ``answer.json``
    then gives the shape's period or time (``shape``).

    Raises
    ------
    ValueError
        ``effect`` is not one of :data:`DRIFTGEN_EFFECTS` or :data:`DRIFTGEN_SHAPES`.
    """
    known = DRIFTGEN_EFFECTS + DRIFTGEN_SHAPES
    if effect not in known:
        raise ValueError(f"effect must be one of {known}, got {effect!r}")
    rng = np.random.default_rng([seed, known.index(effect), 20261127])
    period_s, scan_s = 240.0, 120.0
    n = int(hours * 3600.0 / period_s)
    t_end = n * period_s
    t = np.arange(0.0, t_end + _CHANNEL_STEP_S, _CHANNEL_STEP_S)
    dt = _CHANNEL_STEP_S

    # --- logged channels
    hvac_period = rng.uniform(1200.0, 2400.0)
    hvac = np.clip(1.6 * np.sin(2 * np.pi * t / hvac_period + rng.uniform(0, 6.3)), -1, 1)
    temp = (
        rng.uniform(20.0, 23.0)
        + rng.uniform(-0.3, 0.3) * t / t_end
        + rng.uniform(0.05, 0.2) * hvac
        + _ar1(rng, t.size, dt, 900.0, 0.03)
    )
    humid = (
        rng.uniform(35.0, 55.0)
        + rng.uniform(2.0, 6.0) * np.sin(2 * np.pi * t / 86400.0 + rng.uniform(0, 6.3))
        + _ar1(rng, t.size, dt, 1800.0, 1.0)
    )
    press = rng.uniform(1000.0, 1025.0) + np.cumsum(rng.normal(0.0, 0.02, size=t.size))

    # --- events: manipulations (no drift), offset moves (pairs), approaches
    events: list[tuple[float, str, float, float]] = []
    for tm in np.sort(rng.uniform(600.0, t_end - 600.0, size=rng.integers(15, 30))):
        events.append((float(tm), "manipulation", *rng.uniform(0.0, 1000.0, size=2).tolist()))
    moves: list[tuple[float, FloatArray]] = []
    for tm in np.sort(rng.uniform(1800.0, t_end - 1800.0, size=rng.integers(4, 8))):
        d = rng.uniform(-5000.0, 5000.0, size=2)
        back = tm + rng.uniform(60.0, 100.0)
        events.append((float(tm), "offset_move", float(d[0]), float(d[1])))
        events.append((float(back), "offset_move", float(-d[0]), float(-d[1])))
        moves += [(float(tm), d), (float(back), -d)]
    approaches = np.sort(rng.uniform(1800.0, t_end - 3600.0, size=3))
    for tm in approaches:
        events.append((float(tm), "approach", 0.0, 0.0))
    if effect == "warmup":
        events.append((0.0, "power_on", 0.0, 0.0))
    events.sort()

    # --- the drift: trend + instant thermal + unlogged noise + the hidden effect
    t0_temp = float(temp[0])
    trend = rng.uniform(-2.0, 2.0, size=2) / 60.0  # nm/s
    k_thermal = rng.uniform(20.0, 80.0, size=2) * rng.choice([-1, 1], size=2)
    noise_kind = str(rng.choice(["walk", "pink", "ar2"]))
    drift = np.outer(t, trend) + np.outer(temp - t0_temp, k_thermal)
    drift += _unlogged(rng, t, noise_kind, rng.uniform(0.5, 2.0))
    hidden = np.zeros_like(drift)
    made_of = [
        "steady drift (linear in time)",
        "instant response to the logged temperature_c",
        f"smooth unlogged drift ({noise_kind})",
    ]
    if effect == "thermal_lag":
        tau = rng.uniform(300.0, 1200.0)
        k = rng.uniform(30.0, 90.0, size=2) * rng.choice([-1, 1], size=2)
        hidden = np.outer(_first_order(temp, dt, tau) - t0_temp, k)
        made_of.append(f"thermal response through a lag of {tau / 60:.0f} min")
    elif effect == "creep":
        tau = rng.uniform(120.0, 600.0)
        beta = rng.uniform(0.3, 0.6)
        frac = rng.uniform(0.002, 0.006)
        for tm, d in moves:
            after = np.clip(t - tm, 0.0, None)
            hidden += np.outer(1.0 - np.exp(-((after / tau) ** beta)), -frac * d)
        made_of.append(f"stretched-exponential creep after offset moves (beta {beta:.2f})")
    elif effect == "humidity":
        k = rng.uniform(0.5, 2.0, size=2) * rng.choice([-1, 1], size=2)
        hidden = np.outer(_first_order(humid, dt, 600.0) - humid[0], k)
        made_of.append("response to humidity_pct through a 10 min lag")
    elif effect == "warmup":
        a1 = rng.uniform(5.0, 20.0, size=2) * rng.choice([-1, 1], size=2)
        a2 = rng.uniform(5.0, 20.0, size=2) * rng.choice([-1, 1], size=2)
        tau1, tau2 = rng.uniform(1200.0, 2400.0), rng.uniform(7200.0, 10800.0)
        hidden = np.outer(1 - np.exp(-t / tau1), a1) + np.outer(1 - np.exp(-t / tau2), a2)
        made_of.append(f"warm-up after power_on, time constants {tau1 / 60:.0f} min and "
                       f"{tau2 / 3600:.1f} h")  # fmt: skip
    elif effect == "pressure":
        k = rng.uniform(3.0, 10.0, size=2) * rng.choice([-1, 1], size=2)
        hidden = np.outer(press - press[0], k)
        made_of.append("response to pressure_hpa")
    elif effect == "approach_heat":
        amp = rng.uniform(5.0, 15.0, size=2) * rng.choice([-1, 1], size=2)
        tau_r, tau_d = rng.uniform(120.0, 300.0), rng.uniform(1200.0, 2400.0)
        for tm in approaches:
            after = np.clip(t - tm, 0.0, None)
            pulse = np.where(t >= tm, np.exp(-after / tau_d) - np.exp(-after / tau_r), 0.0)
            hidden += np.outer(pulse, amp)
        made_of.append("a heat pulse after each approach event")
    elif effect == "thermal_two":
        tau = rng.uniform(3600.0, 7200.0)
        k = rng.uniform(30.0, 80.0, size=2) * rng.choice([-1, 1], size=2)
        hidden = np.outer(_first_order(temp, dt, tau) - t0_temp, k)
        made_of.append(f"a second thermal path with a lag of {tau / 3600:.1f} h")
    shape: dict[str, Any] = {}
    if effect in DRIFTGEN_SHAPES:
        hidden, shape = _hidden_shape(rng, effect, t, t_end, period_s)
        made_of.append(shape["what"])
    drift += hidden

    # --- frames and measured positions
    starts = period_s * np.arange(n)
    windows = np.column_stack([starts, starts + scan_s])
    mid = windows.mean(axis=1)
    if effect == "scan_direction":
        runs = np.repeat(rng.integers(0, 2, size=n // 3 + 1), 3)[:n]
        directions = ["up" if r else "down" for r in runs]
        bias = rng.uniform(1.0, 4.0, size=2) * rng.choice([-1, 1], size=2)
        made_of.append("a bias between up and down frames")
    else:
        directions = ["up"] * n
        bias = np.zeros(2)
    # A frame's position is the mean of p over the lines it scanned (64 line
    # samples per frame), as registration of a raster frame measures it.
    lines = windows[:, :1] + scan_s * (np.arange(64) + 0.5)[None, :] / 64.0
    truth_mid = np.column_stack([np.interp(lines, t, drift[:, a]).mean(axis=1) for a in (0, 1)])
    sign = np.array([0.5 if d == "up" else -0.5 for d in directions])
    sigma = float(rng.uniform(0.05, 0.15))
    measured = truth_mid - truth_mid[0] + np.outer(sign - sign[0], bias)
    measured += rng.normal(0.0, sigma, size=measured.shape)
    measured[0] = 0.0
    truth = drift - np.array([np.interp(mid[0], t, drift[:, a]) for a in (0, 1)])
    answer: dict[str, Any] = {
        "hidden_effect": effect,
        "named_by": _NAMED_BY[effect] or None,
        "in_afmdrift_library": effect in _IN_LIBRARY or effect == "none",
        "generator": "afmdrift.testing.generate_drift_log",
        "generator_seed": seed,
        "drift_made_of": made_of,
    }
    if shape:
        answer["shape"] = {k: v for k, v in shape.items() if k != "what"}
    return GeneratedLog(
        effect=effect,
        seed=seed,
        frame_times=windows,
        directions=directions,
        t_s=mid,
        xy_nm=measured,
        sigma_nm=sigma,
        channel_t_s=t,
        channels={"temperature_c": temp, "humidity_pct": humid, "pressure_hpa": press},
        events=events,
        truth_t_s=t,
        truth_nm=truth,
        answer=answer,
    )


def _hidden_shape(
    rng: np.random.Generator, effect: str, t: FloatArray, t_end: float, frame_s: float
) -> tuple[FloatArray, dict[str, Any]]:
    """The drift (m, 2) of one of :data:`DRIFTGEN_SHAPES` at ``t``, and what it is."""
    direction = rng.normal(size=2)
    direction /= float(np.hypot(*direction))
    if effect in ("cycle", "thermostat"):
        period = float(rng.uniform(1200.0, 2400.0))
        amp = float(rng.uniform(2.0, 5.0))
        phase = 2.0 * np.pi * t / period + rng.uniform(0.0, 2.0 * np.pi)
        if effect == "cycle":
            wave = np.sin(phase)
            what = f"an unlogged cycle of {period / 60:.0f} min, {amp:.1f} nm (a sine)"
        else:
            wave = _first_order(np.where(np.sin(phase) >= 0.0, 1.0, -1.0), t[1] - t[0], 120.0)
            what = f"an unlogged on/off cycle of {period / 60:.0f} min, {amp:.1f} nm"
        return np.outer(amp * wave, direction), {
            "kind": "periodic",
            "period_s": period,
            "amplitude_nm": amp,
            "what": what,
        }
    if effect in ("slip", "slip_two_frames"):
        size = float(rng.uniform(8.0, 20.0))
        t_j = float(rng.uniform(3600.0, t_end - 3600.0))
        spread = 2.0 * frame_s if effect == "slip_two_frames" else 30.0
        ramp = np.clip((t - t_j) / spread, 0.0, 1.0)
        return np.outer(size * ramp, direction), {
            "kind": "jump",
            "t_s": t_j + 0.5 * spread,
            "t_start_s": t_j,
            "t_end_s": t_j + spread,
            "step_nm": size,
            "what": f"an unlogged slip of {size:.0f} nm over {spread:.0f} s at {t_j:.0f} s",
        }
    rate = float(rng.uniform(20.0, 60.0))
    t_k = float(rng.uniform(5400.0, t_end - 5400.0))
    return np.outer(rate * np.maximum(t - t_k, 0.0) / 3600.0, direction), {
        "kind": "rate_change",
        "t_s": t_k,
        "rate_change_nm_per_h": rate,
        "what": f"an unlogged change of the drift rate by {rate:.0f} nm/h at {t_k:.0f} s",
    }


def write_drift_log(log: GeneratedLog, path: str | Path) -> Path:
    """Write ``log`` as a drift log folder (positions, frames, channels, events,
    truth and answer.json)."""
    root = Path(path)
    root.mkdir(parents=True, exist_ok=True)
    lines = ["frame,t_s,x_nm,y_nm,sigma_nm,direction"]
    lines += [
        f"{k},{_f(log.t_s[k])},{_f(log.xy_nm[k, 0])},{_f(log.xy_nm[k, 1])},{_f(log.sigma_nm)},"
        f"{log.directions[k]}"
        for k in range(log.t_s.size)
    ]
    (root / "positions.csv").write_text("\n".join(lines) + "\n", encoding="utf-8")
    lines = ["frame,t_start_s,t_end_s,direction"]
    lines += [
        f"{k},{_f(a)},{_f(b)},{log.directions[k]}" for k, (a, b) in enumerate(log.frame_times)
    ]
    (root / "frames.csv").write_text("\n".join(lines) + "\n", encoding="utf-8")
    names = list(log.channels)
    lines = ["t_s," + ",".join(names)]
    lines += [
        f"{_f(t)}," + ",".join(_f(log.channels[c][k]) for c in names)
        for k, t in enumerate(log.channel_t_s)
    ]
    (root / "channels.csv").write_text("\n".join(lines) + "\n", encoding="utf-8")
    lines = ["t_s,kind,x_nm,y_nm"] + [f"{_f(t)},{k},{_f(x)},{_f(y)}" for t, k, x, y in log.events]
    (root / "events.csv").write_text("\n".join(lines) + "\n", encoding="utf-8")
    lines = ["t_s,x_nm,y_nm"] + [
        f"{_f(t)},{_f(x)},{_f(y)}" for t, (x, y) in zip(log.truth_t_s, log.truth_nm, strict=True)
    ]
    (root / "truth.csv").write_text("\n".join(lines) + "\n", encoding="utf-8")
    (root / "answer.json").write_text(json.dumps(log.answer, indent=2) + "\n", encoding="utf-8")
    return root


def _f(value: float) -> str:
    return repr(float(value))
