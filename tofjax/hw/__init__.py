"""TMF8828 acquisition: protocol, smbus2 driver, register-level emulator, rigs and recording.

See ``docs/acquisition.md``. Nothing here imports JAX until an emulated rig computes its
forward model, and nothing needs a Raspberry Pi until a real bus is opened.
"""

from .bus import BusFaults as BusFaults
from .bus import SimBus as SimBus
from .bus import SimClock as SimClock
from .driver import DriverOptions as DriverOptions
from .driver import ErrorCounts as ErrorCounts
from .driver import FrameDropped as FrameDropped
from .driver import TMF8828 as TMF8828
from .driver import TMF8828Array as TMF8828Array
from .emulator import DeviceFaults as DeviceFaults
from .emulator import TMF8828Emulator as TMF8828Emulator
from .rig import Rig as Rig
from .rig import emulated_bus as emulated_bus
from .rig import load_rig as load_rig
from .rig import open_array as open_array
