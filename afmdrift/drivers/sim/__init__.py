"""The simulated AFM: physics, sample, raster scanner, and protocol server.

The physics (each drift effect with its equation and sources) is documented in
``docs/physics.md``. Runtime code (``afmdrift.service``) never imports this
package.
"""

from afmdrift.drivers.sim._heat_network import HEAT_NETWORK_COMPONENTS, HeatNetworkPhysics
from afmdrift.drivers.sim._instrument import PIEZO_RANGE_NM, SimulatedAFM
from afmdrift.drivers.sim._models import SimPhysics, make_physics
from afmdrift.drivers.sim._physics import COMPONENTS, DriftPhysics
from afmdrift.drivers.sim._sample import Sample
from afmdrift.drivers.sim._scenario import (
    SCENARIO_DIR,
    Scenario,
    load_scenario,
    parse_scenario,
    resolve_scenario_path,
)

__all__ = [
    "COMPONENTS",
    "HEAT_NETWORK_COMPONENTS",
    "PIEZO_RANGE_NM",
    "SCENARIO_DIR",
    "DriftPhysics",
    "HeatNetworkPhysics",
    "Sample",
    "Scenario",
    "SimPhysics",
    "SimulatedAFM",
    "load_scenario",
    "make_physics",
    "parse_scenario",
    "resolve_scenario_path",
]
