"""The NDI Polaris Vega as a device: the Combined-API state machine, one command line in, one reply out.

It speaks the Combined API as in reference/ndi.md, reusing the protocol core of
``fullperc_drivers.ndi``: both command forms (``CMD:params+CRC`` and ``CMD params``; a wrong CRC
is answered ``ERROR04``), lowercase hex parameters, handle state (PHRQ -> PVWR -> PINIT -> PENA, so
``PHSR:00..04`` answer as a real device does), .rom uploads, TSTART/TSTOP, BX and TX (options 0001,
0008, 0800), VER, APIREV, GET/GETINFO/SET, PHINF, COMM (serial rate switch after ``OKAY``), RESET,
BEEP, ECHO. BX2/STREAM are not emulated (``ERROR01``). The links (TCP, pty) and fault injection are in
:mod:`.vega_server`, the executable in :mod:`.vega_cli`.

Pose source API (used by the simulator)::

    VegaDevice(tools={"tool": rom_bytes, ...}, pose_source=f, frame_rate_hz=60)
    f(t_host_ns: int) -> dict[str, ToolPose | None]

``f`` is called once per device frame with that frame's capture time on the host clock
(``time.time_ns()`` domain); ``ToolPose(position_mm, quat_xyzw, error_mm=0.1, markers_mm=None)``
is the tool's pose in the ``ots`` frame, i.e. the NDI camera frame, where the measurement volume
lies at negative z (a tool in front of the camera has z ~ -950 .. -2400 mm). ``quat_xyzw`` is ROS
order; the emulator converts to NDI's scalar-first order on the wire. ``None`` (or a missing key)
means the tool is not visible: MISSING. A pose outside ``frustum`` is also MISSING (with reply
option 0800 it is reported, port status 0x40 "out of volume"). ``frustum`` is the margin model's
:class:`fullperc_fusion.margin.layout.Frustum` (metres, in the ``ots`` frame; the simulator passes its layout's),
by default :func:`pyramid_frustum`. A ROM uploaded by the host is matched to a tool by its bytes (zero
padding ignored) or, failing that, by its part number; an unknown but well-formed ROM loads fine and is
always MISSING.

Frame numbers count at ``frame_rate_hz`` from emulator start (``TSTART:80`` resets them); all
handles of one reply share the frame number. :meth:`VegaDevice.align_frames` puts the frame times on another
clock's grid (the simulator's Vega samples), so that ``f`` is asked for the times it has samples of.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

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
from fullperc_fusion.margin.layout import Frustum


@dataclass
class ToolPose:
    """A tool pose in the ``ots`` frame (NDI camera frame)."""

    position_mm: np.ndarray
    quat_xyzw: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 0.0, 1.0]))
    error_mm: float = 0.1
    markers_mm: np.ndarray | None = None  # (n, 3) in the ots frame, for reply option 0008


PoseSource = Callable[[int], dict[str, "ToolPose | None"]]


def pyramid_frustum(near_mm: float = 950.0, far_mm: float = 2400.0, half_angle_x_deg: float = 18.0,
                    half_angle_y_deg: float = 15.0) -> Frustum:
    """The emulator's default measurement volume: a pyramid along -z from ``near_mm`` to ``far_mm``.

    Defaults: the Polaris pyramid's 950-2400 mm depth (ndi.md §7.1); the half-angles are our nominal choice
    (the Vega lateral extents are UNCERTAIN in ndi.md) — configure them. As a margin-model
    :class:`~fullperc_fusion.margin.layout.Frustum` (metres) its two planes are the near and far cross-sections;
    the linear interpolation between them is the pyramid's ``|x| <= d tan(half_angle_x)``,
    ``|y| <= d tan(half_angle_y)``.
    """
    tx, ty = math.tan(math.radians(half_angle_x_deg)), math.tan(math.radians(half_angle_y_deg))
    planes = np.array([[d / 1000.0, d / 1000.0 * tx, d / 1000.0 * ty] for d in (near_mm, far_mm)])
    return Frustum(planes, "-z")


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
                 frame_rate_hz: float = 60.0, frustum: Frustum | None = None,
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
        self.frustum = frustum if frustum is not None else pyramid_frustum()
        self.freeze_tag = freeze_tag
        self.max_handles = max_handles
        self.serial_number = serial_number
        self.frame_start = frame_start
        self.lock = threading.RLock()
        self.t0_ns = time.time_ns()
        self._grid_ref_ns: int | None = None   # align_frames
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

    def align_frames(self, ref_ns: int) -> None:
        """Frame times from now on fall on ``ref_ns + k / frame_rate_hz`` (k integer), also after ``TSTART:80``.

        Why: a real Vega captures a frame at its frame time, and the simulator has poses at its own Vega sample
        times only. Unaligned, the emulator answered each frame with the latest sample before it -- a pose up to one
        frame period older than the frame's time, by a phase that changed from run to run -- and a driver that
        stamps frames correctly published poses older than their stamps (the demo's walking instrument: raw Vega
        chain 0.30-1.46 mm off its truth, 0.17-0.21 mm aligned; ``report/instrument/eval.json``,
        ``single_sources``). The start moves back by less than one period, so frame numbers never go back (one
        may be skipped, as when the device drops a frame).
        """
        with self.lock:
            self._grid_ref_ns = int(ref_ns)
            self._align()

    def _align(self) -> None:
        if self._grid_ref_ns is None:
            return
        m = math.floor((self.t0_ns - self._grid_ref_ns) * self.frame_rate_hz / 1e9)
        self.t0_ns = self._grid_ref_ns + int(round(m * 1e9 / self.frame_rate_hz))
        self._frame_cache = None

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
            self._align()
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
                inside = bool(np.asarray(self.frustum.contains(p.reshape(1, 3) / 1000.0)).reshape(-1)[0])
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

