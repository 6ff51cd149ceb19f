"""OMC backend ``stream``: the simulator's UDP frame stream (wire format in ``fullperc_drivers.streams``).

A :class:`~fullperc_drivers.udp_stream.UdpStreamBackend` whose decoder turns a datagram into a :class:`RawFrame`
in device units, stamped with the host receive time; malformed datagrams are counted and skipped there.
"""

from __future__ import annotations

from collections.abc import Callable

from ..streams import decode_omc
from ..udp_stream import UdpStreamBackend
from .frames import RawBody, RawFrame


def raw_frame(data: bytes, recv_ns: int) -> RawFrame:
    """One OMC datagram as a :class:`RawFrame` (raises ``StreamDecodeError`` if malformed)."""
    f = decode_omc(data)
    bodies = [RawBody(b.id, b.name, tuple(b.position_mm), tuple(b.quat_xyzw), b.mean_error_mm, b.tracked,
                      b.markers) for b in f.bodies]
    return RawFrame(f.frame_number, f.timestamp_ns, f.latency_s, recv_ns, bodies)


class OmcStreamBackend(UdpStreamBackend[RawFrame]):
    def __init__(self, host: str, port: int, on_frame: Callable[[RawFrame], None]) -> None:
        super().__init__(host, port, on_frame, raw_frame, thread_name="omc-stream")
