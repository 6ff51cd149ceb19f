"""Map a device's timestamps onto the host clock so ``header.stamp`` is the acquisition time (ROS-free).

Derivation. Let the host clock be the reference (``time.time_ns()``) and let the device clock read
``t_dev = t_host - θ`` (θ: unknown, slowly varying offset). A sample is *captured* at host time ``c``,
leaves the device ``L`` later (``L``: the latency the device reports, capture → send) and arrives after a
transport delay ``δ ≥ δ_min``. The device stamps the message with a device time ``s_dev`` that is either
the capture time (``c - θ``) or the send time (``c + L - θ``); in both cases the device-clock send time is
known: ``send_dev = c_dev + L``. On receipt at host time ``r = c + L + δ``:

    r - send_dev = θ + δ            (one offset sample per message)

``δ`` is positive and noisy, so the *minimum* over a window converges to ``θ + δ_min``. The capture time on
the host clock is then

    stamp = c_dev + θ̂ = c + (δ_min - 0)      with θ̂ = min_window(r - send_dev),

i.e. the true capture time plus the minimal transport delay (tens of µs on a LAN/localhost, constant; it
can be removed with a configured ``transport_delay_ns`` if known). Note that ``L`` is subtracted exactly
once: it enters the offset sample (``send_dev``) and the stamp uses ``c_dev``. If a device reports no
latency (L = 0) and stamps at capture, the estimate absorbs the constant processing delay into θ̂ and the
stamp is late by it — a property of such a device, not of this estimator.

Window and steps. A sliding-window minimum follows a drifting offset with a lag of at most
``drift · window`` (50 ppm · 5 s = 0.25 ms). A downward step of θ is followed immediately (the new samples
are smaller). An upward step (the device clock was set back, or the host clock stepped forward) would keep
the stale minimum for a whole window, so ``reset_after`` consecutive samples more than
``reset_threshold_s`` above the estimate restart the window. Device time going backwards by more than the
threshold is a device clock reset: the window restarts at once. Both are counted for /diagnostics.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass


@dataclass
class ClockSyncStats:
    samples: int = 0
    resets: int = 0
    backwards: int = 0  # device time went backwards (sample rejected or window restarted)


class ClockSync:
    """Running-minimum estimator of host − device clock offset (integer nanoseconds throughout)."""

    def __init__(self, window_s: float = 5.0, reset_threshold_s: float = 0.5, reset_after: int = 20,
                 transport_delay_ns: int = 0) -> None:
        if not window_s > 0 or not reset_threshold_s > 0 or reset_after < 1:
            raise ValueError("window_s and reset_threshold_s must be > 0 and reset_after >= 1")
        self.window_ns = int(window_s * 1e9)
        self.reset_threshold_ns = int(reset_threshold_s * 1e9)
        self.reset_after = int(reset_after)
        self.transport_delay_ns = int(transport_delay_ns)
        self.stats = ClockSyncStats()
        self._win: deque[tuple[int, int]] = deque()  # (host_ns, offset sample), offset samples increasing
        self._last_dev: int | None = None
        self._above = 0

    @property
    def ready(self) -> bool:
        return bool(self._win)

    @property
    def offset_ns(self) -> int | None:
        """Current estimate θ̂ + δ_min − transport_delay (host = device + offset), or None before any sample."""
        return self._win[0][1] - self.transport_delay_ns if self._win else None

    def reset(self) -> None:
        self._win.clear()
        self._last_dev = None
        self._above = 0
        self.stats.resets += 1

    def observe(self, send_dev_ns: int, host_recv_ns: int) -> bool:
        """Add one message: its device-clock send time and its host receive time. False if rejected."""
        send_dev_ns, host_recv_ns = int(send_dev_ns), int(host_recv_ns)
        if self._last_dev is not None and send_dev_ns < self._last_dev:
            self.stats.backwards += 1
            if self._last_dev - send_dev_ns <= self.reset_threshold_ns:
                return False  # jitter or reordering: keep the estimate, ignore this sample
            self.reset()
        self._last_dev = send_dev_ns
        sample = host_recv_ns - send_dev_ns
        if self._win and sample - self._win[0][1] > self.reset_threshold_ns:
            self._above += 1
            if self._above >= self.reset_after:
                self.reset()
                self._last_dev = send_dev_ns
        else:
            self._above = 0
        while self._win and self._win[-1][1] >= sample:
            self._win.pop()
        self._win.append((host_recv_ns, sample))
        while self._win[0][0] < host_recv_ns - self.window_ns:
            self._win.popleft()
        self.stats.samples += 1
        return True

    def to_host(self, dev_ns: int) -> int | None:
        """Host-clock time of a device-clock time, or None before the first sample."""
        off = self.offset_ns
        return None if off is None else int(dev_ns) + off
