"""Block phase-correlation drift measurement (Yang et al., IEEE T-NANO 2008)."""

from afmdrift.registration._config import RegistrationConfig

__all__ = ["RegistrationConfig"]
