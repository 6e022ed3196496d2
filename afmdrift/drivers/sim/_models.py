"""The physics a scenario selects (``physics.model``) and what the simulator asks of it."""

from __future__ import annotations

from typing import Protocol

import numpy as np
import numpy.typing as npt

from afmdrift.drivers.sim._heat_network import HeatNetworkPhysics
from afmdrift.drivers.sim._physics import DriftPhysics, OffsetMove, TipChange
from afmdrift.drivers.sim._scenario import PhysicsConfig

__all__ = ["SimPhysics", "make_physics"]

FloatArray = npt.NDArray[np.float64]


class SimPhysics(Protocol):
    """Ground-truth drift, true sensor values and the offset actuator of a simulated AFM.

    Sign conventions (both models): a feature at image position u at time 0
    appears at ``u + p(t)`` (:meth:`drift_at`); a commanded move of ``+Δ``
    moves the scan window by ``+Δ`` and is not part of p(t).
    """

    def head_temperature_c(self, t_s: npt.ArrayLike) -> FloatArray: ...

    def humidity_pct(self, t_s: npt.ArrayLike) -> FloatArray: ...

    def channel_values(self, t_s: npt.ArrayLike) -> dict[str, FloatArray]: ...

    def command_offset(self, t_s: float, x_nm: float, y_nm: float) -> OffsetMove: ...

    def add_tip_change(self, t_s: float, dx_nm: float, dy_nm: float) -> TipChange: ...

    @property
    def moves(self) -> list[OffsetMove]: ...

    def commanded_offset_at(self, t_s: npt.ArrayLike) -> FloatArray: ...

    def ramp_compensation(
        self,
        t_s: float,
        velocity_nm_per_s: tuple[float, float],
        limit_nm: tuple[float, float],
        *,
        release: bool = False,
    ) -> FloatArray: ...

    def compensation_at(self, t_s: npt.ArrayLike) -> FloatArray: ...

    def scan_offset_at(self, t_s: npt.ArrayLike) -> FloatArray: ...

    def components_at(self, t_s: npt.ArrayLike) -> dict[str, FloatArray]: ...

    def drift_at(self, t_s: npt.ArrayLike) -> FloatArray: ...

    def z_offset_nm(self, t_s: npt.ArrayLike, *, rate_nm_per_s: float) -> FloatArray: ...


def make_physics(
    config: PhysicsConfig, *, seed: int, start_offset_nm: tuple[float, float] = (0.0, 0.0)
) -> DriftPhysics | HeatNetworkPhysics:
    """The physics ``config.model`` names: ``effects`` or ``heat_network``."""
    if config.model == "heat_network":
        return HeatNetworkPhysics(config, seed=seed, start_offset_nm=start_offset_nm)
    return DriftPhysics(config, seed=seed, start_offset_nm=start_offset_nm)
