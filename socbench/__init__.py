"""socbench: a testbed for battery state-of-charge estimation.

Conventions: current in A, positive = discharge; SOC a fraction in [0, 1]; time in s; voltage in V; temperature in °C.
"""

from .errors import ConfigError, DataError, ModelError, UserError
from .ocv import OCVCurve
from .profile import Profile, ProfileMeta

__version__ = "0.1.0"
__all__ = ["Profile", "ProfileMeta", "OCVCurve", "DataError", "ConfigError", "ModelError", "UserError"]
