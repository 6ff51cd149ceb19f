"""Typed parsers (host side) and formatters (emulator side) for NDI Combined API replies.

Layouts follow reference/ndi.md §2-§4 (TX options 0001/0008/0800, BX options 0001/0008/0800,
PHSR, PHRQ, VER, APIREV, GET). NDI transmits quaternions scalar first (q0 qx qy qz);
:class:`ToolTransform` keeps that order in ``q_wxyz`` and converts to ROS order only through
``fullperc_common.transforms.quat_wxyz_to_xyzw`` (``q_xyzw``), pinned by test_ndi_protocol.py.

Every parser takes the reply data without CRC/CR (``protocol.Reply.data``/``.text``) and raises
:class:`~.protocol.NdiProtocolError` (only) on malformed input. Parsers are strict: a reply must be
consumed exactly, so a frame that passes the CRC but is garbled is still caught.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np

from fullperc_common.transforms import quat_wxyz_to_xyzw

from .protocol import NdiProtocolError, is_hex

# TX/BX reply options (bit OR).
OPT_TRANSFORMS = 0x0001
OPT_TOOL_INFO = 0x0002
OPT_SINGLE_STRAY = 0x0004
OPT_MARKERS = 0x0008
OPT_NOT_NORMALLY_REPORTED = 0x0800
OPT_PASSIVE_STRAYS = 0x1000
SUPPORTED_OPTIONS = OPT_TRANSFORMS | OPT_MARKERS | OPT_NOT_NORMALLY_REPORTED

# BX per-handle status byte.
BX_VALID = 0x01
BX_MISSING = 0x02
BX_DISABLED = 0x04
_BX_STATUS = {BX_VALID: "valid", BX_MISSING: "missing", BX_DISABLED: "disabled"}
_BX_CODE = {v: k for k, v in _BX_STATUS.items()}

# Port status bits (low byte, NDICAPI).
PORT_OCCUPIED = 0x01
PORT_INITIALIZED = 0x10
PORT_ENABLED = 0x20
PORT_OUT_OF_VOLUME = 0x40
PORT_PARTIALLY_OUT_OF_VOLUME = 0x80

# PHSR handle status bits.
PHSR_OCCUPIED = 0x001
PHSR_INITIALIZED = 0x010
PHSR_ENABLED = 0x020

_XFORM = struct.Struct("<8f")
_U32 = struct.Struct("<I")
_U16 = struct.Struct("<H")


@dataclass
class ToolTransform:
    """One handle's entry of a TX/BX reply (device units: millimetres)."""

    handle: int
    status: str  # "valid" | "missing" | "disabled" (| "unoccupied", TX only)
    q_wxyz: np.ndarray | None = None  # NDI order, scalar first
    t_mm: np.ndarray | None = None
    error_mm: float | None = None  # RMS marker fit error
    port_status: int | None = None
    frame_number: int | None = None
    markers_mm: np.ndarray | None = None  # (n, 3), option 0008
    markers_oov: tuple[bool, ...] | None = None

    @property
    def visible(self) -> bool:
        return self.status == "valid"

    @property
    def q_xyzw(self) -> np.ndarray | None:
        """Quaternion in ROS order (x, y, z, w)."""
        return None if self.q_wxyz is None else quat_wxyz_to_xyzw(self.q_wxyz)


@dataclass
class TrackingData:
    """A whole TX/BX reply."""

    tools: list[ToolTransform] = field(default_factory=list)
    system_status: int = 0

    def by_handle(self) -> dict[int, ToolTransform]:
        return {t.handle: t for t in self.tools}

    @property
    def frame_number(self) -> int | None:
        """The frame number shared by the handles (first one that reports one)."""
        for t in self.tools:
            if t.frame_number is not None:
                return t.frame_number
        return None


def _check_options(options: int) -> None:
    if options & ~SUPPORTED_OPTIONS & 0xFFFF or options < 0 or options > 0xFFFF:
        raise NdiProtocolError(f"reply option {options:04X} is not supported (supported: 0001 0008 0800)")


def _hex(text: str, pos: int, n: int, what: str) -> int:
    s = text[pos:pos + n]
    if len(s) != n or not is_hex(s):
        raise NdiProtocolError(f"expected {n} hex digits for {what} at {pos}, got {s!r}")
    return int(s, 16)


def _signed(text: str, pos: int, n: int, what: str) -> int:
    s = text[pos:pos + n]
    if len(s) != n or s[0] not in "+-" or not s[1:].isdigit() or not s[1:].isascii():
        raise NdiProtocolError(f"expected a signed {n}-char number for {what} at {pos}, got {s!r}")
    return int(s)


# ----------------------------------------------------------------------------------------------
# TX (ASCII)


def parse_tx(text: str, options: int = OPT_TRANSFORMS) -> TrackingData:
    """Parse the data of a ``TX:oooo`` reply (options 0001, 0008, 0800)."""
    _check_options(options)
    n = _hex(text, 0, 2, "handle count")
    pos = 2
    tools: list[ToolTransform] = []
    for _ in range(n):
        handle = _hex(text, pos, 2, "port handle")
        pos += 2
        tool = ToolTransform(handle, "valid")
        if text.startswith("UNOCCUPIED", pos):
            tool.status = "unoccupied"
            pos += 10
            if pos < len(text) and text[pos] != "\n":
                tool.port_status = _hex(text, pos, 8, "port status")
                tool.frame_number = _hex(text, pos + 8, 8, "frame number")
                pos += 16
        elif options & OPT_TRANSFORMS:
            if text.startswith("MISSING", pos):
                tool.status = "missing"
                pos += 7
                has_tail = True
            elif text.startswith("DISABLED", pos):
                tool.status = "disabled"
                pos += 8
                # Clients disagree on whether status+frame follow DISABLED (ndi.md §3): accept both.
                has_tail = pos < len(text) and text[pos] != "\n"
            else:
                q = [_signed(text, pos + 6 * k, 6, "quaternion") / 10000.0 for k in range(4)]
                t = [_signed(text, pos + 24 + 7 * k, 7, "translation") / 100.0 for k in range(3)]
                err = _signed(text, pos + 45, 6, "error") / 10000.0
                tool.q_wxyz = np.array(q)
                tool.t_mm = np.array(t)
                tool.error_mm = err
                pos += 51
                has_tail = True
            if has_tail:
                tool.port_status = _hex(text, pos, 8, "port status")
                tool.frame_number = _hex(text, pos + 8, 8, "frame number")
                pos += 16
            if options & OPT_MARKERS and tool.status != "disabled":
                pos = _parse_tx_markers(text, pos, tool)
        if pos >= len(text) or text[pos] != "\n":
            raise NdiProtocolError(f"expected LF after handle {handle:02X} at {pos}")
        pos += 1
        tools.append(tool)
    system_status = _hex(text, pos, 4, "system status")
    pos += 4
    if pos != len(text):
        raise NdiProtocolError(f"{len(text) - pos} unexpected characters at the end of the TX reply")
    return TrackingData(tools, system_status)


def _parse_tx_markers(text: str, pos: int, tool: ToolTransform) -> int:
    m = _hex(text, pos, 2, "marker count")
    pos += 2
    nib = (m + 3) // 4
    oov_bits = _hex(text, pos, nib, "out-of-volume bits") if nib else 0
    pos += nib
    pts = np.empty((m, 3))
    for k in range(m):
        for a in range(3):
            pts[k, a] = _signed(text, pos, 7, "marker position") / 100.0
            pos += 7
    tool.markers_mm = pts
    # Bit k (from the most significant nibble, marker A first) flags marker k out of volume.
    tool.markers_oov = tuple(bool(oov_bits >> (4 * nib - 1 - k) & 1) for k in range(m))
    return pos


def _fmt_signed(value: float, width: int, scale: float) -> str:
    v = int(round(float(value) * scale))
    lim = 10 ** (width - 1) - 1
    v = max(-lim, min(lim, v))
    return f"{'+' if v >= 0 else '-'}{abs(v):0{width - 1}d}"


def format_tx(data: TrackingData, options: int = OPT_TRANSFORMS) -> str:
    """Emulator side: the data of a TX reply (without CRC/CR)."""
    _check_options(options)
    out = [f"{len(data.tools):02X}"]
    for t in data.tools:
        out.append(f"{t.handle:02X}")
        if options & OPT_TRANSFORMS:
            if t.status == "missing":
                out.append("MISSING")
            elif t.status == "disabled":
                out.append("DISABLED")
            else:
                assert t.q_wxyz is not None and t.t_mm is not None
                out += [_fmt_signed(v, 6, 1e4) for v in t.q_wxyz]
                out += [_fmt_signed(v, 7, 1e2) for v in t.t_mm]
                out.append(_fmt_signed(t.error_mm or 0.0, 6, 1e4))
            out.append(f"{(t.port_status or 0) & 0xFFFFFFFF:08X}{(t.frame_number or 0) & 0xFFFFFFFF:08X}")
            if options & OPT_MARKERS and t.status != "disabled":
                pts = np.zeros((0, 3)) if t.markers_mm is None else np.asarray(t.markers_mm, float)
                m = len(pts)
                nib = (m + 3) // 4
                oov = t.markers_oov or (False,) * m
                bits = sum(1 << (4 * nib - 1 - k) for k in range(m) if oov[k])
                out.append(f"{m:02X}" + (f"{bits:0{nib}X}" if nib else ""))
                out += [_fmt_signed(v, 7, 1e2) for v in pts.ravel()]
        out.append("\n")
    out.append(f"{data.system_status & 0xFFFF:04X}")
    return "".join(out)


# ----------------------------------------------------------------------------------------------
# BX (binary)


def parse_bx(body: bytes, options: int = OPT_TRANSFORMS) -> TrackingData:
    """Parse the body of a ``BX:oooo`` reply (options 0001, 0008, 0800)."""
    _check_options(options)
    body = bytes(body)
    if len(body) < 3:
        raise NdiProtocolError(f"BX body too short ({len(body)} bytes)")
    n = body[0]
    pos = 1
    end = len(body) - 2
    tools: list[ToolTransform] = []
    try:
        for _ in range(n):
            if pos + 2 > end:
                raise NdiProtocolError("BX body ends inside a handle")
            handle, code = body[pos], body[pos + 1]
            pos += 2
            status = _BX_STATUS.get(code)
            if status is None:
                raise NdiProtocolError(f"BX handle {handle:02X} has unknown status {code:#04x}")
            tool = ToolTransform(handle, status)
            tools.append(tool)
            if status == "disabled":
                continue
            if options & OPT_TRANSFORMS:
                if status == "valid":
                    if pos + 32 > end:
                        raise NdiProtocolError("BX body ends inside a transform")
                    v = _XFORM.unpack_from(body, pos)
                    pos += 32
                    tool.q_wxyz = np.array(v[0:4], dtype=float)
                    tool.t_mm = np.array(v[4:7], dtype=float)
                    tool.error_mm = float(v[7])
                if pos + 8 > end:
                    raise NdiProtocolError("BX body ends inside port status / frame number")
                tool.port_status = _U32.unpack_from(body, pos)[0]
                tool.frame_number = _U32.unpack_from(body, pos + 4)[0]
                pos += 8
            if options & OPT_MARKERS:
                if pos + 1 > end:
                    raise NdiProtocolError("BX body ends before the marker count")
                m = body[pos]
                nb = (m + 7) // 8
                pos += 1
                if pos + nb + 12 * m > end:
                    raise NdiProtocolError("BX body ends inside the marker block")
                oov = body[pos:pos + nb]
                pos += nb
                pts = np.frombuffer(body, dtype="<f4", count=3 * m, offset=pos).astype(float).reshape(m, 3)
                pos += 12 * m
                tool.markers_mm = pts
                tool.markers_oov = tuple(bool(oov[k // 8] >> (k % 8) & 1) for k in range(m))
    except struct.error as e:  # pragma: no cover - bounds are checked above
        raise NdiProtocolError(str(e)) from e
    if pos != end:
        raise NdiProtocolError(f"BX body has {end - pos} unexpected bytes before the system status")
    (system_status,) = _U16.unpack_from(body, end)
    return TrackingData(tools, system_status)


def format_bx(data: TrackingData, options: int = OPT_TRANSFORMS) -> bytes:
    """Emulator side: the body of a BX reply (wrap with ``protocol.encode_binary_reply``)."""
    _check_options(options)
    out = bytearray([len(data.tools) & 0xFF])
    for t in data.tools:
        out += bytes([t.handle & 0xFF, _BX_CODE[t.status]])
        if t.status == "disabled":
            continue
        if options & OPT_TRANSFORMS:
            if t.status == "valid":
                assert t.q_wxyz is not None and t.t_mm is not None
                out += _XFORM.pack(*map(float, t.q_wxyz), *map(float, t.t_mm), float(t.error_mm or 0.0))
            out += _U32.pack((t.port_status or 0) & 0xFFFFFFFF) + _U32.pack((t.frame_number or 0) & 0xFFFFFFFF)
        if options & OPT_MARKERS:
            pts = np.zeros((0, 3)) if t.markers_mm is None else np.asarray(t.markers_mm, float)
            m = len(pts)
            oov = t.markers_oov or (False,) * m
            bits = bytearray((m + 7) // 8)
            for k in range(m):
                if oov[k]:
                    bits[k // 8] |= 1 << (k % 8)
            out += bytes([m]) + bits + pts.astype("<f4").tobytes()
    out += _U16.pack(data.system_status & 0xFFFF)
    return bytes(out)


# ----------------------------------------------------------------------------------------------
# Handle management and information replies


def parse_phsr(text: str) -> list[tuple[int, int]]:
    """``PHSR`` data -> [(handle, status bits)], status: 0x01 occupied, 0x10 initialized, 0x20 enabled."""
    n = _hex(text, 0, 2, "handle count")
    if len(text) != 2 + 5 * n:
        raise NdiProtocolError(f"PHSR reply length {len(text)} does not fit {n} handles")
    return [(_hex(text, 2 + 5 * i, 2, "handle"), _hex(text, 4 + 5 * i, 3, "handle status")) for i in range(n)]


def format_phsr(entries: Iterable[tuple[int, int]]) -> str:
    entries = list(entries)
    return f"{len(entries):02X}" + "".join(f"{h:02X}{s:03X}" for h, s in entries)


def parse_phrq(text: str) -> int:
    """``PHRQ`` data -> the new port handle."""
    if len(text) != 2:
        raise NdiProtocolError(f"PHRQ reply must be 2 hex digits, got {text[:16]!r}")
    return _hex(text, 0, 2, "port handle")


@dataclass(frozen=True)
class VersionInfo:
    raw: str
    fields: dict[str, str]

    @property
    def freeze_tag(self) -> str | None:
        return self.fields.get("Freeze Tag")


def parse_ver(text: str) -> VersionInfo:
    """``VER:n`` data: LF-separated ``Key: value`` lines (options 0/3/4) or a bare revision (5)."""
    if not text or any(ord(c) < 0x20 and c != "\n" for c in text) or not text.isascii():
        raise NdiProtocolError("VER reply is empty or contains control/non-ASCII characters")
    fields: dict[str, str] = {}
    for line in text.split("\n"):
        if ":" in line:
            k, v = line.split(":", 1)
            fields[k.strip()] = v.strip()
    return VersionInfo(text, fields)


@dataclass(frozen=True)
class ApiRevision:
    family: str  # "G" (Polaris Spectra/Vicra/Vega), "D" (Aurora)
    major: int
    minor: int | None
    raw: str


def parse_apirev(text: str) -> ApiRevision:
    """``APIREV`` data, e.g. ``G.001.005`` or ``G.003``."""
    parts = text.split(".")
    if len(parts) not in (2, 3) or len(parts[0]) != 1 or not parts[0].isalpha() or not parts[0].isascii():
        raise NdiProtocolError(f"malformed API revision {text[:20]!r}")
    nums = parts[1:]
    if any(len(p) != 3 or not p.isdigit() or not p.isascii() for p in nums):
        raise NdiProtocolError(f"malformed API revision {text[:20]!r}")
    return ApiRevision(parts[0], int(nums[0]), int(nums[1]) if len(nums) == 2 else None, text)


def parse_get(text: str) -> dict[str, str]:
    """``GET`` data: ``name=value`` lines separated by LF -> {name: value}."""
    out: dict[str, str] = {}
    for line in text.split("\n"):
        if not line:
            continue
        if "=" not in line or not line.isascii():
            raise NdiProtocolError(f"GET line without '=': {line[:40]!r}")
        k, v = line.split("=", 1)
        out[k] = v
    if not out:
        raise NdiProtocolError("empty GET reply")
    return out


def pvwr_params(handle: int, rom: bytes, pad_to: int | None = None) -> list[str]:
    """Parameters of the PVWR commands that upload ``rom`` to ``handle`` (64-byte chunks).

    ``pad_to=1024`` writes the whole virtual SROM like ndicapi/PLUS; the default writes only
    ceil(len/64) chunks like NDI's samples/SAW (the last one zero-padded).
    """
    data = bytes(rom)
    size = max(len(data), pad_to or 0)
    size = math.ceil(size / 64) * 64
    data = data.ljust(size, b"\0")
    if size > 1024:
        raise NdiProtocolError(f"tool definition of {len(rom)} bytes does not fit the 1 KiB virtual SROM")
    return [f"{handle:02X}{addr:04X}{data[addr:addr + 64].hex().upper()}" for addr in range(0, size, 64)]


def tools_visible(data: TrackingData, handles: Sequence[int]) -> list[bool]:
    idx = data.by_handle()
    return [h in idx and idx[h].visible for h in handles]
