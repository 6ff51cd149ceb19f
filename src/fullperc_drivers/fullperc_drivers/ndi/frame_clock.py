"""Device frame numbers -> host time: the lower envelope of (receive time - frame number x period)."""

from __future__ import annotations

import math
from collections import deque


class FrameClock:
    """Maps device frame numbers to host time [ns].

    Each reply gives (frame number f, host receive time r). With the device frame period P the
    capture time is c(f) = c0 + f P, and r = c(f) + latency with latency >= its minimum, so the
    lower envelope of r - f P over a sliding window estimates c0 + min latency; subtracting the
    configured device latency gives the capture time. A frame number that goes backwards or jumps
    by more than ``max_jump_s`` resets the estimate (device re-initialised or reconnected).

    The offsets are kept relative to the first receive time after a reset (an integer): host times
    are ~1.7e18 ns since the epoch, where a float64 resolves only 256 ns, so r - f P taken as a float
    would move every stamp by up to ~128 ns.
    """

    def __init__(self, frame_rate_hz: float, window: int = 240, device_latency_s: float = 0.0,
                 max_jump_s: float = 10.0) -> None:
        if not frame_rate_hz > 0:
            raise ValueError("frame_rate_hz must be > 0")
        self.period_ns = 1e9 / frame_rate_hz
        self.latency_ns = int(device_latency_s * 1e9)
        self.max_jump = max_jump_s * frame_rate_hz
        self._offsets: deque[float] = deque(maxlen=window)
        self._last_frame: int | None = None
        self._base_frame = 0
        self._base_recv = 0
        self.resets = 0

    def reset(self) -> None:
        self._offsets.clear()
        self._last_frame = None

    def stamp(self, frame: int, recv_ns: int) -> int:
        if self._last_frame is not None:
            d = frame - self._last_frame
            if d < 0 or d > self.max_jump:
                self.reset()
                self.resets += 1
        if self._last_frame is None:
            self._base_frame, self._base_recv = frame, recv_ns
        self._last_frame = frame
        k = frame - self._base_frame
        self._offsets.append((recv_ns - self._base_recv) - k * self.period_ns)
        c0 = min(self._offsets)
        return self._base_recv + math.floor(c0 + k * self.period_ns) - self.latency_ns
