"""NDI Combined API (Polaris Vega over TCP, Spectra/Vicra over serial): protocol core and driver.

Modules: :mod:`.crc` (CRC-16/ARC), :mod:`.protocol` (command encoding, reply framing, error
types), :mod:`.replies` (typed TX/BX/PHSR/VER/... parsers and the emulator's formatters),
:mod:`.rom` (tool definition files), :mod:`.transport` (TCP, serial), :mod:`.client` (command
client: CRC checks, timeouts, retries), :mod:`.frame_clock` (frame numbers -> host time),
:mod:`.driver` (the ROS-free bring-up / polling / reconnect state machine). No ROS imports anywhere
in this package.
"""

from .protocol import NdiCrcError, NdiDeviceError, NdiError, NdiProtocolError  # noqa: F401
from .transport import NdiLinkError  # noqa: F401
