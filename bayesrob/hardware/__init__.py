"""Hardware: servo controllers, position trackers, data collection, simulated devices.

Submodules: ``controller`` (shared interface, safety checks, errors), ``maestro`` (Pololu
Maestro), ``ssc32`` (Lynxmotion SSC-32), ``tracker`` (streaming tracker, manual entry),
``collect`` (``bayesrob collect``) and ``simdevice`` (``bayesrob sim-device``).
"""

from bayesrob.hardware.controller import (
    DisconnectedError,
    HardwareError,
    LimitError,
    ServoController,
)

__all__ = ["DisconnectedError", "HardwareError", "LimitError", "ServoController"]
