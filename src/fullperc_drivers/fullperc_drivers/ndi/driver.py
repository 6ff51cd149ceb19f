"""ROS-free NDI tracking driver: command client, device-to-host time mapping, and the
connect / load tools / poll / reconnect state machine.

Bring-up (reference/ndi.md §2.1): open link (serial: probe with INIT at 9600, else break and wait
for RESET; then COMM to the configured rate, host switches after OKAY) -> ``INIT`` -> ``VER:0``
-> optional ``SET:Param.Tracking.Selected Volume=n`` -> ``PHSR:01`` + ``PHF`` for stale handles ->
per tool ``PHRQ:*********1****``, ``PVWR`` in 64-byte chunks, ``PINIT``, ``PENA`` -> ``PHSR:04``
check -> ``TSTART`` -> poll ``BX``/``TX`` at the configured rate -> ``TSTOP`` on shutdown.

Errors: a CRC error, a garbled reply or a read timeout is counted, the input is drained and the
request repeated (``max_retries`` times); after that, or when the link drops, the driver closes
the link, backs off (0 s first, then doubling up to ``backoff_max_s``) and runs the whole
bring-up again (the tools are re-loaded). The driver never hands out a non-finite pose: a tool
whose transform is not finite/unit is reported as not visible and counted in ``bad_poses``.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fullperc_common.transforms import is_finite_pose

from . import replies as R
from .protocol import (
    FrameReader,
    NdiCrcError,
    NdiDeviceError,
    NdiError,
    NdiProtocolError,
    Reply,
    check_status,
    encode_command,
    parse_okay,
)
from .transport import NdiLinkError, SerialTransport, TcpTransport, Transport, baud_code

log = logging.getLogger("fullperc.ndi")


class NdiTimeout(NdiLinkError):
    """No complete reply within the read timeout."""


# ----------------------------------------------------------------------------------------------
# Counters


@dataclass
class Counters:
    commands: int = 0
    frames: int = 0  # tracking replies parsed
    duplicate_frames: int = 0  # poll returned a frame number already delivered
    crc_errors: int = 0
    garbled: int = 0  # replies that passed framing but failed to parse
    timeouts: int = 0
    retries: int = 0
    device_errors: int = 0
    device_warnings: int = 0
    link_losses: int = 0
    reconnects: int = 0  # successful bring-ups after a loss
    bad_poses: int = 0  # non-finite / non-unit transforms refused
    bytes_drained: int = 0

    def as_dict(self) -> dict[str, int]:
        return dict(self.__dict__)


# ----------------------------------------------------------------------------------------------
# Command client


class NdiClient:
    """Request/response over a :class:`Transport`, with CRC checks, timeouts and retries."""

    def __init__(self, transport: Transport, read_timeout: float = 0.5, crc_form: bool = True,
                 max_retries: int = 3, counters: Counters | None = None) -> None:
        self.t = transport
        self.read_timeout = read_timeout
        self.crc_form = crc_form
        self.max_retries = max_retries
        self.counters = counters or Counters()
        self._frames = FrameReader()

    # -- low level ------------------------------------------------------------------------------
    def _read_reply(self, timeout: float) -> Reply:
        end = time.monotonic() + timeout
        while True:
            rep = self._frames.pop()  # may raise NdiCrcError / NdiProtocolError
            if rep is not None:
                return rep
            left = end - time.monotonic()
            if left <= 0:
                raise NdiTimeout(f"no reply within {timeout:.3f} s")
            self._frames.feed(self.t.read(left))

    def _recover(self) -> None:
        self._frames.clear()
        self.counters.bytes_drained += self.t.drain()

    def raw(self, name: str, params: str = "", timeout: float | None = None, retry: bool = True) -> Reply:
        """Send one command and return its CRC-checked reply (``ERRORxx`` raises NdiDeviceError).

        CRC errors, malformed frames and timeouts are counted and the command repeated up to
        ``max_retries`` times; then the last error propagates (a link-level failure).
        """
        cmd = encode_command(name, params, self.crc_form)
        attempts = 1 + (self.max_retries if retry else 0)
        last: NdiError | None = None
        for attempt in range(attempts):
            if attempt:
                self.counters.retries += 1
            self.t.write(cmd)
            self.counters.commands += 1
            try:
                rep = self._read_reply(self.read_timeout if timeout is None else timeout)
            except NdiCrcError as e:
                self.counters.crc_errors += 1
                last = e
                self._recover()
                continue
            except NdiTimeout as e:
                self.counters.timeouts += 1
                last = e
                self._recover()
                continue
            except NdiProtocolError as e:
                self.counters.garbled += 1
                last = e
                self._recover()
                continue
            if not rep.binary and rep.data.startswith(b"ERROR"):
                self.counters.device_errors += 1
            return check_status(rep, name)
        assert last is not None
        if isinstance(last, NdiLinkError):
            raise last
        raise NdiLinkError(f"{name}: {attempts} attempts failed, last: {last}") from last

    def okay(self, name: str, params: str = "", timeout: float | None = None) -> None:
        warn = parse_okay(self.raw(name, params, timeout), name)
        if warn is not None:
            self.counters.device_warnings += 1
            log.warning("NDI %s answered WARNING%02X", name, warn)

    def _parsed(self, name: str, params: str, parse: Callable, timeout: float | None = None):
        """Send, parse; a reply that passes the CRC but does not parse is retried like a CRC error."""
        for attempt in range(1 + self.max_retries):
            rep = self.raw(name, params, timeout)
            try:
                return parse(rep)
            except NdiProtocolError as e:
                self.counters.garbled += 1
                self._recover()
                if attempt == self.max_retries:
                    raise NdiLinkError(f"{name}: reply does not parse: {e}") from e
                self.counters.retries += 1
        raise AssertionError("unreachable")  # pragma: no cover

    # -- commands -------------------------------------------------------------------------------
    def init(self, timeout: float = 5.0) -> None:
        self.okay("INIT", "", timeout)

    def ver(self, option: int = 0) -> R.VersionInfo:
        return self._parsed("VER", str(option), lambda r: R.parse_ver(r.text))

    def apirev(self) -> R.ApiRevision:
        return self._parsed("APIREV", "", lambda r: R.parse_apirev(r.text))

    def get(self, name: str) -> dict[str, str]:
        return self._parsed("GET", name, lambda r: R.parse_get(r.text))

    def set(self, name: str, value) -> None:
        self.okay("SET", f"{name}={value}")

    def phsr(self, option: int = 0) -> list[tuple[int, int]]:
        return self._parsed("PHSR", f"{option:02X}", lambda r: R.parse_phsr(r.text))

    def phf(self, handle: int) -> None:
        self.okay("PHF", f"{handle:02X}")

    def phrq(self) -> int:
        return self._parsed("PHRQ", "*********1****", lambda r: R.parse_phrq(r.text))

    def pvwr(self, handle: int, rom: bytes, pad_to: int | None = None) -> int:
        chunks = R.pvwr_params(handle, rom, pad_to)
        for p in chunks:
            self.okay("PVWR", p)
        return len(chunks)

    def pinit(self, handle: int) -> None:
        self.okay("PINIT", f"{handle:02X}")

    def pena(self, handle: int, priority: str = "D") -> None:
        if priority not in ("S", "D", "B"):
            raise ValueError("tracking priority must be S, D or B")
        self.okay("PENA", f"{handle:02X}{priority}")

    def tstart(self) -> None:
        self.okay("TSTART", "")

    def tstop(self) -> None:
        self.okay("TSTOP", "")

    def comm(self, baud: int) -> None:
        self.okay("COMM", f"{baud_code(baud)}0000")

    def bx(self, options: int = R.OPT_TRANSFORMS) -> R.TrackingData:
        def parse(r: Reply) -> R.TrackingData:
            if not r.binary:
                raise NdiProtocolError("BX reply is not binary")
            return R.parse_bx(r.data, options)

        return self._parsed("BX", f"{options:04X}", parse)

    def tx(self, options: int = R.OPT_TRANSFORMS) -> R.TrackingData:
        def parse(r: Reply) -> R.TrackingData:
            if r.binary:
                raise NdiProtocolError("TX reply is binary")
            return R.parse_tx(r.text, options)

        return self._parsed("TX", f"{options:04X}", parse)


# ----------------------------------------------------------------------------------------------
# Device time -> host time


class FrameClock:
    """Maps device frame numbers to host time [ns].

    Each reply gives (frame number f, host receive time r). With the device frame period P the
    capture time is c(f) = c0 + f P, and r = c(f) + latency with latency >= its minimum, so the
    lower envelope of r - f P over a sliding window estimates c0 + min latency; subtracting the
    configured device latency gives the capture time. A frame number that goes backwards or jumps
    by more than ``max_jump_s`` resets the estimate (device re-initialised or reconnected).
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
            self._base_frame = frame
        self._last_frame = frame
        k = frame - self._base_frame
        self._offsets.append(recv_ns - k * self.period_ns)
        c0 = min(self._offsets)
        return int(c0 + k * self.period_ns) - self.latency_ns


# ----------------------------------------------------------------------------------------------
# The driver


@dataclass
class ToolConfig:
    name: str
    rom: bytes
    priority: str = "D"  # PENA: S static/reference, D dynamic, B button box

    @classmethod
    def from_file(cls, name: str, path: str | Path, priority: str = "D") -> ToolConfig:
        return cls(name, Path(path).read_bytes(), priority)


@dataclass
class DriverConfig:
    transport: str = "tcp"  # "tcp" | "serial"
    host: str = "127.0.0.1"
    port: int = 8765
    serial_device: str = "/dev/ttyUSB0"
    baud: int = 115200  # serial rate after COMM
    tools: list[ToolConfig] = field(default_factory=list)
    mode: str = "BX"  # "BX" | "TX"
    reply_option: int = R.OPT_TRANSFORMS
    rate_hz: float = 60.0  # maximum polling rate (0: back to back); polls are phase-locked to frames
    frame_rate_hz: float = 60.0  # device frame frequency (frame number -> time)
    device_latency_s: float = 0.0
    volume: int | None = None  # Param.Tracking.Selected Volume
    read_timeout_s: float = 0.5
    init_timeout_s: float = 5.0
    max_retries: int = 3
    backoff_initial_s: float = 0.05
    backoff_max_s: float = 2.0
    crc_form: bool = True
    pvwr_pad_to: int | None = None  # 1024 to write the whole virtual SROM like ndicapi

    def validate(self) -> None:
        if self.transport not in ("tcp", "serial"):
            raise ValueError(f"transport must be 'tcp' or 'serial', not {self.transport!r}")
        if self.mode not in ("BX", "TX"):
            raise ValueError(f"mode must be 'BX' or 'TX', not {self.mode!r}")
        if not self.tools:
            raise ValueError("at least one tool (name + ROM) is required")
        names = [t.name for t in self.tools]
        if len(set(names)) != len(names):
            raise ValueError(f"tool names must be unique: {names}")
        if not (self.rate_hz >= 0 and self.frame_rate_hz > 0):
            raise ValueError("rate_hz must be >= 0 and frame_rate_hz > 0")
        R._check_options(self.reply_option)
        if self.transport == "serial":
            baud_code(self.baud)


@dataclass
class ToolSample:
    """One tool in one device frame, SI units, ROS quaternion order."""

    name: str
    visible: bool
    position_m: np.ndarray | None = None
    quat_xyzw: np.ndarray | None = None
    fit_error_m: float = -1.0
    port_status: int = 0
    frame_number: int = 0
    markers: int = 0


@dataclass
class FrameResult:
    stamp_ns: int  # acquisition time on the host clock
    recv_ns: int  # when the reply arrived
    frame_number: int
    system_status: int
    tools: dict[str, ToolSample]


class NdiDriver:
    """Connect, load tools, poll, reconnect. Run :meth:`run` in a thread (or :meth:`start`)."""

    def __init__(self, config: DriverConfig, on_frame: Callable[[FrameResult], None] | None = None,
                 on_state: Callable[[str, str], None] | None = None,
                 transport: Transport | None = None) -> None:
        config.validate()
        self.cfg = config
        self.on_frame = on_frame
        self.on_state = on_state
        self.counters = Counters()
        self._transport = transport
        self.client: NdiClient | None = None
        self.clock = FrameClock(config.frame_rate_hz, device_latency_s=config.device_latency_s)
        self.state = "idle"
        self.state_detail = ""
        self.handles: dict[str, int] = {}
        self.firmware = ""
        self.last_error = ""
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._last_frame: int | None = None
        # Liveness record of reconnects: (lost at, tracking again at), time.monotonic_ns().
        self.reconnect_log: list[tuple[int, int]] = []
        self._lost_at: int | None = None
        self._lock = threading.Lock()

    # -- state ----------------------------------------------------------------------------------
    def _set_state(self, state: str, detail: str = "") -> None:
        self.state, self.state_detail = state, detail
        if self.on_state:
            try:
                self.on_state(state, detail)
            except Exception:  # noqa: BLE001 - a callback must not kill the driver
                log.exception("state callback failed")

    def make_transport(self) -> Transport:
        if self._transport is not None:
            return self._transport
        if self.cfg.transport == "tcp":
            return TcpTransport(self.cfg.host, self.cfg.port, connect_timeout=max(1.0, self.cfg.read_timeout_s))
        return SerialTransport(self.cfg.serial_device)

    # -- bring-up -------------------------------------------------------------------------------
    def connect(self) -> None:
        """Open the link and bring the device to tracking with all tools loaded."""
        cfg = self.cfg
        self._set_state("connecting")
        t = self.make_transport()
        t.open()
        c = NdiClient(t, cfg.read_timeout_s, cfg.crc_form, cfg.max_retries, self.counters)
        self.client = c
        if isinstance(t, SerialTransport):
            self._serial_bringup(c, t)
        else:
            c.init(cfg.init_timeout_s)
        self._set_state("configuring")
        try:
            self.firmware = c.ver(0).freeze_tag or ""
        except NdiDeviceError:
            self.firmware = ""
        if cfg.volume is not None:
            c.set("Param.Tracking.Selected Volume", int(cfg.volume))
        for h, _st in c.phsr(0x01):
            c.phf(h)
        self.handles = {}
        for tool in cfg.tools:
            h = c.phrq()
            c.pvwr(h, tool.rom, cfg.pvwr_pad_to)
            self.handles[tool.name] = h
        for tool in cfg.tools:
            c.pinit(self.handles[tool.name])
            c.pena(self.handles[tool.name], tool.priority)
        enabled = {h for h, st in c.phsr(0x04) if st & R.PHSR_ENABLED}
        missing = [n for n, h in self.handles.items() if h not in enabled]
        if missing:
            raise NdiLinkError(f"tools not enabled after PENA: {missing}")
        c.tstart()
        self.clock.reset()
        self._last_frame = None
        self._set_state("tracking", f"{len(self.handles)} tools, firmware '{self.firmware}'")

    def _serial_bringup(self, c: NdiClient, t: SerialTransport) -> None:
        """9600 8N1: INIT; if silent, break -> RESET -> INIT; then COMM and switch the host rate."""
        try:
            parse_okay(c.raw("INIT", "", timeout=min(1.0, self.cfg.init_timeout_s), retry=False), "INIT")
        except (NdiLinkError, NdiProtocolError, NdiDeviceError):
            t.send_break()
            rep = c._read_reply(t.reset_timeout)
            if rep.data != b"RESET":
                raise NdiLinkError(f"expected RESET after a serial break, got {rep.data[:16]!r}") from None
            c.init(self.cfg.init_timeout_s)
        if self.cfg.baud != 9600:
            c.comm(self.cfg.baud)
            time.sleep(0.1)  # the device switches after sending OKAY
            t.set_baud(self.cfg.baud)
            c.init(self.cfg.init_timeout_s)  # also proves the new rate works

    def shutdown(self) -> None:
        """TSTOP and close (best effort)."""
        c = self.client
        if c is not None and c.t.is_open:
            try:
                if self.state == "tracking":
                    c.tstop()
            except NdiError as e:
                log.info("TSTOP on shutdown failed: %s", e)
            if isinstance(c.t, SerialTransport):
                try:
                    c.comm(9600)  # leave the device at its default rate
                except (NdiError, ValueError):
                    pass
            c.t.close()
        self._set_state("stopped")

    # -- polling --------------------------------------------------------------------------------
    def poll_once(self) -> FrameResult | None:
        """One BX/TX request. Returns the frame, or None if it repeats the previous frame number."""
        c = self.client
        if c is None:
            raise NdiLinkError("not connected")
        data = c.bx(self.cfg.reply_option) if self.cfg.mode == "BX" else c.tx(self.cfg.reply_option)
        recv = time.time_ns()
        self.counters.frames += 1
        fno = data.frame_number
        if fno is None:  # every tool disabled: nothing to time-stamp
            return None
        if self._last_frame is not None and fno == self._last_frame:
            self.counters.duplicate_frames += 1
            return None
        self._last_frame = fno
        stamp = self.clock.stamp(fno, recv)
        by_h = data.by_handle()
        tools: dict[str, ToolSample] = {}
        for name, h in self.handles.items():
            tt = by_h.get(h)
            tools[name] = self._sample(name, tt, fno)
        return FrameResult(stamp, recv, fno, data.system_status, tools)

    def _sample(self, name: str, tt: R.ToolTransform | None, fno: int) -> ToolSample:
        if tt is None:
            return ToolSample(name, False, frame_number=fno)
        s = ToolSample(name, False, port_status=tt.port_status or 0,
                       frame_number=tt.frame_number if tt.frame_number is not None else fno)
        if tt.visible and tt.q_wxyz is not None and tt.t_mm is not None:
            q = tt.q_xyzw
            n = float(np.linalg.norm(q)) if np.all(np.isfinite(q)) else float("nan")
            p = tt.t_mm / 1000.0
            err = tt.error_mm
            if n > 0 and is_finite_pose(p, q / n, 1e-6) and abs(n - 1.0) < 1e-2 and np.isfinite(err or 0.0):
                s.visible = True
                s.position_m = p
                s.quat_xyzw = q / n
                s.fit_error_m = float(err) / 1000.0 if err is not None else -1.0
                if tt.markers_mm is not None:
                    s.markers = len(tt.markers_mm)
            else:
                self.counters.bad_poses += 1
        return s

    # -- main loop ------------------------------------------------------------------------------
    def start(self) -> threading.Thread:
        self._stop.clear()
        self._thread = threading.Thread(target=self.run, name="ndi-driver", daemon=True)
        self._thread.start()
        return self._thread

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)

    def run(self) -> None:
        backoff = 0.0
        first = True
        while not self._stop.is_set():
            try:
                self.connect()
                if not first:
                    self.counters.reconnects += 1
                if self._lost_at is not None:
                    self.reconnect_log.append((self._lost_at, time.monotonic_ns()))
                    self._lost_at = None
                first = False
                backoff = 0.0
                self._poll_loop()
            except (NdiError, OSError) as e:
                if self._stop.is_set():
                    break
                self.last_error = str(e)
                if self.state == "tracking":
                    self.counters.link_losses += 1
                    self._lost_at = time.monotonic_ns()
                    log.warning("NDI link lost: %s", e)
                else:
                    log.info("NDI bring-up failed: %s", e)
                if not first and self._lost_at is None:
                    self._lost_at = time.monotonic_ns()
                self._set_state("reconnecting", str(e))
                if self.client is not None:
                    self.client.t.close()
                if self._stop.wait(backoff):
                    break
                backoff = min(self.cfg.backoff_max_s, max(self.cfg.backoff_initial_s, backoff * 2))
        self.shutdown()

    def _poll_loop(self) -> None:
        """Poll phase-locked to the device frames.

        Requests follow an absolute time grid (no drift from sleep overshoot) whose step is the
        frame period (or the configured poll period, if longer) shortened by 0.1 %, so the
        phase creeps earlier until a poll sees a repeated frame number; that one is re-polled a
        fifth of a period later, which re-anchors the grid just after the device's frame
        boundary. This follows device clocks up to 1000 ppm fast. ``rate_hz = 0`` polls back
        to back.
        """
        period = 1.0 / self.cfg.rate_hz if self.cfg.rate_hz > 0 else 0.0
        frame_period = 1.0 / self.cfg.frame_rate_hz
        step = max(period, frame_period) * 0.999
        target = time.monotonic()
        while not self._stop.is_set():
            fr = self.poll_once()
            if fr is not None and self.on_frame is not None:
                try:
                    self.on_frame(fr)
                except Exception:  # noqa: BLE001 - a consumer bug must not take the link down
                    log.exception("frame callback failed")
            if not period:
                continue
            now = time.monotonic()
            if fr is None:
                target = now + 0.2 * frame_period
            else:
                target += step
                if target < now - frame_period:  # fell far behind (e.g. retries): restart the grid
                    target = now
            delay = target - now
            if delay > 0 and self._stop.wait(delay):
                break
