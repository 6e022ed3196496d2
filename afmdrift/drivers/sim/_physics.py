"""The drift physics of the simulated AFM: p(t) as a sum of documented effects.

Sign convention (the registration engine's): a feature at image position u at
time 0 appears at ``u + p(t)``. A commanded offset move of ``+Δ`` moves the scan
window by ``+Δ`` over the sample, so features appear at ``u − Δ``; commanded
moves are *not* drift and are not part of p(t). Their uncommanded side effects
(creep, hysteresis) are.

Effects (equations, magnitudes and sources in ``docs/physics.md``), each a
function of time since power-on ``t`` and each zero at ``t = 0``:

* thermal expansion ``p_th = α (T_s(t) − T_s(0))``, with the scanner temperature
  ``T_s`` lagging the head temperature ``T_h`` by a first-order time constant
  ``τ``: ``dT_s/dt = (T_h − T_s)/τ``;
* head (room) temperature ``T_h = T_0 + k t + AC(t) + OU(t)``: slow trend, an
  air-conditioning cycle (sine or triangle) and an Ornstein–Uhlenbeck
  fluctuation;
* warm-up ``p_w = A (1 − exp(−t/τ_w))``;
* logarithmic piezo creep after each commanded move ``Δ_m`` at ``t_m``:
  ``p_c = −γ Δ_m log10(1 + (t − t_m)/t_0)`` for ``t > t_m``;
* hysteresis of the commanded offset ``c``: a play operator of half-width ``r``
  gives the actual offset ``a = P_r[c]``; ``p_hy = −(a − c)``;
* humidity ``p_h = β (RH(t) − RH(0))`` with RH its own trend, slow sine and OU;
* tip changes: a step ``s_k`` at each tip change time ``t_k``;
* a Wiener process with ``σ`` nm/√s per axis;
* extra logged channels C (``[[physics.channels]]``: pressure, a stage
  thermometer, ...), each coupled through any number of paths
  ``p_ch = Σ_j g_j (C_j(t) − C_j(0))``, ``τ_j dC_j/dt = C − C_j`` (τ_j = 0:
  C_j = C), or through none (a distractor);
* logged events of any kind (``[[physics.events]]``), each followed by
  ``A_e (1 − exp(−(t − t_e)/τ))`` (``settle``) or ``A_e log10(1 + (t − t_e)/t_0)``
  (``log``), or by nothing.

The stochastic processes live on a regular grid of step ``dt_s``, generated in
fixed-size chunks from their own random streams, so a given seed gives the same
p(t) however the time axis is queried. Between grid points they are linearly
interpolated. The event-driven terms are evaluated exactly, creep through a
sum-of-exponentials state (error below 1e-7 of a decade; see ``_CreepModes``) so
that a query costs the same after one move or after a day of closed-loop moves.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.signal import lfilter

from afmdrift.drivers.sim._scenario import PhysicsConfig

__all__ = ["COMPONENTS", "DriftPhysics", "OffsetMove", "TipChange"]

#: Names of the drift components, in the order of ``truth_components.csv``.
COMPONENTS: tuple[str, ...] = (
    "thermal",
    "warmup",
    "creep",
    "hysteresis",
    "humidity",
    "tip_change",
    "random_walk",
    "channels",
    "events",
)

_CHUNK = 8192  # grid samples generated at a time (fixed, for determinism)

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class OffsetMove:
    """A commanded offset change at ``t_s`` to the absolute offset ``(x_nm, y_nm)``.

    ``dx_nm, dy_nm`` is the commanded step, ``ex_nm, ey_nm`` the hysteresis error
    ``a − c`` of the actual offset after the move.
    """

    t_s: float
    x_nm: float
    y_nm: float
    dx_nm: float
    dy_nm: float
    ex_nm: float
    ey_nm: float


@dataclass(frozen=True, slots=True)
class TipChange:
    """A tip change at ``t_s`` shifting the apparent position by ``(dx_nm, dy_nm)``."""

    t_s: float
    dx_nm: float
    dy_nm: float


class _StepTable:
    """A piecewise-constant (x, y) function of time, appended in time order.

    ``at(t)`` is the value set by the last entry with time <= t, or ``initial``.
    """

    def __init__(self, initial: tuple[float, float]) -> None:
        self.count = 0
        self.times = np.zeros(16)
        self.values = np.zeros((17, 2))  # row 0: the initial value
        self.values[0] = initial

    def append(self, t_s: float, x: float, y: float) -> None:
        k = self.count
        if k == self.times.size:
            self.times = np.resize(self.times, 2 * k)
            self.values = np.resize(self.values, (2 * k + 1, 2))
        self.times[k] = t_s
        self.values[k + 1] = (x, y)
        self.count = k + 1

    @property
    def last(self) -> FloatArray:
        out: FloatArray = self.values[self.count]
        return out

    def at(self, t_s: FloatArray) -> FloatArray:
        k = np.searchsorted(self.times[: self.count], t_s, side="right")
        out: FloatArray = self.values[k]
        return out


class _RampTable:
    """A piecewise-linear (x, y) displacement that stops at its limits.

    Segment ``k`` starts at ``t_k`` from ``q_k`` with velocity ``v_k`` and
    limits ``±L_k`` per axis: ``q(t) = clip(q_k + v_k (t − t_k), −L_k, L_k)``
    for ``t_k <= t < t_{k+1}``; zero before the first segment. Appended in
    time order.
    """

    def __init__(self) -> None:
        self.times: list[float] = []
        self.starts: list[tuple[float, float]] = []
        self.velocities: list[tuple[float, float]] = []
        self.limits: list[tuple[float, float]] = []

    def append(
        self,
        t_s: float,
        start: tuple[float, float],
        velocity: tuple[float, float],
        limit: tuple[float, float],
    ) -> None:
        if self.times and t_s < self.times[-1]:
            raise ValueError(f"compensation change at t={t_s} s is before the last one")
        self.times.append(float(t_s))
        self.starts.append(start)
        self.velocities.append(velocity)
        self.limits.append(limit)

    def at(self, t_s: FloatArray) -> FloatArray:
        out = np.zeros((*np.shape(t_s), 2))
        if not self.times:
            return out
        times = np.asarray(self.times)
        k = np.searchsorted(times, t_s, side="right") - 1
        ok = k >= 0
        kk = np.where(ok, k, 0)
        q0 = np.asarray(self.starts)[kk]
        v = np.asarray(self.velocities)[kk]
        lim = np.asarray(self.limits)[kk]
        q = np.clip(q0 + v * (np.asarray(t_s) - times[kk])[..., None], -lim, lim)
        out[ok] = q[ok]
        return out


class _CreepModes:
    """Sum-of-exponentials state of the logarithmic creep of many moves.

    Modes ``s_i = e^{u_i}`` on a grid of step ``h = 0.5`` in ``u = ln s`` from
    ``1e-8 / τ_max`` (``τ_max = 1e8`` s, about three years) to ``40 / t_0``,
    weights ``w_i = h e^{−t_0 s_i}``. The approximation of ``ln(1 + τ/t_0)``
    is better than 1e-7 (absolute) for 0 ≤ τ ≤ τ_max.
    """

    def __init__(self, t0_s: float) -> None:
        u = np.arange(math.log(1e-8 / 1e8), math.log(40.0 / t0_s), 0.5)
        self.s = np.exp(u)
        self.w = 0.5 * np.exp(-t0_s * self.s)
        self.count = 0
        self.times = np.zeros(16)
        self.total = np.zeros((16, 2))
        self.state = np.zeros((16, self.s.size, 2))

    def add(self, t_s: float, dx_nm: float, dy_nm: float) -> None:
        k = self.count
        if k == self.times.size:
            self.times = np.resize(self.times, 2 * k)
            self.total = np.resize(self.total, (2 * k, 2))
            self.state = np.resize(self.state, (2 * k, self.s.size, 2))
        step = np.array([dx_nm, dy_nm])
        if k == 0:
            self.total[0] = step
            self.state[0] = step[None, :]
        else:
            decay = np.exp(-(t_s - self.times[k - 1]) * self.s)
            self.total[k] = self.total[k - 1] + step
            self.state[k] = self.state[k - 1] * decay[:, None] + step[None, :]
        self.times[k] = t_s
        self.count = k + 1


class _Grid:
    """Growable regular-grid store of the stochastic processes."""

    def __init__(self, dt_s: float, names: tuple[str, ...]) -> None:
        self.dt_s = dt_s
        self.n = 0
        self.data: dict[str, FloatArray] = {k: np.zeros(0) for k in names}

    def append(self, chunk: dict[str, FloatArray]) -> None:
        m = len(next(iter(chunk.values())))
        for k, v in chunk.items():
            arr = self.data[k]
            if self.n + m > arr.size:
                grown = np.zeros(max(2 * arr.size, self.n + m))
                grown[: self.n] = arr[: self.n]
                self.data[k] = arr = grown
            arr[self.n : self.n + m] = v
        self.n += m

    def at(self, name: str, t_s: FloatArray) -> FloatArray:
        """Linear interpolation of ``name`` at times ``t_s`` (must lie on the grid)."""
        x = t_s / self.dt_s
        k = np.clip(np.floor(x).astype(np.int64), 0, self.n - 2)
        f = x - k
        v = self.data[name]
        out: FloatArray = v[k] + (v[k + 1] - v[k]) * f
        return out


def total_drift(components: dict[str, FloatArray]) -> FloatArray:
    """p(t), the sum of the drift components (each of shape (..., 2), nm)."""
    values = iter(components.values())
    total = np.array(next(values), dtype=np.float64)
    for v in values:
        total += v
    return total


class DriftPhysics:
    """Ground-truth drift p(t), the sensors' true values, and the offset actuator.

    Parameters
    ----------
    config : PhysicsConfig
        The ``[physics]`` table of a scenario.
    seed : int
        Seed of every random stream (the same seed gives the same p(t)).
    start_offset_nm : (float, float)
        Commanded XY offset at power-on.
    """

    def __init__(
        self, config: PhysicsConfig, *, seed: int, start_offset_nm: tuple[float, float] = (0, 0)
    ) -> None:
        self.config = config
        self._dt = float(config.dt_s)
        ss = np.random.SeedSequence([int(seed), 0x5EED])
        room_ss, rh_ss, rw_ss = ss.spawn(3)
        self._rng_room = np.random.default_rng(room_ss)
        self._rng_rh = np.random.default_rng(rh_ss)
        self._rng_rw = np.random.default_rng(rw_ss)
        # Extra channels and event amplitudes draw from their own streams, so a
        # scenario without them gives the same p(t) as before they existed.
        ext_ss = np.random.SeedSequence([int(seed), 0xC4A7]).spawn(len(config.channels) + 1)
        self._rng_ch = [np.random.default_rng(s) for s in ext_ss[:-1]]
        rng_ev = np.random.default_rng(ext_ss[-1])
        self._event_scale = [
            1.0 + ev.amplitude_spread * float(rng_ev.normal()) for ev in config.events
        ]
        names = ["t_head", "t_scanner", "rh", "rw_x", "rw_y"]
        for i, ch in enumerate(config.channels):
            names += [f"ch{i}", f"ch{i}_room"] + [f"ch{i}_p{j}" for j in range(len(ch.paths))]
        self._grid = _Grid(self._dt, tuple(names))
        self._ch_state: list[dict[str, float]] = []
        self._ou_room = 0.0
        self._ou_rh = 0.0
        self._rw = np.zeros(2)
        self._t_scanner = 0.0
        self._t_head_prev = 0.0
        # First samples of each random stream set the state at t = 0.
        r = self.config.room
        if r.fluctuation_k > 0:
            self._ou_room = float(self._rng_room.normal(0.0, r.fluctuation_k))
        h = self.config.humidity
        if h.fluctuation_pct > 0:
            self._ou_rh = float(self._rng_rh.normal(0.0, h.fluctuation_pct))
        self._moves: list[OffsetMove] = []
        self._commanded = _StepTable((float(start_offset_nm[0]), float(start_offset_nm[1])))
        self._hyst = _StepTable((0.0, 0.0))  # drift term −(a − c) after each move
        self._tip_table = _StepTable((0.0, 0.0))  # cumulative tip-change steps
        self._creep_modes = _CreepModes(config.creep.t0_s)
        self._start_offset = (float(start_offset_nm[0]), float(start_offset_nm[1]))
        self._play = np.array(self._start_offset, dtype=np.float64)  # play-operator output
        self._tips: list[TipChange] = []
        self._comp = _RampTable()  # drift compensation: the piezo ramped at a velocity
        self._generate_first()
        self._t_scanner_0 = float(self._grid.data["t_scanner"][0])
        self._rh_0 = float(self._grid.data["rh"][0])

    # ------------------------------------------------------------------ grid processes

    def _head_deterministic(self, t: FloatArray) -> FloatArray:
        r = self.config.room
        phase = t / r.ac_period_s
        if r.ac_shape == "sine":
            ac = np.sin(2.0 * np.pi * phase)
        else:  # triangle wave with the sine's phase: 0 -> +1 -> 0 -> -1 -> 0
            ac = 2.0 / np.pi * np.arcsin(np.sin(2.0 * np.pi * phase))
        out: FloatArray = r.mean_c + r.trend_k_per_h * t / 3600.0 + r.ac_amplitude_k * ac
        return out

    def _rh_deterministic(self, t: FloatArray) -> FloatArray:
        h = self.config.humidity
        out: FloatArray = (
            h.mean_pct
            + h.trend_pct_per_h * t / 3600.0
            + h.amplitude_pct * np.sin(2.0 * np.pi * t / h.period_s)
        )
        return out

    def _ou(
        self, rng: np.random.Generator, x0: float, std: float, tau_s: float, n: int
    ) -> FloatArray:
        """Exact AR(1) discretisation of an Ornstein–Uhlenbeck process; x0 is the last value."""
        if std <= 0:
            return np.zeros(n)
        phi = math.exp(-self._dt / tau_s)
        eps = rng.normal(0.0, std * math.sqrt(1.0 - phi * phi), n)
        out, _ = lfilter([1.0], [1.0, -phi], eps, zi=[phi * x0])
        return np.asarray(out, dtype=np.float64)

    def _lag(self, u_prev: float, y_prev: float, u: FloatArray, tau: float) -> FloatArray:
        """Exact first-order lag y' = (u − y)/τ for u linear between grid points."""
        a = math.exp(-self._dt / tau)
        u0 = np.concatenate([[u_prev], u[:-1]])
        m_tau = (u - u0) / self._dt * tau
        b = u - m_tau - a * (u0 - m_tau)
        out, _ = lfilter([1.0], [1.0, -a], b, zi=[a * y_prev])
        return np.asarray(out, dtype=np.float64)

    def _generate_first(self) -> None:
        t0 = np.zeros(1)
        head0 = float(self._head_deterministic(t0)[0] + self._ou_room)
        self._t_scanner = head0 + self.config.thermal.initial_offset_k
        self._t_head_prev = head0
        rh0 = float(np.clip(self._rh_deterministic(t0)[0] + self._ou_rh, 0.0, 100.0))
        self._head_first = head0
        self._grid.append(
            {
                "t_head": np.array([head0]),
                "t_scanner": np.array([self._t_scanner]),
                "rh": np.array([rh0]),
                "rw_x": np.zeros(1),
                "rw_y": np.zeros(1),
                **self._channels_first(head0),
            }
        )

    def _generate_chunk(self) -> None:
        n0 = self._grid.n
        t = (n0 + np.arange(_CHUNK, dtype=np.float64)) * self._dt
        r = self.config.room
        ou_room = self._ou(
            self._rng_room, self._ou_room, r.fluctuation_k, r.fluctuation_tau_s, _CHUNK
        )
        if ou_room.size:
            self._ou_room = float(ou_room[-1])
        head = self._head_deterministic(t) + ou_room
        scanner = self._lag(self._t_head_prev, self._t_scanner, head, self.config.thermal.tau_s)
        extra = self._channels_chunk(t, head)
        self._t_head_prev = float(head[-1])
        self._t_scanner = float(scanner[-1])
        h = self.config.humidity
        ou_rh = self._ou(self._rng_rh, self._ou_rh, h.fluctuation_pct, h.fluctuation_tau_s, _CHUNK)
        if ou_rh.size:
            self._ou_rh = float(ou_rh[-1])
        rh = np.clip(self._rh_deterministic(t) + ou_rh, 0.0, 100.0)  # a relative humidity
        sigma = np.asarray(self.config.random_walk.sigma_nm_per_sqrt_s, dtype=np.float64)
        steps = self._rng_rw.normal(0.0, 1.0, (_CHUNK, 2)) * sigma * math.sqrt(self._dt)
        rw = self._rw + np.cumsum(steps, axis=0)
        self._rw = rw[-1].copy()
        self._grid.append(
            {
                "t_head": head,
                "t_scanner": scanner,
                "rh": rh,
                "rw_x": rw[:, 0],
                "rw_y": rw[:, 1],
                **extra,
            }
        )

    def _channel_own(self, i: int, t: FloatArray) -> FloatArray:
        c = self.config.channels[i]
        out: FloatArray = (
            c.mean
            + c.trend_per_h * t / 3600.0
            + c.amplitude * np.sin(2.0 * np.pi * t / c.period_s + c.phase_rad)
        )
        return out

    def _channels_first(self, head0: float) -> dict[str, FloatArray]:
        """Grid values of the extra channels and their path states at t = 0."""
        out: dict[str, FloatArray] = {}
        for i, c in enumerate(self.config.channels):
            ou0 = float(self._rng_ch[i].normal(0.0, c.fluctuation)) if c.fluctuation > 0 else 0.0
            value = float(self._channel_own(i, np.zeros(1))[0]) + ou0
            self._ch_state.append({"ou": ou0, "room": head0, "value": value})
            out[f"ch{i}"] = np.array([value])
            out[f"ch{i}_room"] = np.array([head0])
            for j in range(len(c.paths)):
                self._ch_state[i][f"p{j}"] = value
                out[f"ch{i}_p{j}"] = np.array([value])
        return out

    def _channels_chunk(self, t: FloatArray, head: FloatArray) -> dict[str, FloatArray]:
        """Grid values of the extra channels (true values) and their path states."""
        out: dict[str, FloatArray] = {}
        for i, c in enumerate(self.config.channels):
            st = self._ch_state[i]
            ou = self._ou(self._rng_ch[i], st["ou"], c.fluctuation, c.fluctuation_tau_s, t.size)
            if c.fluctuation > 0:
                st["ou"] = float(ou[-1])
            room = (
                self._lag(self._t_head_prev, st["room"], head, c.room_lag_s)
                if c.room_lag_s > 0
                else head
            )
            st["room"] = float(room[-1])
            value = self._channel_own(i, t) + ou + c.room_gain * (room - self._head_first)
            out[f"ch{i}"] = value
            out[f"ch{i}_room"] = room
            for j, path in enumerate(c.paths):
                key = f"p{j}"
                lagged = (
                    self._lag(st["value"], st[key], value, path.tau_s) if path.tau_s > 0 else value
                )
                st[key] = float(lagged[-1])
                out[f"ch{i}_{key}"] = lagged
            st["value"] = float(value[-1])
        return out

    def _ensure(self, t_max_s: float) -> None:
        while (self._grid.n - 1) * self._dt < t_max_s:
            self._generate_chunk()

    def _times(self, t_s: npt.ArrayLike) -> FloatArray:
        t = np.maximum(np.asarray(t_s, dtype=np.float64), 0.0)
        if t.size:
            self._ensure(float(t.max()))
        return t

    # ------------------------------------------------------------------ sensors (true values)

    def head_temperature_c(self, t_s: npt.ArrayLike) -> FloatArray:
        """Head (room air) temperature T_h at ``t_s``, °C; what the sensor reads."""
        return self._grid.at("t_head", self._times(t_s))

    def scanner_temperature_c(self, t_s: npt.ArrayLike) -> FloatArray:
        """Scanner temperature T_s (first-order lag of T_h), °C; not measured."""
        return self._grid.at("t_scanner", self._times(t_s))

    def humidity_pct(self, t_s: npt.ArrayLike) -> FloatArray:
        """Relative humidity at ``t_s``, %."""
        return self._grid.at("rh", self._times(t_s))

    def channel_values(self, t_s: npt.ArrayLike) -> dict[str, FloatArray]:
        """True values of the extra channels (``[[physics.channels]]``) at ``t_s``, by name."""
        t = self._times(t_s)
        return {c.name: self._grid.at(f"ch{i}", t) for i, c in enumerate(self.config.channels)}

    # ------------------------------------------------------------------ actuator and events

    def command_offset(self, t_s: float, x_nm: float, y_nm: float) -> OffsetMove:
        """Record a commanded absolute offset at ``t_s`` (time order); return the move."""
        if self._moves and t_s < self._moves[-1].t_s:
            raise ValueError(f"offset move at t={t_s} s is before the last one")
        cx, cy = self._commanded.last
        c = np.array([x_nm, y_nm], dtype=np.float64)
        if self.config.hysteresis.enabled:
            r = np.asarray(self.config.hysteresis.play_nm, dtype=np.float64)
            self._play = np.maximum(c - r, np.minimum(c + r, self._play))
        else:
            self._play = c.copy()
        e = self._play - c
        move = OffsetMove(
            t_s=float(t_s),
            x_nm=float(x_nm),
            y_nm=float(y_nm),
            dx_nm=float(x_nm - cx),
            dy_nm=float(y_nm - cy),
            ex_nm=float(e[0]),
            ey_nm=float(e[1]),
        )
        self._moves.append(move)
        self._commanded.append(move.t_s, move.x_nm, move.y_nm)
        self._hyst.append(move.t_s, -move.ex_nm, -move.ey_nm)
        if move.dx_nm or move.dy_nm:
            self._creep_modes.add(move.t_s, move.dx_nm, move.dy_nm)
        return move

    def add_tip_change(self, t_s: float, dx_nm: float, dy_nm: float) -> TipChange:
        """Record a tip change at ``t_s`` with its step in apparent position."""
        change = TipChange(float(t_s), float(dx_nm), float(dy_nm))
        self._tips.append(change)
        total = self._tip_table.last + np.array([change.dx_nm, change.dy_nm])
        self._tip_table.append(change.t_s, float(total[0]), float(total[1]))
        return change

    @property
    def moves(self) -> list[OffsetMove]:
        return list(self._moves)

    def commanded_offset_at(self, t_s: npt.ArrayLike) -> FloatArray:
        """Commanded XY offset (piecewise constant), shape (..., 2), nm."""
        t = np.asarray(t_s, dtype=np.float64)
        return self._commanded.at(t)

    def ramp_compensation(
        self,
        t_s: float,
        velocity_nm_per_s: tuple[float, float],
        limit_nm: tuple[float, float],
        *,
        release: bool = False,
    ) -> FloatArray:
        """From ``t_s`` on, ramp the compensation displacement at ``velocity_nm_per_s``.

        The displacement ``q`` adds to the commanded offset (it moves the scan
        window like an offset move, without creep or hysteresis) and stops at
        ``±limit_nm`` per axis. ``release`` first returns it to zero (the
        compensation switched off). Returns ``q(t_s)`` before the change.
        """
        q = self.compensation_at(float(t_s))
        start = (0.0, 0.0) if release else (float(q[0]), float(q[1]))
        velocity = (float(velocity_nm_per_s[0]), float(velocity_nm_per_s[1]))
        self._comp.append(float(t_s), start, velocity, (float(limit_nm[0]), float(limit_nm[1])))
        return q

    def compensation_at(self, t_s: npt.ArrayLike) -> FloatArray:
        """Drift-compensation displacement of the scan window, shape (..., 2), nm."""
        return self._comp.at(np.asarray(t_s, dtype=np.float64))

    def scan_offset_at(self, t_s: npt.ArrayLike) -> FloatArray:
        """Where the actuator puts the scan window: commanded offset plus compensation, nm."""
        return self.commanded_offset_at(t_s) + self.compensation_at(t_s)

    # ------------------------------------------------------------------ drift components

    def components_at(self, t_s: npt.ArrayLike) -> dict[str, FloatArray]:
        """Every drift component at ``t_s``, each of shape (..., 2) in nm."""
        t = self._times(t_s)
        cfg = self.config
        zero = np.zeros((*t.shape, 2))
        out: dict[str, FloatArray] = {}
        if cfg.thermal.enabled:
            dts = self._grid.at("t_scanner", t) - self._t_scanner_0
            out["thermal"] = dts[..., None] * np.asarray(cfg.thermal.alpha_nm_per_k)
        else:
            out["thermal"] = zero
        if cfg.warmup.enabled:
            w = -np.expm1(-t / cfg.warmup.tau_s)
            out["warmup"] = w[..., None] * np.asarray(cfg.warmup.amplitude_nm)
        else:
            out["warmup"] = zero
        out["creep"] = self._creep(t) if cfg.creep.enabled else zero
        out["hysteresis"] = self._hysteresis(t) if cfg.hysteresis.enabled else zero
        if cfg.humidity.enabled:
            drh = self._grid.at("rh", t) - self._rh_0
            out["humidity"] = drh[..., None] * np.asarray(cfg.humidity.beta_nm_per_pct)
        else:
            out["humidity"] = zero
        out["tip_change"] = self._tip_steps(t)
        if cfg.random_walk.enabled:
            out["random_walk"] = np.stack(
                [self._grid.at("rw_x", t), self._grid.at("rw_y", t)], axis=-1
            )
        else:
            out["random_walk"] = zero
        out["channels"] = self._channel_drift(t)
        out["events"] = self._event_drift(t)
        return out

    def _channel_drift(self, t: FloatArray) -> FloatArray:
        """Σ over extra channels and their paths of g_j (C_j(t) − C_j(0)), nm."""
        out = np.zeros((*t.shape, 2))
        for i, c in enumerate(self.config.channels):
            for j, path in enumerate(c.paths):
                v = self._grid.at(f"ch{i}_p{j}", t) - self._grid.data[f"ch{i}_p{j}"][0]
                out += v[..., None] * np.asarray(path.gain_nm_per_unit)
        return out

    def _event_drift(self, t: FloatArray) -> FloatArray:
        """Σ over logged events of their settling or creep response, nm."""
        out = np.zeros((*t.shape, 2))
        for ev, scale in zip(self.config.events, self._event_scale, strict=True):
            if ev.shape == "none":
                continue
            dt = np.maximum(t - ev.t_s, 0.0)
            r = -np.expm1(-dt / ev.tau_s) if ev.shape == "settle" else np.log10(1.0 + dt / ev.t0_s)
            out += (scale * r)[..., None] * np.asarray(ev.amplitude_nm)
        return out

    def drift_at(self, t_s: npt.ArrayLike) -> FloatArray:
        """True drift p(t), shape (..., 2) in nm (sum of :meth:`components_at`)."""
        return total_drift(self.components_at(t_s))

    def z_offset_nm(self, t_s: npt.ArrayLike, *, rate_nm_per_s: float) -> FloatArray:
        """Slow height offset: ``rate · t + α_z (T_s − T_s(0))``, nm."""
        t = self._times(t_s)
        z: FloatArray = rate_nm_per_s * t
        if self.config.thermal.enabled and self.config.thermal.z_alpha_nm_per_k:
            z = z + self.config.thermal.z_alpha_nm_per_k * (
                self._grid.at("t_scanner", t) - self._t_scanner_0
            )
        return z

    def _creep(self, t: FloatArray) -> FloatArray:
        """Σ_m −γ Δ_m log10(1 + (t − t_m)/t_0), in O(modes) per time whatever the moves.

        ``ln(1 + τ/t_0) = ∫_0^∞ e^{−t_0 s} (1 − e^{−τ s}) ds/s`` (a Frullani
        integral), discretised by the trapezoidal rule in ``ln s``:
        ``≈ Σ_i w_i (1 − e^{−τ s_i})`` (see :class:`_CreepModes`). So the creep of
        all moves up to move k is carried by ``D_k = Σ Δ_m`` and the per-mode
        states ``S_k,i = Σ Δ_m e^{−(t_k − t_m) s_i}``; a closed-loop controller
        that moves the offset every second for days costs the same per query
        as a single move.
        """
        out = np.zeros((*t.shape, 2))
        modes = self._creep_modes
        if modes.count == 0:
            return out
        flat_t = t.reshape(-1)
        flat = out.reshape(-1, 2)
        scale = -self.config.creep.gamma_per_decade / math.log(10.0)
        times = modes.times[: modes.count]
        for lo in range(0, flat_t.size, 4096):
            tt = flat_t[lo : lo + 4096]
            k = np.searchsorted(times, tt, side="right") - 1
            ok = k >= 0
            if not ok.any():
                continue
            kk = k[ok]
            decay = np.exp(-(tt[ok] - times[kk])[:, None] * modes.s[None, :])
            # Σ_m Δ_m (1 − e^{−τ_m s_i}) per mode; exactly 0 at the instant of a move.
            rest = modes.total[kk][:, None, :] - modes.state[kk] * decay[:, :, None]
            flat[lo : lo + 4096][ok] = scale * np.einsum("i,nia->na", modes.w, rest)
        return out

    def _hysteresis(self, t: FloatArray) -> FloatArray:
        return self._hyst.at(t)

    def _tip_steps(self, t: FloatArray) -> FloatArray:
        return self._tip_table.at(t)
