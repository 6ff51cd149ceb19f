"""A byte-exact NDI Polaris Vega emulator (TCP, and a pty for the serial Spectra/Vicra path).

It speaks the Combined API as in reference/ndi.md, reusing the protocol core of
``fullperc_drivers.ndi``: both command forms (``CMD:params+CRC`` and ``CMD params``; a wrong CRC
is answered ``ERROR04``), lowercase hex parameters, handle state (PHRQ -> PVWR -> PINIT -> PENA, so
``PHSR:00..04`` answer as a real device does), .rom uploads, TSTART/TSTOP, BX and TX (options 0001,
0008, 0800), VER, APIREV, GET/GETINFO/SET, PHINF, COMM (serial rate switch after ``OKAY``), RESET,
BEEP, ECHO. BX2/STREAM are not emulated (``ERROR01``). It binds 127.0.0.1 by default.

Pose source API (used by the simulator)::

    VegaEmulator(pose_source=f, tools={"tool": rom_bytes, ...}, frame_rate_hz=60)
    f(t_host_ns: int) -> dict[str, ToolPose | None]

``f`` is called once per device frame with that frame's capture time on the host clock
(``time.time_ns()`` domain); ``ToolPose(position_mm, quat_xyzw, error_mm=0.1, markers_mm=None)``
is the tool's pose in the ``ots`` frame, i.e. the NDI camera frame, where the measurement volume
lies at negative z (a tool in front of the camera has z ~ -950 .. -2400 mm). ``quat_xyzw`` is ROS
order; the emulator converts to NDI's scalar-first order on the wire. ``None`` (or a missing key)
means the tool is not visible: MISSING. A pose outside ``frustum`` is also MISSING (with reply
option 0800 it is reported, port status 0x40 "out of volume"). ``frustum`` is a :class:`Frustum`
or any callable mapping (N, 3) mm points to a bool array. A ROM uploaded by the host is matched
to a tool by its bytes (zero padding ignored) or, failing that, by its part number; an unknown
but well-formed ROM loads fine and is always MISSING.

Frame numbers count at ``frame_rate_hz`` from emulator start (``TSTART:80`` resets them); all
handles of one reply share the frame number.

Fault injection (:class:`FaultConfig`): corrupt a reply's CRC with probability p, prepend garbage
bytes, delay replies, and drop the link every N seconds (TCP: close every client socket; serial:
the device power-cycles back to 9600 baud and is silent for ``drop_silence_s``).

Serial over a pty: :meth:`VegaEmulator.open_pty` returns the slave path for pyserial. The emulated
device checks the host's line rate (the pty's termios) and ignores bytes sent at the wrong rate,
like a UART producing framing errors. A serial break cannot be seen through a pty, so closing the
port (hang-up) is treated as the break a host sends before reconnecting: the device resets to
9600 baud.

Executable ``vega_emulator``: see :func:`main` (``--help``).
"""

from __future__ import annotations

import argparse
import math
import os
import random
import select
import signal
import socket
import sys
import termios
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fullperc_common.transforms import quat_xyzw_to_wxyz
from fullperc_drivers.ndi import replies as R
from fullperc_drivers.ndi.protocol import (
    NdiCrcError,
    NdiProtocolError,
    decode_command,
    encode_ascii_reply,
    encode_binary_reply,
    is_hex,
)
from fullperc_drivers.ndi.rom import read_rom
from fullperc_drivers.ndi.transport import COMM_CODE_BAUD


@dataclass
class ToolPose:
    """A tool pose in the ``ots`` frame (NDI camera frame)."""

    position_mm: np.ndarray
    quat_xyzw: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 0.0, 1.0]))
    error_mm: float = 0.1
    markers_mm: np.ndarray | None = None  # (n, 3) in the ots frame, for reply option 0008


PoseSource = Callable[[int], dict[str, "ToolPose | None"]]


@dataclass
class Frustum:
    """Pyramid measurement volume in the NDI camera frame: along -z from ``near_mm`` to ``far_mm``.

    Defaults: the Polaris pyramid's 950-2400 mm depth (ndi.md §7.1); the half-angles are our
    nominal choice (the Vega lateral extents are UNCERTAIN in ndi.md) — configure them.
    """

    near_mm: float = 950.0
    far_mm: float = 2400.0
    half_angle_x_deg: float = 18.0
    half_angle_y_deg: float = 15.0

    def __call__(self, p_mm: np.ndarray) -> np.ndarray:
        p = np.atleast_2d(np.asarray(p_mm, dtype=float))
        d = -p[:, 2]
        return ((d >= self.near_mm) & (d <= self.far_mm)
                & (np.abs(p[:, 0]) <= d * math.tan(math.radians(self.half_angle_x_deg)))
                & (np.abs(p[:, 1]) <= d * math.tan(math.radians(self.half_angle_y_deg))))


@dataclass
class FaultConfig:
    corrupt_crc_prob: float = 0.0  # per reply
    garbage_prob: float = 0.0  # per reply: random bytes before it
    delay_prob: float = 0.0  # per reply
    delay_s: float = 0.0
    drop_every_s: float | None = None  # drop the link periodically
    drop_silence_s: float = 0.1  # serial: device silent after a drop (power cycle)
    seed: int | None = None


@dataclass
class _Handle:
    rom: bytearray = field(default_factory=lambda: bytearray(1024))
    written: bool = False
    initialized: bool = False
    enabled: bool = False
    priority: str = "D"
    tool: str | None = None  # matched tool name
    part_number: str = ""

    @property
    def phsr_status(self) -> int:
        s = 0
        if self.written:
            s |= R.PHSR_OCCUPIED
        if self.initialized:
            s |= R.PHSR_INITIALIZED
        if self.enabled:
            s |= R.PHSR_ENABLED
        return s


class DeviceError(Exception):
    def __init__(self, code: int) -> None:
        super().__init__(f"ERROR{code:02X}")
        self.code = code


class VegaDevice:
    """The device state machine: one command line in, one complete reply (with CRC) out."""

    def __init__(self, tools: dict[str, bytes], pose_source: PoseSource | None = None,
                 frame_rate_hz: float = 60.0, frustum: Callable | None = None,
                 freeze_tag: str = "Polaris Vega 010", max_handles: int = 24,
                 frame_start: int = 1000, serial_number: str = "P9-00042") -> None:
        self.tools = {n: bytes(r) for n, r in tools.items()}
        self._tool_parts = {}
        for n, r in self.tools.items():
            try:
                self._tool_parts[read_rom(r).part_number] = n
            except NdiProtocolError:
                pass
        self.pose_source = pose_source or (lambda t: {})
        self.frame_rate_hz = float(frame_rate_hz)
        self.frustum = frustum if frustum is not None else Frustum()
        self.freeze_tag = freeze_tag
        self.max_handles = max_handles
        self.serial_number = serial_number
        self.frame_start = frame_start
        self.lock = threading.RLock()
        self.t0_ns = time.time_ns()
        self.serial_baud = 9600
        self.pending_baud: int | None = None
        self.commands: list[str] = []  # log of command names received (for tests)
        self.params = {
            "Features.Firmware.Version": ("G.003.004", False),
            "Features.Hardware.Serial Number": (serial_number, False),
            "Device.Type": ("Polaris Vega ST", False),
            "Param.Tracking.Available Volumes": ("Pyramid;Extended Pyramid", False),
            "Param.Tracking.Selected Volume": ("0", True),
            "Param.Tracking.Frame Frequency": (f"{frame_rate_hz:g}", False),
            "Param.Tracking.Track Frequency": ("2", True),
            "Param.Tracking.Illuminator Rate": ("2", True),
        }
        self._frame_cache: tuple[int, dict] | None = None
        self.reset()

    # -- state ----------------------------------------------------------------------------------
    def reset(self) -> None:
        """Power-up / break state: not initialized, no handles, 9600 baud."""
        with self.lock:
            self.initialized = False
            self.tracking = False
            self.handles: dict[int, _Handle] = {}
            self.serial_baud = 9600
            self.pending_baud = None

    def frame_number(self, now_ns: int | None = None) -> int:
        now = time.time_ns() if now_ns is None else now_ns
        return self.frame_start + int((now - self.t0_ns) * self.frame_rate_hz // 1e9)

    def frame_time_ns(self, frame: int) -> int:
        return self.t0_ns + int(round((frame - self.frame_start) * 1e9 / self.frame_rate_hz))

    def poses_for_frame(self, frame: int) -> dict:
        if self._frame_cache is None or self._frame_cache[0] != frame:
            self._frame_cache = (frame, dict(self.pose_source(self.frame_time_ns(frame)) or {}))
        return self._frame_cache[1]

    def loaded_rom(self, handle: int) -> bytes:
        return bytes(self.handles[handle].rom)

    # -- dispatch -------------------------------------------------------------------------------
    def handle_line(self, line: bytes) -> bytes:
        """Reply bytes (ASCII with CRC+CR, or a binary frame) to one command line."""
        with self.lock:
            try:
                cmd = decode_command(line)
            except NdiCrcError:
                return encode_ascii_reply("ERROR04")
            except NdiProtocolError:
                return encode_ascii_reply("ERROR01")
            self.commands.append(cmd.name)
            fn = getattr(self, f"_cmd_{cmd.name}", None)
            if fn is None:
                return encode_ascii_reply("ERROR01")
            try:
                out = fn(cmd.params)
            except DeviceError as e:
                return encode_ascii_reply(f"ERROR{e.code:02X}")
            if isinstance(out, bytes):  # binary body
                return encode_binary_reply(out)
            return encode_ascii_reply(out)

    def _need_init(self) -> None:
        if not self.initialized:
            raise DeviceError(0x10)

    def _need_setup_mode(self) -> None:
        self._need_init()
        if self.tracking:
            raise DeviceError(0x0C)

    def _handle(self, txt: str) -> tuple[int, _Handle]:
        if len(txt) < 2 or not is_hex(txt[:2]):
            raise DeviceError(0x07)
        h = int(txt[:2], 16)
        if h not in self.handles:
            raise DeviceError(0x08)
        return h, self.handles[h]

    # -- commands -------------------------------------------------------------------------------
    def _cmd_INIT(self, p: str) -> str:
        self.initialized = True
        self.tracking = False
        self.handles = {}
        return "OKAY"

    def _cmd_RESET(self, p: str) -> str:
        baud = self.serial_baud
        self.reset()
        self.serial_baud = baud  # the reply still goes out at the current rate
        self.pending_baud = 9600
        return "RESET"

    def _cmd_COMM(self, p: str) -> str:
        if len(p) != 5:
            raise DeviceError(0x07)
        baud = COMM_CODE_BAUD.get(p[0].upper())
        if baud is None or any(c not in "01" for c in p[1:]) or p[1] == "1":
            raise DeviceError(0x06)
        self.pending_baud = baud  # applied by the serial link after this reply is sent
        return "OKAY"

    def _cmd_VER(self, p: str) -> str:
        opt = int(p) if p.isdigit() else 0
        if opt == 5:
            return "010"
        if opt not in (0, 3, 4):
            raise DeviceError(0x23)
        return ("Type of Firmware: Polaris Vega Control Firmware\n"
                f"NDI S/N: {self.serial_number}\n"
                "Characterization Date: 2021-03-04\n"
                f"Freeze Tag: {self.freeze_tag}\n"
                "Freeze Date: 2021-01-15\n"
                "(C) Copyright 2021 fullperc emulator (not NDI firmware)")

    def _cmd_APIREV(self, p: str) -> str:
        return "G.003.004"

    def _select_params(self, name: str) -> list[str]:
        if name.endswith("*"):
            keys = [k for k in self.params if k.startswith(name[:-1])]
        else:
            keys = [k for k in self.params if k == name]
        if not keys:
            raise DeviceError(0x34)
        return keys

    def _cmd_GET(self, p: str) -> str:
        return "\n".join(f"{k}={self.params[k][0]}" for k in self._select_params(p.strip()))

    def _cmd_GETINFO(self, p: str) -> str:
        out = []
        for k in self._select_params(p.strip()):
            v, rw = self.params[k]
            out.append(f"{k}={v};0;{'0' if rw else '1'};0;0;;emulated parameter {k} (fullperc Vega emulator)")
        return "\n".join(out)

    def _cmd_SET(self, p: str) -> str:
        if "=" not in p:
            raise DeviceError(0x07)
        name, value = p.split("=", 1)
        if name not in self.params:
            raise DeviceError(0x34)
        if not self.params[name][1]:
            raise DeviceError(0x39)
        if name == "Param.Tracking.Selected Volume" and value not in ("0", "1"):
            raise DeviceError(0x36)
        if name in ("Param.Tracking.Track Frequency", "Param.Tracking.Illuminator Rate") and value not in "012":
            raise DeviceError(0x36)
        self.params[name] = (value, True)
        return "OKAY"

    def _cmd_BEEP(self, p: str) -> str:
        if not (p.isdigit() and 1 <= int(p) <= 9):
            raise DeviceError(0x23)
        return "1"

    def _cmd_ECHO(self, p: str) -> str:
        return p

    def _cmd_LED(self, p: str) -> str:
        self._handle(p)
        if len(p) != 4 or p[2] not in "123":
            raise DeviceError(0x0A)
        if p[3] not in "BFS":
            raise DeviceError(0x0B)
        return "OKAY"

    def _cmd_IRATE(self, p: str) -> str:
        return "OKAY"

    def _cmd_VSEL(self, p: str) -> str:
        return "OKAY"

    def _cmd_PHSR(self, p: str) -> str:
        opt = int(p, 16) if p and is_hex(p) else 0
        if opt > 4:
            raise DeviceError(0x23)
        sel = []
        for h, st in sorted(self.handles.items()):
            ok = {0: True,
                  1: not st.written,  # allocated but never given a tool: to be freed
                  2: st.written and not st.initialized,
                  3: st.initialized and not st.enabled,
                  4: st.enabled}[opt]
            if ok:
                sel.append((h, st.phsr_status))
        return R.format_phsr(sel)

    def _cmd_PHF(self, p: str) -> str:
        if len(p) < 2 or not is_hex(p[:2]):
            raise DeviceError(0x07)
        h = int(p[:2], 16)
        if h not in self.handles:
            raise DeviceError(0x2B)
        del self.handles[h]
        return "OKAY"

    def _cmd_PHRQ(self, p: str) -> str:
        self._need_setup_mode()
        if len(p) != 14:
            raise DeviceError(0x07)
        if p[9] not in "1*" or p[10:12] not in ("**", "00"):
            raise DeviceError(0x2F)  # only wireless (passive) tools exist on this device
        for h in range(1, 256):
            if h not in self.handles:
                break
        if len(self.handles) >= self.max_handles:
            raise DeviceError(0x2D)
        self.handles[h] = _Handle()
        return f"{h:02X}"

    def _cmd_PVWR(self, p: str) -> str:
        self._need_setup_mode()
        h, st = self._handle(p)
        if len(p) != 2 + 4 + 128 or not is_hex(p):
            raise DeviceError(0x07)
        addr = int(p[2:6], 16)
        if addr % 64 or addr + 64 > 1024:
            raise DeviceError(0x23)
        st.rom[addr:addr + 64] = bytes.fromhex(p[6:])
        st.written = True
        st.initialized = st.enabled = False
        return "OKAY"

    def _match_tool(self, rom: bytes) -> tuple[str | None, str]:
        info = read_rom(rom)  # NdiProtocolError if not a tool definition
        for name, ref in self.tools.items():
            if rom[:len(ref)] == ref and not any(rom[len(ref):]):
                return name, info.part_number
        return self._tool_parts.get(info.part_number), info.part_number

    def _cmd_PINIT(self, p: str) -> str:
        self._need_setup_mode()
        h, st = self._handle(p)
        if not st.written:
            raise DeviceError(0x0D)
        try:
            st.tool, st.part_number = self._match_tool(bytes(st.rom))
        except NdiProtocolError:
            raise DeviceError(0x0D) from None  # what a Vega says to a bad ROM (SKS #50)
        st.initialized = True
        return "OKAY"

    def _cmd_PENA(self, p: str) -> str:
        self._need_setup_mode()
        h, st = self._handle(p)
        if len(p) != 3 or p[2] not in "SDB":
            raise DeviceError(0x09)
        if not st.initialized:
            raise DeviceError(0x0E)
        st.enabled, st.priority = True, p[2]
        return "OKAY"

    def _cmd_PDIS(self, p: str) -> str:
        self._need_setup_mode()
        h, st = self._handle(p)
        if not st.enabled:
            raise DeviceError(0x0F)
        st.enabled = False
        return "OKAY"

    def _cmd_PHINF(self, p: str) -> str:
        h, st = self._handle(p)
        opt = int(p[2:6], 16) if len(p) >= 6 and is_hex(p[2:6]) else 0x0001
        if not st.written:
            return "UNOCCUPIED"
        out = ""
        if opt & 0x0001:
            port = 0x01 | (0x10 if st.initialized else 0) | (0x20 if st.enabled else 0)
            main_type = "01" if st.priority == "S" else "02"  # reference / probe
            out += f"{main_type}000000" + "NDI".ljust(12) + "000" + "00000000" + f"{port:02X}"
        if opt & 0x0002:
            out += "00000000"
        if opt & 0x0004:
            out += st.part_number.ljust(20)[:20] if st.part_number else (read_rom_safe(st.rom).ljust(20)[:20])
        if opt & 0x0008:
            out += "00"
        if opt & 0x0010:
            out += "00"
        if opt & 0x0020:  # device no. (8), system 0 = Polaris, 1 = wireless, port, channel
            out += "00000000" + "0" + "1" + f"{h:02X}" + "00"
        if opt & 0x0040:
            out += "00"
        return out

    def _cmd_TSTART(self, p: str) -> str:
        self._need_init()
        if self.tracking:
            raise DeviceError(0x0C)
        if p.strip() == "80":
            self.t0_ns = time.time_ns()
            self._frame_cache = None
        self.tracking = True
        return "OKAY"

    def _cmd_TSTOP(self, p: str) -> str:
        self._need_init()
        if not self.tracking:
            raise DeviceError(0x0C)
        self.tracking = False
        return "OKAY"

    def _tracking(self, p: str) -> tuple[R.TrackingData, int]:
        self._need_init()
        if not self.tracking:
            raise DeviceError(0x0C)
        if p and (not is_hex(p) or len(p) > 4):
            raise DeviceError(0x07)
        opt = int(p, 16) if p else R.OPT_TRANSFORMS
        if opt & ~R.SUPPORTED_OPTIONS:
            raise DeviceError(0x23)
        return self.tracking_data(opt), opt

    def tracking_data(self, options: int = R.OPT_TRANSFORMS, now_ns: int | None = None) -> R.TrackingData:
        frame = self.frame_number(now_ns)
        poses = self.poses_for_frame(frame)
        tools = []
        for h, st in sorted(self.handles.items()):
            if not st.enabled:
                continue
            port = R.PORT_OCCUPIED | R.PORT_INITIALIZED | R.PORT_ENABLED
            pose = poses.get(st.tool) if st.tool else None
            t = R.ToolTransform(h, "missing", port_status=port, frame_number=frame)
            if pose is not None:
                p = np.asarray(pose.position_mm, dtype=float)
                inside = bool(np.asarray(self.frustum(p.reshape(1, 3))).reshape(-1)[0])
                if inside or options & R.OPT_NOT_NORMALLY_REPORTED:
                    t.status = "valid"
                    t.q_wxyz = quat_xyzw_to_wxyz(np.asarray(pose.quat_xyzw, dtype=float))
                    t.t_mm = p
                    t.error_mm = float(pose.error_mm)
                    if not inside:
                        t.port_status |= R.PORT_OUT_OF_VOLUME
                    if pose.markers_mm is not None:
                        t.markers_mm = np.asarray(pose.markers_mm, dtype=float).reshape(-1, 3)
            tools.append(t)
        return R.TrackingData(tools, 0)

    def _cmd_BX(self, p: str) -> bytes:
        data, opt = self._tracking(p)
        return R.format_bx(data, opt)

    def _cmd_TX(self, p: str) -> str:
        data, opt = self._tracking(p)
        return R.format_tx(data, opt)


def read_rom_safe(rom: bytes) -> str:
    try:
        return read_rom(bytes(rom)).part_number
    except NdiProtocolError:
        return ""


# ----------------------------------------------------------------------------------------------
# Links: TCP server and pty


@dataclass
class EmulatorStats:
    connections: int = 0
    commands: int = 0
    replies: int = 0
    corrupted: int = 0
    garbage: int = 0
    delayed: int = 0
    drops: int = 0
    rx_wrong_baud: int = 0  # serial bytes discarded because the host was at another rate


class VegaEmulator:
    """TCP server (and optional pty) around one :class:`VegaDevice`, with fault injection."""

    def __init__(self, pose_source: PoseSource | None = None, tools: dict[str, bytes] | None = None,
                 frame_rate_hz: float = 60.0, host: str = "127.0.0.1", port: int = 0,
                 faults: FaultConfig | None = None, **device_kw) -> None:
        self.device = VegaDevice(tools or {}, pose_source, frame_rate_hz, **device_kw)
        self.host = host
        self.port = port
        self.faults = faults or FaultConfig()
        self.stats = EmulatorStats()
        self._rng = random.Random(self.faults.seed)
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._clients: set[socket.socket] = set()
        self._clients_lock = threading.Lock()
        self._server: socket.socket | None = None
        self._pty_master: int | None = None
        self.pty_path: str | None = None
        self._serial_silent_until = 0.0
        self.drop_times: list[float] = []

    # -- lifecycle ------------------------------------------------------------------------------
    def start(self, tcp: bool = True) -> VegaEmulator:
        if tcp:
            srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            srv.bind((self.host, self.port))
            srv.listen(8)
            srv.settimeout(0.2)
            self._server = srv
            self.port = srv.getsockname()[1]
            self._spawn(self._accept_loop, "vega-accept")
        if self.faults.drop_every_s:
            self._spawn(self._drop_loop, "vega-drop")
        return self

    def __enter__(self) -> VegaEmulator:
        return self.start() if self._server is None and not self._threads else self

    def __exit__(self, *exc) -> None:
        self.stop()

    def stop(self) -> None:
        self._stop.set()
        if self._server is not None:
            self._server.close()
        self._close_clients()
        for t in self._threads:
            t.join(2.0)
        if self._pty_master is not None:
            os.close(self._pty_master)
            self._pty_master = None

    def _spawn(self, fn, name: str, *args) -> threading.Thread:
        t = threading.Thread(target=fn, args=args, name=name, daemon=True)
        t.start()
        self._threads.append(t)
        return t

    # -- faults ---------------------------------------------------------------------------------
    def _apply_faults(self, reply: bytes) -> tuple[bytes, float]:
        f = self.faults
        delay = 0.0
        rng = self._rng
        if f.corrupt_crc_prob and rng.random() < f.corrupt_crc_prob:
            self.stats.corrupted += 1
            b = bytearray(reply)
            if b[:2] == b"\xc4\xa5":
                b[-1] ^= 0x5A  # body CRC high byte
            else:
                i = len(b) - 2  # last CRC digit, replaced by a different hex digit
                b[i] = ord("0") if b[i] != ord("0") else ord("1")
            reply = bytes(b)
        if f.garbage_prob and rng.random() < f.garbage_prob:
            self.stats.garbage += 1
            reply = bytes(rng.randrange(256) for _ in range(rng.randint(1, 16))) + reply
        if f.delay_prob and rng.random() < f.delay_prob:
            self.stats.delayed += 1
            delay = f.delay_s
        return reply, delay

    def drop_link(self) -> None:
        """Drop every connection now (TCP) / power-cycle the serial device."""
        self.stats.drops += 1
        self.drop_times.append(time.monotonic())
        self._close_clients()
        if self._pty_master is not None:
            self.device.reset()
            self._serial_silent_until = time.monotonic() + self.faults.drop_silence_s

    def _drop_loop(self) -> None:
        period = float(self.faults.drop_every_s or 0)
        while not self._stop.wait(period):
            self.drop_link()

    # -- TCP ------------------------------------------------------------------------------------
    def _close_clients(self) -> None:
        with self._clients_lock:
            for c in list(self._clients):
                try:
                    c.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
                c.close()
            self._clients.clear()

    def _accept_loop(self) -> None:
        assert self._server is not None
        while not self._stop.is_set():
            try:
                conn, _ = self._server.accept()
            except TimeoutError:
                continue
            except OSError:
                break
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with self._clients_lock:
                self._clients.add(conn)
            self.stats.connections += 1
            self._spawn(self._serve_tcp, "vega-client", conn)

    def _serve_tcp(self, conn: socket.socket) -> None:
        buf = bytearray()
        try:
            while not self._stop.is_set():
                try:
                    data = conn.recv(65536)
                except OSError:
                    break
                if not data:
                    break
                buf += data
                while True:
                    i = buf.find(b"\r")
                    if i < 0:
                        if len(buf) > 4096:  # no command is this long: ERROR02 and resync
                            buf.clear()
                            conn.sendall(encode_ascii_reply("ERROR02"))
                        break
                    line = bytes(buf[:i + 1])
                    del buf[:i + 1]
                    reply, delay = self._reply(line)
                    if delay:
                        time.sleep(delay)
                    conn.sendall(reply)
        except OSError:
            pass
        finally:
            with self._clients_lock:
                self._clients.discard(conn)
            conn.close()

    def _reply(self, line: bytes) -> tuple[bytes, float]:
        self.stats.commands += 1
        reply = self.device.handle_line(line)
        self.stats.replies += 1
        return self._apply_faults(reply)

    # -- serial over a pty ----------------------------------------------------------------------
    def open_pty(self, link: str | None = None) -> str:
        """Create a pty, serve the serial protocol on it, return the path to open with pyserial."""
        import tty

        master, slave = os.openpty()
        tty.setraw(master)
        tty.setraw(slave)
        path = os.ttyname(slave)
        attrs = termios.tcgetattr(slave)
        attrs[4] = attrs[5] = termios.B9600
        termios.tcsetattr(slave, termios.TCSANOW, attrs)
        os.close(slave)  # hosts open the path; a hang-up is then visible as EIO on the master
        self._pty_master = master
        self.pty_path = path
        if link:
            try:
                os.unlink(link)
            except FileNotFoundError:
                pass
            os.symlink(path, link)
        self._spawn(self._serve_pty, "vega-pty")
        return path

    def _host_baud(self) -> int | None:
        assert self._pty_master is not None
        speed = termios.tcgetattr(self._pty_master)[5]
        for name in dir(termios):
            if name.startswith("B") and name[1:].isdigit() and getattr(termios, name) == speed:
                return int(name[1:])
        return None

    def _serve_pty(self) -> None:
        fd = self._pty_master
        assert fd is not None
        buf = bytearray()
        hung_up = True
        while not self._stop.is_set() and self._pty_master is not None:
            try:
                r, _, _ = select.select([fd], [], [], 0.1)
            except (OSError, ValueError):
                break
            if not r:
                continue
            try:
                data = os.read(fd, 4096)
            except OSError:
                # No host has the port open. A host reconnecting sends a break first; a pty
                # cannot carry one, so the hang-up stands in for it: back to 9600 baud.
                if not hung_up:
                    hung_up = True
                    self.device.reset()
                    buf.clear()
                time.sleep(0.02)
                continue
            hung_up = False
            if time.monotonic() < self._serial_silent_until:
                continue
            if self._host_baud() != self.device.serial_baud:
                self.stats.rx_wrong_baud += len(data)
                continue
            buf += data
            while True:
                i = buf.find(b"\r")
                if i < 0:
                    if len(buf) > 4096:
                        buf.clear()
                    break
                line = bytes(buf[:i + 1])
                del buf[:i + 1]
                reply, delay = self._reply(line)
                if delay:
                    time.sleep(delay)
                try:
                    os.write(fd, reply)
                except OSError:
                    break
                if self.device.pending_baud is not None:
                    self.device.serial_baud = self.device.pending_baud
                    self.device.pending_baud = None
                    buf.clear()


# ----------------------------------------------------------------------------------------------
# Executable


def _default_rom_dir() -> Path:
    try:
        from ament_index_python.packages import get_package_share_directory

        return Path(get_package_share_directory("fullperc_drivers")) / "config"
    except Exception:  # noqa: BLE001 - not installed: use the source tree
        import fullperc_drivers

        return Path(fullperc_drivers.__file__).resolve().parents[1] / "config"


@dataclass
class ScriptedTool:
    """One tool of the executable's pose set: static pose, optional circle and blinking."""

    position_mm: tuple[float, float, float]
    quat_xyzw: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)
    error_mm: float = 0.1
    circle_radius_mm: float = 0.0
    circle_period_s: float = 4.0
    hidden_every_s: float = 0.0  # 0: always shown
    hidden_for_s: float = 0.0

    def pose(self, t_s: float) -> ToolPose | None:
        if self.hidden_every_s > 0 and (t_s % self.hidden_every_s) >= self.hidden_every_s - self.hidden_for_s:
            return None
        p = np.array(self.position_mm, dtype=float)
        if self.circle_radius_mm:
            a = 2 * math.pi * t_s / self.circle_period_s
            p = p + self.circle_radius_mm * np.array([math.cos(a), math.sin(a), 0.0])
        return ToolPose(p, np.array(self.quat_xyzw, dtype=float), self.error_mm)


def scripted_source(tools: dict[str, ScriptedTool], t0_ns: int | None = None) -> PoseSource:
    t0 = time.time_ns() if t0_ns is None else t0_ns

    def source(t_ns: int) -> dict[str, ToolPose | None]:
        t = (t_ns - t0) / 1e9
        return {name: st.pose(t) for name, st in tools.items()}

    return source


DEFAULT_POSES = {
    "tool": dict(position_mm=(0.0, 0.0, -1500.0), quat_xyzw=(0.0, 0.0, 0.0, 1.0)),
    "base": dict(position_mm=(150.0, 80.0, -1700.0), quat_xyzw=(0.0, 0.0, 0.3826834, 0.9238795)),
}


def load_config(path: str | None) -> dict:
    if not path:
        return {}
    import yaml

    with open(path) as f:
        return yaml.safe_load(f) or {}


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="vega_emulator", description="NDI Polaris Vega emulator (Combined API).")
    ap.add_argument("--config", help="YAML: tools: {name: {rom, position_mm, quat_xyzw, error_mm, "
                                     "circle_radius_mm, circle_period_s, hidden_every_s, hidden_for_s}}")
    ap.add_argument("--host", default="127.0.0.1")
    ap.add_argument("--port", type=int, default=8765, help="TCP port (0: any free port)")
    ap.add_argument("--port-file", help="write the bound TCP port here once listening")
    ap.add_argument("--no-tcp", action="store_true")
    ap.add_argument("--pty", action="store_true", help="also serve the serial protocol on a pty")
    ap.add_argument("--pty-link", help="symlink to create to the pty slave")
    ap.add_argument("--tool", action="append", default=[], metavar="NAME=ROM",
                    help="tool name and .rom path (default: tool and base from fullperc_drivers/config)")
    ap.add_argument("--pose", action="append", default=[], metavar="NAME=x,y,z[,qx,qy,qz,qw]",
                    help="static pose [mm] in the ots frame")
    ap.add_argument("--hidden", action="append", default=[], metavar="NAME", help="tool never visible")
    ap.add_argument("--circle", type=float, default=0.0, metavar="RADIUS_MM", help="move every tool on a circle")
    ap.add_argument("--rate", type=float, default=60.0, help="frame rate [Hz]")
    ap.add_argument("--freeze-tag", default="Polaris Vega 010")
    ap.add_argument("--corrupt-crc", type=float, default=0.0, help="probability per reply")
    ap.add_argument("--garbage", type=float, default=0.0, help="probability per reply")
    ap.add_argument("--delay-prob", type=float, default=0.0)
    ap.add_argument("--delay-s", type=float, default=0.0)
    ap.add_argument("--drop-every", type=float, default=0.0, help="drop the link every N seconds")
    ap.add_argument("--seed", type=int, default=None)
    return ap


def _floats(txt: str, n: tuple[int, ...]) -> list[float]:
    v = [float(x) for x in txt.split(",")]
    if len(v) not in n:
        raise ValueError(f"expected {n} comma-separated numbers, got {txt!r}")
    return v


def make_emulator(args: argparse.Namespace) -> VegaEmulator:
    cfg = load_config(args.config)
    rom_dir = _default_rom_dir()
    tool_cfg: dict[str, dict] = {k: dict(v or {}) for k, v in (cfg.get("tools") or {}).items()}
    if not tool_cfg and not args.tool:
        tool_cfg = {k: dict(v) for k, v in DEFAULT_POSES.items()}
    for spec in args.tool:
        name, rom = spec.split("=", 1)
        tool_cfg.setdefault(name, {})["rom"] = rom
    for spec in args.pose:
        name, vals = spec.split("=", 1)
        v = _floats(vals, (3, 7))
        tool_cfg.setdefault(name, {})["position_mm"] = v[:3]
        if len(v) == 7:
            tool_cfg[name]["quat_xyzw"] = v[3:]
    roms: dict[str, bytes] = {}
    scripted: dict[str, ScriptedTool] = {}
    for i, (name, tc) in enumerate(tool_cfg.items()):
        rom_path = Path(tc.get("rom", f"{name}.rom"))
        if not rom_path.is_absolute() and not rom_path.exists():
            rom_path = rom_dir / rom_path
        roms[name] = rom_path.read_bytes()
        if name in args.hidden:
            continue
        pos = tc.get("position_mm", DEFAULT_POSES.get(name, {}).get("position_mm", (60.0 * i, 0.0, -1500.0)))
        scripted[name] = ScriptedTool(
            tuple(pos), tuple(tc.get("quat_xyzw", (0.0, 0.0, 0.0, 1.0))), float(tc.get("error_mm", 0.1)),
            float(tc.get("circle_radius_mm", args.circle)), float(tc.get("circle_period_s", 4.0)),
            float(tc.get("hidden_every_s", 0.0)), float(tc.get("hidden_for_s", 0.0)))
    faults = FaultConfig(args.corrupt_crc, args.garbage, args.delay_prob, args.delay_s,
                         args.drop_every or None, seed=args.seed)
    return VegaEmulator(scripted_source(scripted), roms, args.rate, args.host, args.port, faults,
                        freeze_tag=args.freeze_tag)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    emu = make_emulator(args)
    emu.start(tcp=not args.no_tcp)
    if not args.no_tcp:
        print(f"vega_emulator listening on {emu.host}:{emu.port}", flush=True)
        if args.port_file:
            tmp = args.port_file + ".tmp"
            Path(tmp).write_text(str(emu.port))
            os.replace(tmp, args.port_file)
    if args.pty or args.pty_link:
        path = emu.open_pty(args.pty_link)
        print(f"vega_emulator serial on {path}", flush=True)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    while not stop.wait(1.0):
        pass
    emu.stop()
    s = emu.stats
    print(f"vega_emulator stopped: {s}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
