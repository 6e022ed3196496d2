"""The second physics of the simulated AFM: a heat network, a thermostat, a wander.

Built to differ on purpose from :class:`~afmdrift.drivers.sim._physics.DriftPhysics`
(the sum of effects), so that a closed loop tuned on one is also measured on
another. Same sign convention: a feature at image position u at time 0 appears
at ``u + p(t)``; a commanded offset move of ``+Δ`` moves the window by ``+Δ``
over the sample, so features appear at ``u − Δ``, and the move is not drift.
Here a move has no side effect at all (no creep, no hysteresis).

Equations (magnitudes and reasons in ``docs/physics.md``, "The second physics"),
with ``t`` the time since power-on and ``u = T_a − T_set`` the room air:

* thermostat: ``u`` piecewise linear inside ``[−h, +h]``, rising at ``r_h``
  while the heater is on and falling at ``r_c`` while it is off, from ``u = 0``
  rising;
* heat network: stage ``τ_1 dT_st/dt = T_a − T_st``, scanner
  ``τ_2 dT_sc/dt = T_st − T_sc``, each lagging the node before it; solved in
  closed form on each linear piece of ``u`` (:meth:`HeatNetworkPhysics._nodes`);
* thermal drift, an instant part and two lagged parts with their own
  couplings per axis: ``K_a ΔT_a + K_st ΔT_st + K_sc ΔT_sc`` (``Δ``: since
  power-on);
* warm-up, algebraic rather than exponential: ``A t / (t + τ_w)``;
* wander, logged by nothing: per axis ``Σ_k a_k (sin(ω_k t + φ_k) − sin φ_k)``
  with random phases, periods log-spaced and jittered, ``a_k ∝ 1/ω_k``;
* cross-coupling of the axes: the sum of the above goes through
  ``[[1, k_xy], [k_yx, 1]]``;
* tip changes: steps, as in ``DriftPhysics``.

The logged humidity follows the air, ``RH = RH_0 + g u`` (a distractor that
moves nothing). Nothing here is random but the wander's phases and periods,
drawn once from the seed, so every query is exact and a seed gives the same
p(t) however the time axis is asked.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from afmdrift.drivers.sim._physics import DriftPhysics, OffsetMove, TipChange, total_drift
from afmdrift.drivers.sim._scenario import HeatNetworkConfig, PhysicsConfig

__all__ = ["HEAT_NETWORK_COMPONENTS", "HeatNetworkPhysics"]

#: Names of the drift components of :class:`HeatNetworkPhysics`, in order.
HEAT_NETWORK_COMPONENTS: tuple[str, ...] = (
    "air",
    "stage",
    "scanner",
    "warmup",
    "wander",
    "tip_change",
)

FloatArray = npt.NDArray[np.float64]

#: An actuator with every drift effect off: the offset, the compensation ramp
#: and the tip steps, shared with the first physics.
_ACTUATOR_ONLY = {"thermal": {"enabled": False}}


class _Thermostat:
    """The air ``u(t)`` and the two lagged nodes, segment by segment, grown on demand.

    Segment ``k`` starts at ``t_k`` with ``u = a_k + r_k s`` (``s = t − t_k``)
    and node states ``(y1_k, y2_k)`` (stage and scanner minus the set point).
    """

    def __init__(self, cfg: HeatNetworkConfig) -> None:
        self.band = float(cfg.band_k)
        self.heat = float(cfg.heating_k_per_h) / 3600.0
        self.cool = -float(cfg.cooling_k_per_h) / 3600.0
        self.tau1 = float(cfg.tau_stage_s)
        self.tau2 = float(cfg.tau_scanner_s)
        y0 = float(cfg.stage_offset_k)
        self.starts = [0.0]
        self.values = [0.0]
        self.rates = [self.heat]
        self.y1 = [y0]
        self.y2 = [y0]

    def _append_next(self) -> None:
        t, a, r = self.starts[-1], self.values[-1], self.rates[-1]
        end = self.band if r > 0 else -self.band
        length = (end - a) / r
        _, y1, y2 = self._solve(np.array([length]), a, r, self.y1[-1], self.y2[-1])
        self.starts.append(t + length)
        self.values.append(end)
        self.rates.append(self.cool if r > 0 else self.heat)
        self.y1.append(float(y1[0]))
        self.y2.append(float(y2[0]))

    def _solve(
        self,
        s: FloatArray,
        a: npt.ArrayLike,
        r: npt.ArrayLike,
        y1: npt.ArrayLike,
        y2: npt.ArrayLike,
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Air, stage and scanner at ``s`` into a segment (closed form for a linear input).

        ``y1 = u − r τ_1 + D e^{−s/τ_1}``, ``D = y1_0 − a + r τ_1``;
        ``y2 = u − r (τ_1 + τ_2) + B e^{−s/τ_1} + C e^{−s/τ_2}``,
        ``B = D τ_1 / (τ_1 − τ_2)``, ``C = y2_0 − a + r (τ_1 + τ_2) − B``.
        """
        t1, t2 = self.tau1, self.tau2
        a_ = np.asarray(a, dtype=np.float64)
        r_ = np.asarray(r, dtype=np.float64)
        d = np.asarray(y1, dtype=np.float64) - a_ + r_ * t1
        b = d * t1 / (t1 - t2)
        c = np.asarray(y2, dtype=np.float64) - a_ + r_ * (t1 + t2) - b
        e1 = np.exp(-s / t1)
        u = a_ + r_ * s
        stage = u - r_ * t1 + d * e1
        scanner = u - r_ * (t1 + t2) + b * e1 + c * np.exp(-s / t2)
        return u, stage, scanner

    def at(self, t: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """``(u, T_st − T_set, T_sc − T_set)`` at times ``t`` (any shape), K."""
        if t.size:
            while self.starts[-1] <= float(t.max()):
                self._append_next()
        starts = np.asarray(self.starts)
        k = np.searchsorted(starts, t, side="right") - 1
        return self._solve(
            t - starts[k],
            np.asarray(self.values)[k],
            np.asarray(self.rates)[k],
            np.asarray(self.y1)[k],
            np.asarray(self.y2)[k],
        )


class HeatNetworkPhysics:
    """Ground-truth drift of the heat-network model, its logged sensors and the actuator.

    The same public interface as :class:`~afmdrift.drivers.sim._physics.DriftPhysics`
    (what :class:`~afmdrift.drivers.sim.SimulatedAFM` and the servers use). The
    actuator (commanded offset, drift-compensation ramp, tip steps) is the first
    physics' own, with every effect off: the controller is the same instrument.

    Parameters
    ----------
    config : PhysicsConfig
        The ``[physics]`` table of a scenario, ``model = "heat_network"``.
    seed : int
        Seed of the wander's phases and periods.
    start_offset_nm : (float, float)
        Commanded XY offset at power-on.
    """

    def __init__(
        self, config: PhysicsConfig, *, seed: int, start_offset_nm: tuple[float, float] = (0, 0)
    ) -> None:
        if config.model != "heat_network":
            raise ValueError(
                f"HeatNetworkPhysics needs physics.model = 'heat_network', not {config.model!r}"
            )
        self.config = config
        cfg = config.heat_network
        self._cfg = cfg
        self._actuator = DriftPhysics(
            PhysicsConfig.model_validate(_ACTUATOR_ONLY),
            seed=seed,
            start_offset_nm=start_offset_nm,
        )
        self._nodes = _Thermostat(cfg)
        # The nodes at power-on as the closed form gives them, so that p(0) = 0 exactly.
        self._nodes0 = tuple(float(x[0]) for x in self._nodes.at(np.zeros(1)))
        self._couple = np.array([[1.0, cfg.cross_coupling[0]], [cfg.cross_coupling[1], 1.0]])
        self._omega, self._phase, self._amp = self._wander_terms(cfg, seed)

    @staticmethod
    def _wander_terms(
        cfg: HeatNetworkConfig, seed: int
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Angular frequencies, phases and amplitudes, each of shape (2, n)."""
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x4EA7]))
        n = int(cfg.wander_terms)
        lo, hi = (math.log(p) for p in cfg.wander_periods_s)
        step = (hi - lo) / n
        log_periods = lo + step * (np.arange(n) + 0.5) + rng.uniform(-0.5, 0.5, (2, n)) * step
        periods = np.exp(log_periods)
        omega = 2.0 * np.pi / periods
        phase = rng.uniform(0.0, 2.0 * np.pi, (2, n))
        shape = periods / np.sqrt(0.5 * np.sum(periods**2, axis=1, keepdims=True))
        amp = shape * np.asarray(cfg.wander_nm, dtype=np.float64)[:, None]
        return omega, phase, amp

    # ------------------------------------------------------------------ sensors (true values)

    def _temperatures(self, t_s: npt.ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
        t = np.maximum(np.asarray(t_s, dtype=np.float64), 0.0)
        return self._nodes.at(t)

    def head_temperature_c(self, t_s: npt.ArrayLike) -> FloatArray:
        """Room air temperature at the head, °C; what the sensor reads."""
        out: FloatArray = self._cfg.air_mean_c + self._temperatures(t_s)[0]
        return out

    def stage_temperature_c(self, t_s: npt.ArrayLike) -> FloatArray:
        """Stage temperature (first node), °C; not measured."""
        out: FloatArray = self._cfg.air_mean_c + self._temperatures(t_s)[1]
        return out

    def scanner_temperature_c(self, t_s: npt.ArrayLike) -> FloatArray:
        """Scanner temperature (second node), °C; not measured."""
        out: FloatArray = self._cfg.air_mean_c + self._temperatures(t_s)[2]
        return out

    def humidity_pct(self, t_s: npt.ArrayLike) -> FloatArray:
        """Relative humidity, %: ``RH_0 + g u`` (air at a constant dew point)."""
        u = self._temperatures(t_s)[0]
        out: FloatArray = np.clip(
            self._cfg.humidity_mean_pct + self._cfg.humidity_pct_per_k * u, 0.0, 100.0
        )
        return out

    def channel_values(self, t_s: npt.ArrayLike) -> dict[str, FloatArray]:
        """No extra channels in this model (the scenario cannot declare any)."""
        return {}

    # ------------------------------------------------------------------ actuator and events

    def command_offset(self, t_s: float, x_nm: float, y_nm: float) -> OffsetMove:
        """Record a commanded absolute offset at ``t_s`` (time order); return the move."""
        return self._actuator.command_offset(t_s, x_nm, y_nm)

    def add_tip_change(self, t_s: float, dx_nm: float, dy_nm: float) -> TipChange:
        """Record a tip change at ``t_s`` with its step in apparent position."""
        return self._actuator.add_tip_change(t_s, dx_nm, dy_nm)

    @property
    def moves(self) -> list[OffsetMove]:
        return self._actuator.moves

    def commanded_offset_at(self, t_s: npt.ArrayLike) -> FloatArray:
        """Commanded XY offset (piecewise constant), shape (..., 2), nm."""
        return self._actuator.commanded_offset_at(t_s)

    def ramp_compensation(
        self,
        t_s: float,
        velocity_nm_per_s: tuple[float, float],
        limit_nm: tuple[float, float],
        *,
        release: bool = False,
    ) -> FloatArray:
        """The controller's drift compensation (see ``DriftPhysics.ramp_compensation``)."""
        return self._actuator.ramp_compensation(t_s, velocity_nm_per_s, limit_nm, release=release)

    def compensation_at(self, t_s: npt.ArrayLike) -> FloatArray:
        """Drift-compensation displacement of the scan window, shape (..., 2), nm."""
        return self._actuator.compensation_at(t_s)

    def scan_offset_at(self, t_s: npt.ArrayLike) -> FloatArray:
        """Where the actuator puts the scan window: commanded offset plus compensation, nm."""
        return self._actuator.scan_offset_at(t_s)

    # ------------------------------------------------------------------ drift components

    def components_at(self, t_s: npt.ArrayLike) -> dict[str, FloatArray]:
        """Every drift component at ``t_s`` (:data:`HEAT_NETWORK_COMPONENTS`), (..., 2) nm.

        Each is shown after the cross-coupling of the axes, so they sum to p(t).
        """
        t = np.maximum(np.asarray(t_s, dtype=np.float64), 0.0)
        cfg = self._cfg
        nodes = self._nodes.at(t)
        gains = (cfg.air_nm_per_k, cfg.stage_nm_per_k, cfg.scanner_nm_per_k)
        out: dict[str, FloatArray] = {}
        for name, node, node0, gain in zip(
            ("air", "stage", "scanner"), nodes, self._nodes0, gains, strict=True
        ):
            out[name] = (node - node0)[..., None] * np.asarray(gain)
        out["warmup"] = (t / (t + cfg.warmup_tau_s))[..., None] * np.asarray(cfg.warmup_nm)
        arg = t[..., None, None] * self._omega + self._phase  # (..., 2, n)
        out["wander"] = np.sum(self._amp * (np.sin(arg) - np.sin(self._phase)), axis=-1)
        for name in ("air", "stage", "scanner", "warmup", "wander"):
            out[name] = out[name] @ self._couple.T
        out["tip_change"] = self._actuator.components_at(t)["tip_change"]
        return out

    def drift_at(self, t_s: npt.ArrayLike) -> FloatArray:
        """True drift p(t), shape (..., 2) in nm (sum of :meth:`components_at`)."""
        return total_drift(self.components_at(t_s))

    def z_offset_nm(self, t_s: npt.ArrayLike, *, rate_nm_per_s: float) -> FloatArray:
        """Slow height offset ``rate · t``, nm (no thermal height drift in this model)."""
        out: FloatArray = rate_nm_per_s * np.maximum(np.asarray(t_s, dtype=np.float64), 0.0)
        return out
