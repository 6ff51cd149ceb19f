"""Backend-independent OMC frame model: SI units, validity, frame-number accounting and capture stamps.

Both backends (vendor SDK through ctypes, simulator UDP stream) produce :class:`RawFrame` in device
units (mm, device clock); :class:`FramePipeline` turns them into :class:`MocapFrame` in SI units with a
host-clock capture stamp, decides per body whether it is tracked, and counts dropped / duplicate frames.
It is pure Python so the same code runs in the node, offline, and in the unit tests.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..clock_sync import ClockSync

# NokovSDKTypes.h: `#define UNDEFINED 999999.9999`; users also report 99999 and 9999999.999999 for a lost
# body (reference/nokov_mocap.md §0). No real mocap volume is 99 m across, so anything at or beyond this
# magnitude (mm) is a sentinel, not a measurement.
SENTINEL_MM = 99_000.0
QUAT_UNIT_TOL = 1e-2  # float32 quaternions from the device; renormalised after this check
# body_validity reasons that mean "the device sent a pose we refused" (not "the body is out of view")
REFUSED_REASONS = frozenset({"non-finite", "non-unit quaternion"})


@dataclass
class RawBody:
    id: int
    name: str  # "" when the backend has not resolved the id yet
    position_mm: tuple[float, float, float]
    quat_xyzw: tuple[float, float, float, float]
    mean_error_mm: float = 0.0
    tracked_flag: bool = True  # the device's own tracking flag (stream) or flag test (SDK)
    markers: int = 0


@dataclass
class RawFrame:
    frame_number: int
    device_ts_ns: int  # device clock; <= 0 means "the device gave no timestamp"
    latency_s: float  # capture -> send, as reported by the device
    recv_ns: int  # host clock (time.time_ns) when the frame reached us
    bodies: list[RawBody] = field(default_factory=list)


@dataclass
class BodySample:
    id: int
    name: str
    tracked: bool
    position_m: np.ndarray | None  # (3,) or None when not tracked
    quat_xyzw: np.ndarray | None  # (4,) unit, or None when not tracked
    mean_error_m: float
    markers: int
    reason: str = ""  # why not tracked


@dataclass
class MocapFrame:
    frame_number: int
    stamp_ns: int  # capture time on the host clock
    recv_ns: int
    latency_s: float
    bodies: list[BodySample]


def body_validity(b: RawBody) -> tuple[bool, str]:
    """(tracked, reason). Sentinels, NaN/inf, non-unit quaternions and a cleared device flag mean "not tracked"."""
    if not b.tracked_flag:
        return False, "device flag"
    p = np.asarray(b.position_mm, dtype=float)
    q = np.asarray(b.quat_xyzw, dtype=float)
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
        return False, "non-finite"
    if np.any(np.abs(p) >= SENTINEL_MM):
        return False, "sentinel"
    if abs(float(np.linalg.norm(q)) - 1.0) > QUAT_UNIT_TOL:
        return False, "non-unit quaternion"
    return True, ""


@dataclass
class FrameCounters:
    frames: int = 0  # accepted frames
    dropped: int = 0  # missing frame numbers (gaps)
    duplicates: int = 0  # repeated or older frame numbers (discarded)
    restarts: int = 0  # frame numbers jumped far backwards (device restarted numbering)
    no_device_time: int = 0  # frames stamped from receive time because the device gave none
    bad_latency: int = 0  # latency NaN/negative/implausible: treated as 0
    stamp_not_increasing: int = 0  # mapped stamp not after the previous one (discarded)


class FramePipeline:
    """RawFrame -> MocapFrame: dedupe by frame number, count gaps, convert mm -> m, stamp with capture time.

    ``device_stamp``: what the device's timestamp marks — ``"capture"`` (NOKOV "FrameGroup timestamp",
    NatNet semantics; default) or ``"send"``. ``stamp_source``: ``"device"`` (clock sync, see
    :mod:`fullperc_drivers.clock_sync`) or ``"receive"`` (receive time − latency; for devices without a
    usable timestamp). ``latency_compensation=False`` treats the reported latency as 0.
    """

    def __init__(self, sync: ClockSync | None = None, device_stamp: str = "capture", stamp_source: str = "device",
                 latency_compensation: bool = True, max_latency_s: float = 1.0, restart_gap: int = 1000,
                 frame_modulo: int = 1 << 32) -> None:
        if device_stamp not in ("capture", "send"):
            raise ValueError(f"device_stamp must be 'capture' or 'send', got {device_stamp!r}")
        if stamp_source not in ("device", "receive"):
            raise ValueError(f"stamp_source must be 'device' or 'receive', got {stamp_source!r}")
        self.sync = sync or ClockSync()
        self.device_stamp = device_stamp
        self.stamp_source = stamp_source
        self.latency_compensation = latency_compensation
        self.max_latency_s = max_latency_s
        self.restart_gap = restart_gap
        self.modulo = frame_modulo
        self.counters = FrameCounters()
        self._last_fno: int | None = None
        self._last_stamp: int | None = None

    def _frame_gap(self, fno: int) -> int | None:
        """Frames missing before ``fno`` (0 = consecutive), or None for a duplicate/old frame."""
        if self._last_fno is None:
            return 0
        d = (fno - self._last_fno) % self.modulo
        if d == 0:
            return None
        if d > self.modulo // 2:  # behind the last frame
            if self.modulo - d > self.restart_gap:
                self.counters.restarts += 1
                return 0
            return None
        return d - 1

    def _latency_ns(self, lat: float) -> int:
        if not self.latency_compensation:
            return 0
        if not (math.isfinite(lat) and 0.0 <= lat <= self.max_latency_s):
            self.counters.bad_latency += 1
            return 0
        return int(round(lat * 1e9))

    def _stamp(self, raw: RawFrame) -> int:
        lat_ns = self._latency_ns(raw.latency_s)
        if self.stamp_source == "receive" or raw.device_ts_ns <= 0:
            if self.stamp_source == "device":
                self.counters.no_device_time += 1
            return raw.recv_ns - lat_ns
        cap_dev = raw.device_ts_ns if self.device_stamp == "capture" else raw.device_ts_ns - lat_ns
        self.sync.observe(cap_dev + lat_ns, raw.recv_ns)
        stamp = self.sync.to_host(cap_dev)
        # Never later than the arrival itself (only possible right after a clock reset).
        return min(int(stamp), raw.recv_ns) if stamp is not None else raw.recv_ns - lat_ns

    def process(self, raw: RawFrame) -> MocapFrame | None:
        """The frame in SI units with its capture stamp, or None if it is a duplicate/out of order."""
        gap = self._frame_gap(raw.frame_number)
        if gap is None:
            self.counters.duplicates += 1
            return None
        stamp = self._stamp(raw)
        if self._last_stamp is not None and stamp <= self._last_stamp:
            self.counters.stamp_not_increasing += 1
            self._last_fno = raw.frame_number
            return None
        self.counters.dropped += gap
        self.counters.frames += 1
        self._last_fno = raw.frame_number
        self._last_stamp = stamp
        bodies = []
        for b in raw.bodies:
            ok, why = body_validity(b)
            err = float(b.mean_error_mm) * 1e-3 if math.isfinite(b.mean_error_mm) else float("nan")
            if ok:
                q = np.asarray(b.quat_xyzw, dtype=float)
                bodies.append(BodySample(b.id, b.name, True, np.asarray(b.position_mm, dtype=float) * 1e-3,
                                         q / np.linalg.norm(q), err, int(b.markers)))
            else:
                bodies.append(BodySample(b.id, b.name, False, None, None, err, int(b.markers), why))
        return MocapFrame(raw.frame_number, stamp, raw.recv_ns, raw.latency_s, bodies)
