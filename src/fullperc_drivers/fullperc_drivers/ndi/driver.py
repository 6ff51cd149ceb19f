"""ROS-free NDI tracking driver: command client, device-to-host time mapping, and the
connect / load tools / poll / reconnect state machine.

Bring-up (reference/ndi.md §2.1): open link (serial: probe with INIT at 9600, else break and wait
for RESET; then COMM to the configured rate, host switches after OKAY) -> ``INIT`` -> ``VER:0``
-> optional ``SET:Param.Tracking.Selected Volume=n`` -> ``PHSR:01`` + ``PHF`` for stale handles ->
per tool ``PHRQ:*********1****``, ``PVWR`` in 64-byte chunks, ``PINIT``, ``PENA`` -> ``PHSR:04``
check -> ``TSTART`` -> poll ``BX``/``TX`` at the configured rate -> ``TSTOP`` on shutdown.

Errors: a CRC error, a garbled reply or a read timeout is counted, the input is drained and the
request repeated (``max_retries`` times); after that, or when the link drops, the driver closes
the link, backs off (0 s first, then doubling up to ``backoff_max_s``; the back-off restarts from 0
only after a bring-up delivered a frame, so a link that comes up and fails at once is not hammered)
and runs the whole bring-up again (the tools are re-loaded). The driver never hands out a
non-finite pose: a tool whose transform is not finite/unit is reported as not visible, with the
reason in :attr:`ToolSample.refused`, and counted in ``bad_poses``.

Tools the device refuses: an ``ERRORxx`` answer to a tool's PHRQ, PVWR, PINIT or PENA (or a tool
that PHSR does not list as enabled) refuses that tool only: its handle is freed, the refusal is
reported (``on_event`` ``tool_refused``, :attr:`NdiDriver.refused`) and the other tools are
tracked. Only when the device refuses every tool does the bring-up fail (and retry with back-off).
ROM files are checked before anything is sent (:meth:`ToolConfig.from_file`: :class:`RomFileError`).

Threading: :meth:`start` runs :meth:`run` in a thread that calls ``on_frame`` and ``on_event``
(both must not block or raise: the node puts them into a hand-off queue); :meth:`stop` joins it.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fullperc_common.transforms import is_finite_pose

from . import replies as R
from .client import Counters, NdiClient, NdiTimeout  # noqa: F401 (NdiTimeout re-exported)
from .frame_clock import FrameClock
from .protocol import ERROR_CODES, NdiDeviceError, NdiError, NdiProtocolError, parse_okay
from .rom import RomFileError, read_rom
from .transport import NdiLinkError, SerialTransport, TcpTransport, Transport, baud_code

# the poll grid's step is shortened by this share of a period until it reaches the frame boundary (_poll_loop)
ACQUIRE_CREEP = 0.05

log = logging.getLogger("fullperc.ndi")


# ----------------------------------------------------------------------------------------------
# The driver


@dataclass
class ToolConfig:
    name: str
    rom: bytes
    priority: str = "D"  # PENA: S static/reference, D dynamic, B button box
    source: str = ""  # where the ROM came from (a file path), for messages

    @classmethod
    def from_file(cls, name: str, path: str | Path, priority: str = "D") -> ToolConfig:
        """Read and check a ROM file; :class:`RomFileError` (naming tool and file) if it is not a tool definition."""
        try:
            data = Path(path).read_bytes()
        except OSError as e:
            raise RomFileError(f"tool '{name}': cannot read ROM file {path}: {e.strerror or e}") from e
        try:
            read_rom(data)
        except NdiProtocolError as e:
            raise RomFileError(f"tool '{name}': ROM file {path} rejected ({len(data)} bytes): {e}") from e
        return cls(name, data, priority, str(path))

    @property
    def label(self) -> str:
        return f"'{self.name}'" + (f" (ROM {self.source})" if self.source else "")


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
    backoff_max_s: float = 0.5  # a device back after an outage is found within this (+ one bring-up); an attempt
    #                             is one TCP connect or a serial INIT probe, cheap at 2 per second (2.0 until 2026-12)
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
    refused: str = ""  # why a transform the device reported was not handed out ("" = not refused)


@dataclass
class DriverEvent:
    """What the driver thread reports besides frames (the node logs these and feeds its health ladder).

    ``kind`` ``state``: ``state`` is connecting | configuring | tracking | reconnecting | stopped, ``detail``
    the reason or summary; on ``tracking``, ``tools`` are the tools the device accepted; on ``reconnecting``,
    ``link_lost`` says whether the link had been tracking (else a bring-up attempt failed).
    ``kind`` ``tool_refused``: ``tool`` (its :attr:`ToolConfig.label` in ``detail``) was refused by the device.
    """

    kind: str
    state: str = ""
    detail: str = ""
    tool: str = ""
    tools: tuple[str, ...] = ()
    link_lost: bool = False


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
                 transport: Transport | None = None,
                 on_event: Callable[[DriverEvent], None] | None = None) -> None:
        config.validate()
        self.cfg = config
        self.on_frame = on_frame
        self.on_state = on_state
        self.on_event = on_event
        self.refused: dict[str, str] = {}  # tool -> why the device refused it (last bring-up)
        self._frames_since_connect = 0
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
        self._dup_run = 0
        # Liveness record of reconnects: (lost at, tracking again at), time.monotonic_ns().
        self.reconnect_log: list[tuple[int, int]] = []
        self._lost_at: int | None = None
        self._lock = threading.Lock()

    # -- state ----------------------------------------------------------------------------------
    def _set_state(self, state: str, detail: str = "", **kw) -> None:
        self.state, self.state_detail = state, detail
        if self.on_state:
            try:
                self.on_state(state, detail)
            except Exception:  # noqa: BLE001 - a callback must not kill the driver
                log.exception("state callback failed")
        self._emit(DriverEvent("state", state, detail, **kw))

    def _emit(self, ev: DriverEvent) -> None:
        if self.on_event:
            try:
                self.on_event(ev)
            except Exception:  # noqa: BLE001 - a callback must not kill the driver
                log.exception("event callback failed")

    def _refuse(self, tool: ToolConfig, why: str) -> None:
        self.refused[tool.name] = why
        log.warning("NDI tool %s %s", tool.label, why)
        self._emit(DriverEvent("tool_refused", detail=why, tool=tool.name))

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
        self.refused = {}
        for tool in cfg.tools:
            step, h = "PHRQ", None
            try:
                h = c.phrq()
                step = "PVWR"
                c.pvwr(h, tool.rom, cfg.pvwr_pad_to)
                self.handles[tool.name] = h
            except NdiDeviceError as e:
                self._refuse_and_free(c, tool, h, step, e)
        for tool in cfg.tools:
            h = self.handles.get(tool.name)
            if h is None:
                continue
            step = "PINIT"
            try:
                c.pinit(h)
                step = "PENA"
                c.pena(h, tool.priority)
            except NdiDeviceError as e:
                self._refuse_and_free(c, tool, h, step, e)
        enabled = {h for h, st in c.phsr(0x04) if st & R.PHSR_ENABLED}
        for tool in cfg.tools:
            h = self.handles.get(tool.name)
            if h is not None and h not in enabled:
                self._refuse_and_free(c, tool, h, "PHSR", None)
        if not self.handles:
            raise NdiLinkError("the device refused every tool: "
                               + "; ".join(f"{n}: {why}" for n, why in self.refused.items()))
        c.tstart()
        self.clock.reset()
        self._last_frame = None
        self._frames_since_connect = 0
        self._dup_run = 0
        detail = f"{len(self.handles)} tools, firmware '{self.firmware}'"
        if self.refused:
            detail = f"{len(self.handles)} of {len(cfg.tools)} tools (refused: {', '.join(self.refused)}), " \
                     f"firmware '{self.firmware}'"
        self._set_state("tracking", detail, tools=tuple(self.handles))

    def _refuse_and_free(self, c: NdiClient, tool: ToolConfig, h: int | None, step: str,
                         e: NdiDeviceError | None) -> None:
        """The device refused ``tool`` at ``step``: report it by name, free its handle, go on with the others."""
        if e is None:
            why = "not enabled after PENA (PHSR)"
        else:
            why = f"{step} answered ERROR{e.code:02X} ({ERROR_CODES.get(e.code, 'unrecognized error code')})"
        self.handles.pop(tool.name, None)
        self._refuse(tool, f"refused by the device: {why}")
        if h is not None:
            try:
                c.phf(h)
            except NdiDeviceError as fe:
                log.info("PHF %02X after the refusal of %s failed: %s", h, tool.name, fe)

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
            try:
                c.comm(self.cfg.baud, retry=False)
            except (NdiLinkError, NdiProtocolError) as e:
                # The OKAY was garbled or lost on its way back, so the device has most likely switched: COMM again
                # at 9600 would talk to a device at the new rate (silence: three read timeouts, then a reconnect).
                # INIT at the new rate below tells; if the device did not switch, it fails and the reconnect's
                # probe at 9600 (else break -> RESET) starts over. An ERROR reply (rate refused) still raises.
                log.info("NDI COMM reply not read (%s); trying the new rate", e)
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
                try:   # leave the device at its default rate; once: a garbled OKAY repeated at the old rate would
                    # talk to a device already at 9600 (three read timeouts for nothing)
                    c.comm(9600, retry=False)
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
            self._dup_run += 1
            return None
        self._dup_run = 0
        if self._last_frame is not None and 1 < fno - self._last_frame <= self.clock.max_jump:
            # frames the device measured and nobody read (BX answers the newest frame): a consumer that counts
            # frame-number gaps downstream (fusion_node's lost samples) sees these too, and cannot tell them from
            # messages lost on the way; this counter says how many were never read
            self.counters.skipped_frames += fno - self._last_frame - 1
        self._last_frame = fno
        self._frames_since_connect += 1
        stamp = self.clock.stamp(fno, recv)
        by_h = data.by_handle()
        tools: dict[str, ToolSample] = {}
        for tool in self.cfg.tools:  # every configured tool, a refused one as not visible
            h = self.handles.get(tool.name)
            tt = by_h.get(h) if h is not None else None
            tools[tool.name] = self._sample(tool.name, tt, fno)
        return FrameResult(stamp, recv, fno, data.system_status, tools)

    @property
    def last_frame_number(self) -> int | None:
        return self._last_frame

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
                s.refused = "non-finite or non-unit transform"
        return s

    # -- main loop ------------------------------------------------------------------------------
    def start(self) -> threading.Thread:
        self._stop.clear()
        self._thread = threading.Thread(target=self.run, name="ndi-driver", daemon=True)
        self._thread.start()
        return self._thread

    def stop(self, timeout: float = 5.0) -> None:
        """Stop polling, TSTOP and close the link, and join the thread: no callback runs after this returns
        (unless the thread is stuck longer than ``timeout``)."""
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
                self._poll_loop()
            except (NdiError, OSError) as e:
                if self._stop.is_set():
                    break
                self.last_error = str(e)
                lost = self.state == "tracking"
                if lost:
                    self.counters.link_losses += 1
                    self._lost_at = time.monotonic_ns()
                    log.warning("NDI link lost: %s", e)
                else:
                    log.info("NDI bring-up failed: %s", e)
                if not first and self._lost_at is None:
                    self._lost_at = time.monotonic_ns()
                if self._frames_since_connect:
                    backoff = 0.0  # the link worked: come back at once
                self._frames_since_connect = 0
                self._set_state("reconnecting", str(e), link_lost=lost)
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

        Acquisition: from a connect until the first repeated frame (at most ``1 / ACQUIRE_CREEP``
        polls) the step is shortened by ``ACQUIRE_CREEP`` instead, so the grid reaches the frame
        boundary within a third of a second. Why: the frame clock stamps a frame at the earliest
        its replies came after the frame boundary (:class:`FrameClock`), so until the grid is at the
        boundary every stamp is late by the poll's phase. At 0.1 % a grid that started a whole frame
        off took 1,000 frames (17 s at 60 Hz) to get there, with stamps up to a frame period late
        meanwhile: the demo's walking instrument, right after the Vega came back from an outage,
        had its raw Vega chain 0.62 mm off its truth (6 ms x its speed) against 0.18 mm.
        """
        period = 1.0 / self.cfg.rate_hz if self.cfg.rate_hz > 0 else 0.0
        frame_period = 1.0 / self.cfg.frame_rate_hz
        step = max(period, frame_period) * 0.999
        acquire_step = max(period, frame_period) * (1.0 - ACQUIRE_CREEP)
        acquiring = math.ceil(1.0 / ACQUIRE_CREEP)   # polls left in acquisition (0: locked)
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
                # a repeated frame: re-poll a fifth of a period later; a device that keeps repeating one
                # frame number for a second (frozen) is polled at the frame rate, not five times faster
                target = now + (frame_period if self._dup_run > self.cfg.frame_rate_hz else 0.2 * frame_period)
                acquiring = 0
            else:
                target += acquire_step if acquiring else step
                acquiring = max(0, acquiring - 1)
                if target < now - frame_period:  # fell far behind (e.g. retries): restart the grid
                    target = now
            delay = target - now
            if delay > 0 and self._stop.wait(delay):
                break
