"""Diana backend ``stream``: the simulator's joint-state UDP stream (wire format in ``fullperc_drivers.streams``).

A :class:`~fullperc_drivers.udp_stream.UdpStreamBackend` decodes datagrams (malformed ones are counted and
skipped) and hands :class:`RawJointState` on; :class:`DianaStreamPipeline` (run on the executor) checks them, counts
sequence gaps and maps the device timestamp to the host clock with :class:`~fullperc_drivers.clock_sync.ClockSync`.
The stream carries no latency field: its timestamp is the sampling time on the device clock, and the
offset estimate absorbs the (minimal) send delay — see the derivation in ``clock_sync``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..clock_sync import ClockSync
from ..diana_kinematics import N_JOINTS
from ..streams import decode_diana
from ..udp_stream import UdpStreamBackend
from . import JointSample


@dataclass
class RawJointState:
    sequence: int
    device_ts_ns: int
    recv_ns: int
    q: np.ndarray
    dq: np.ndarray


@dataclass
class StreamCounters:
    samples: int = 0
    dropped: int = 0  # sequence gaps
    duplicates: int = 0
    restarts: int = 0
    invalid: int = 0  # wrong joint count or non-finite values
    stamp_not_increasing: int = 0


def raw_joint_state(data: bytes, recv_ns: int) -> RawJointState:
    """One Diana datagram as a :class:`RawJointState` (raises ``StreamDecodeError`` if malformed)."""
    s = decode_diana(data)
    return RawJointState(s.sequence, s.timestamp_ns, recv_ns, s.q, s.dq)


class DianaStreamBackend(UdpStreamBackend[RawJointState]):
    def __init__(self, host: str, port: int, on_state: Callable[[RawJointState], None]) -> None:
        super().__init__(host, port, on_state, raw_joint_state, thread_name="diana-stream")


class DianaStreamPipeline:
    """RawJointState -> JointSample with a host-clock stamp; rejects bad samples, counts gaps."""

    def __init__(self, sync: ClockSync | None = None, restart_gap: int = 1000, modulo: int = 1 << 32) -> None:
        self.sync = sync or ClockSync()
        self.counters = StreamCounters()
        self.restart_gap = restart_gap
        self.modulo = modulo
        self._last_seq: int | None = None
        self._last_stamp: int | None = None
        self.last_reason = ""

    def process(self, raw: RawJointState) -> JointSample | None:
        if raw.q.shape != (N_JOINTS,) or raw.dq.shape != (N_JOINTS,):
            self.counters.invalid += 1
            self.last_reason = f"expected {N_JOINTS} joints, got {raw.q.shape[0]}"
            return None
        if not (np.all(np.isfinite(raw.q)) and np.all(np.isfinite(raw.dq))):
            self.counters.invalid += 1
            self.last_reason = "non-finite joint values"
            return None
        if self._last_seq is not None:
            d = (raw.sequence - self._last_seq) % self.modulo
            if d == 0 or (d > self.modulo // 2 and self.modulo - d <= self.restart_gap):
                self.counters.duplicates += 1
                return None
            if d > self.modulo // 2:
                self.counters.restarts += 1
            else:
                self.counters.dropped += d - 1
        self.sync.observe(raw.device_ts_ns, raw.recv_ns)
        stamp = min(int(self.sync.to_host(raw.device_ts_ns)), raw.recv_ns)
        self._last_seq = raw.sequence
        if self._last_stamp is not None and stamp <= self._last_stamp:
            self.counters.stamp_not_increasing += 1
            return None
        self._last_stamp = stamp
        self.counters.samples += 1
        return JointSample(stamp, raw.q.copy(), raw.dq.copy(), raw.sequence)
