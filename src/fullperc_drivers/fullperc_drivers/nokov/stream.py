"""OMC backend ``stream``: the simulator's UDP frame stream (wire format in ``fullperc_drivers.streams``).

Every datagram is decoded on the receiver thread; malformed ones (truncated, garbled, wrong magic or
version) are counted and skipped — ``decode_omc`` raises only ``StreamDecodeError``. Valid frames go to
``on_frame`` as :class:`RawFrame` in device units, stamped with the host receive time.
"""

from __future__ import annotations

from collections.abc import Callable

from ..handoff import UdpReceiver
from ..streams import StreamDecodeError, decode_omc
from .frames import RawBody, RawFrame


class OmcStreamBackend:
    name = "stream"

    def __init__(self, host: str, port: int, on_frame: Callable[[RawFrame], None]) -> None:
        self._on_frame = on_frame
        self.decode_errors = 0
        self.last_error = ""
        self.datagrams = 0
        self._rx = UdpReceiver(host, port, self._datagram, name="omc-stream")
        self.address = self._rx.address

    @property
    def connected(self) -> bool:
        return True  # connectionless; liveness is judged from frame arrival by the node

    def _datagram(self, data: bytes, recv_ns: int) -> None:
        self.datagrams += 1
        try:
            f = decode_omc(data)
        except StreamDecodeError as e:
            self.decode_errors += 1
            self.last_error = str(e)
            return
        bodies = [RawBody(b.id, b.name, tuple(b.position_mm), tuple(b.quat_xyzw), b.mean_error_mm, b.tracked,
                          b.markers) for b in f.bodies]
        self._on_frame(RawFrame(f.frame_number, f.timestamp_ns, f.latency_s, recv_ns, bodies))

    def close(self) -> None:
        self._rx.close()
