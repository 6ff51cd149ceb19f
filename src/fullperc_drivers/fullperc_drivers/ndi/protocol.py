"""NDI Combined API wire protocol: command encoding and reply framing (no ROS, no I/O).

Everything here follows reference/ndi.md §1:

* Commands come in two forms, both accepted by real devices: ``CMD:params`` + CRC16 (4 uppercase
  hex, over everything before it, the ``:`` included) + CR, and ``CMD params`` + CR without CRC.
* ASCII replies are ``data`` + CRC16 (4 hex) + CR; the CRC covers the data including embedded LFs.
* Binary replies (BX, BX2, GETLOG, VGET) start with ``C4 A5``: start u16, body length u16,
  header CRC u16 (over the 4 bytes before it), body, body CRC u16 (over the body) — little-endian.
  An error to a binary command comes back as an ASCII ``ERRORxx`` reply.

Error types: every malformed input raises :class:`NdiProtocolError` (CRC mismatches the subclass
:class:`NdiCrcError`); an ``ERRORxx`` reply raises :class:`NdiDeviceError`, which names the code.
All derive from :class:`NdiError`, the only exception type the parsers let escape (fuzz-tested).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from .crc import crc16, crc16_hex

BINARY_START = b"\xc4\xa5"  # 0xA5C4 little-endian: short binary reply
EXTENDED_START = b"\xc8\xa5"  # 0xA5C8: extended binary reply (no CRCs), BX2/VCAP
STREAM_START = b"\xd4\xb5"  # 0xB5D4: streaming packet wrapper (not used by the driver)
CR = b"\r"
MAX_REPLY = 1 << 16  # largest frame we accept before declaring the stream garbled

# Device error codes (ndi.md §1.7, NDICAPI ndiErrorString).
ERROR_CODES: dict[int, str] = {
    0x01: "invalid command", 0x02: "command too long", 0x03: "command too short",
    0x04: "invalid CRC calculated for command", 0x05: "time-out on command execution",
    0x06: "unable to set up new communication parameters", 0x07: "incorrect number of parameters",
    0x08: "invalid port handle", 0x09: "invalid tracking priority (must be S, D or B)",
    0x0A: "invalid LED", 0x0B: "invalid LED state", 0x0C: "command invalid in current mode",
    0x0D: "no tool assigned to port handle", 0x0E: "port handle not initialized",
    0x0F: "port handle not enabled", 0x10: "system not initialized", 0x11: "unable to stop tracking",
    0x12: "unable to start tracking", 0x13: "unable to initialize tool-in-port",
    0x14: "invalid position-sensor characterization parameters",
    0x15: "unable to initialize the measurement system", 0x16: "unable to start diagnostic mode",
    0x17: "unable to stop diagnostic mode", 0x18: "environmental IR/magnetic interference check failed",
    0x19: "unable to read firmware version", 0x1A: "internal measurement system error",
    0x1B: "unable to initialize environmental IR diagnostics", 0x1C: "unable to set marker firing signature",
    0x1D: "unable to search for SROM IDs", 0x1E: "unable to read SROM data", 0x1F: "unable to write SROM data",
    0x20: "unable to select SROM", 0x21: "unable to perform tool current test",
    0x22: "selected volume does not support the wavelength of an enabled tool",
    0x23: "command parameter out of range", 0x24: "no camera parameters for the selected volume",
    0x25: "unable to determine supported features list", 0x28: "too many tools / frames or unsupported tool",
    0x29: "main processor firmware corrupt", 0x2A: "heap full", 0x2B: "handle not allocated",
    0x2C: "handle became unoccupied", 0x2D: "all handles allocated", 0x2E: "incompatible firmware versions",
    0x2F: "invalid port description", 0x30: "port already has a handle", 0x32: "invalid operation for device",
    0x33: "feature not available", 0x34: "user parameter does not exist", 0x35: "invalid value type",
    0x36: "value out of range", 0x37: "index out of range", 0x38: "size incorrect",
    0x39: "permission denied", 0x3B: "file not found", 0x3C: "file write error", 0x3D: "file read error",
    0x40: "tool definition file error", 0x41: "tool characteristics not supported",
    0x42: "device not present", 0xF1: "too much environmental infrared", 0xF4: "unable to erase flash",
    0xF5: "unable to write flash", 0xF6: "unable to read flash",
}


_HEX = frozenset(b"0123456789ABCDEFabcdef")


def is_hex(text: bytes | str) -> bool:
    """True when ``text`` is non-empty and only hex digits (``int(x, 16)`` also takes '0x', '_', ' ')."""
    if isinstance(text, str):
        text = text.encode("latin-1", "replace")
    return bool(text) and all(c in _HEX for c in text)


class NdiError(Exception):
    """Base of every error raised by the NDI protocol core."""


class NdiProtocolError(NdiError, ValueError):
    """Malformed bytes: not a valid command or reply of the expected kind."""


class NdiCrcError(NdiProtocolError):
    """A frame whose CRC does not match its contents."""


class NdiDeviceError(NdiError):
    """The device answered ``ERRORxx``; ``code`` is the NDI error code."""

    def __init__(self, code: int, command: str = "") -> None:
        self.code = int(code)
        self.command = command
        self.description = ERROR_CODES.get(self.code, "unrecognized error code")
        where = f" to {command}" if command else ""
        super().__init__(f"NDI ERROR{self.code:02X}{where}: {self.description}")


# ----------------------------------------------------------------------------------------------
# Commands


@dataclass(frozen=True)
class Command:
    """A decoded command line (the emulator's view of what a host sent)."""

    name: str  # upper-case command name, e.g. "PVWR"
    params: str  # parameter text without CRC and CR
    crc_form: bool  # True for ``CMD:params+CRC``, False for ``CMD params`` / bare ``CMD``


def encode_command(name: str, params: str = "", crc: bool = True) -> bytes:
    """Encode a command. ``crc=True`` gives ``NAME:params`` + CRC16 + CR, else ``NAME params`` + CR."""
    if not name or not name.replace("_", "").isalnum() or not name.isupper():
        raise NdiProtocolError(f"bad command name {name!r}")
    if "\r" in params:
        raise NdiProtocolError("command parameters must not contain CR")
    if crc:
        body = f"{name}:{params}"
        return (body + crc16_hex(body) + "\r").encode("latin-1")
    return f"{name} {params}\r".encode("latin-1")


def decode_command(line: bytes) -> Command:
    """Decode one command line (with or without the trailing CR).

    Raises :class:`NdiCrcError` when the CRC form's CRC does not match (the device answers
    ``ERROR04``), :class:`NdiProtocolError` for anything that is not a command.
    """
    if line.endswith(CR):
        line = line[:-1]
    try:
        text = bytes(line).decode("ascii")
    except UnicodeDecodeError as e:
        raise NdiProtocolError("command is not ASCII") from e
    i = 0
    while i < len(text) and ("A" <= text[i] <= "Z" or "0" <= text[i] <= "9"):
        i += 1
    name = text[:i]
    if not name:
        raise NdiProtocolError(f"no command name in {text[:20]!r}")
    if i == len(text):
        return Command(name, "", False)
    sep = text[i]
    if sep == ":":
        rest = text[i + 1:]
        if len(rest) < 4:
            raise NdiCrcError(f"{name}: command too short for a CRC")
        params, crc_txt = rest[:-4], rest[-4:]
        if not is_hex(crc_txt):
            raise NdiCrcError(f"{name}: CRC field {crc_txt!r} is not hex")
        if int(crc_txt, 16) != crc16(text[:-4].encode("ascii")):
            raise NdiCrcError(f"{name}: command CRC {crc_txt} does not match")
        return Command(name, params, True)
    if sep == " ":
        return Command(name, text[i + 1:], False)
    raise NdiProtocolError(f"bad separator {sep!r} after command {name}")


# ----------------------------------------------------------------------------------------------
# Replies: encoding (device side) and framing (host side)


def encode_ascii_reply(data: bytes | str) -> bytes:
    if isinstance(data, str):
        data = data.encode("latin-1")
    return bytes(data) + crc16_hex(data).encode("ascii") + CR


def encode_binary_reply(body: bytes) -> bytes:
    if len(body) > 0xFFFF:
        raise NdiProtocolError("binary body longer than 65535 bytes")
    head = BINARY_START + struct.pack("<H", len(body))
    return head + struct.pack("<H", crc16(head)) + bytes(body) + struct.pack("<H", crc16(body))


@dataclass(frozen=True)
class Reply:
    """One complete, CRC-checked reply frame."""

    data: bytes  # ASCII data without CRC/CR, or the binary body without header/CRC
    binary: bool

    @property
    def text(self) -> str:
        return self.data.decode("latin-1")


def check_status(reply: Reply, command: str = "") -> Reply:
    """Raise :class:`NdiDeviceError` if ``reply`` is ``ERRORxx``; return it unchanged otherwise."""
    if not reply.binary and reply.data.startswith(b"ERROR"):
        code_txt = reply.data[5:7]
        if len(code_txt) != 2 or not is_hex(code_txt):
            raise NdiProtocolError(f"malformed error reply {reply.data[:12]!r}")
        raise NdiDeviceError(int(code_txt, 16), command)
    return reply


def parse_okay(reply: Reply, command: str = "") -> int | None:
    """``OKAY`` -> None; ``WARNINGxx`` (or bare ``WARNING``) -> the warning code (0 if none);
    ``ERRORxx`` -> :class:`NdiDeviceError`; anything else -> :class:`NdiProtocolError`."""
    check_status(reply, command)
    d = reply.data
    if d == b"OKAY":
        return None
    if d.startswith(b"WARNING"):
        tail = d[7:]
        if not tail:
            return 0
        if len(tail) != 2 or not is_hex(tail):
            raise NdiProtocolError(f"malformed warning {d[:12]!r}")
        return int(tail, 16)
    raise NdiProtocolError(f"expected OKAY to {command or 'command'}, got {d[:16]!r}")


class FrameReader:
    """Incremental reply framer: feed bytes, pop complete CRC-checked :class:`Reply` frames.

    A frame is binary when it starts with ``C4 A5`` and ASCII (up to CR) otherwise. A CRC
    mismatch raises :class:`NdiCrcError` after the bad frame has been consumed, so the caller
    can count it and go on; :meth:`clear` drops everything buffered (used after errors, like
    ndicapi's input flush).

    Bytes before a reply (line noise, a partial frame from before a reconnect) are skipped and
    counted in :attr:`garbage_bytes`, so the reply behind them is not lost:

    * binary: a ``C4 A5`` whose 6-byte header CRC holds, before the first CR, starts the frame
      (a reply starting elsewhere used to wait for a CR that a binary reply need not contain:
      the read timed out, 0.5 s per garbled BX);
    * ASCII: a frame up to CR whose CRC fails as a whole is tried from each later offset that
      follows a byte no ASCII reply contains (so a reply whose own bytes were corrupted is never
      cut to a shorter one): the one candidate is the printable tail after the last such byte; its
      CRC decides. A false match needs a CRC-16 collision (1 in 65536 of the garbled replies whose
      tail is printable); no match: NdiCrcError, as before;
    * noise that holds a CR itself: a "frame" with a byte no reply contains among its last four (where a
      reply's CRC digits are), or shorter than four bytes, cannot be the end of a reply; it is skipped as
      garbage and the reply behind it read. (It used to raise NdiCrcError: the client then dropped the buffer,
      reply included, drained and repeated the command, and when the reply's tail came after the drain -- a
      busy machine, a pty -- the repeated command read it and timed out: 3 timeouts in 1,039 commands, serial
      with noise before 20 % of the replies, in CI.) A reply whose own CRC digits were corrupted into such a
      byte is then waited for until the read timeout, instead of failing its CRC at once.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self.garbage_bytes = 0   # skipped before replies (see above)
        self._scan = 1

    def feed(self, data: bytes) -> None:
        self._buf += data

    def clear(self) -> None:
        self._buf.clear()
        self._scan = 1

    def _consume(self, n: int) -> None:
        del self._buf[:n]
        self._scan = 1   # where the search for a binary header goes on (_binary_start)

    @property
    def pending(self) -> int:
        return len(self._buf)

    def pop(self) -> Reply | None:
        """The next complete frame, or None if more bytes are needed."""
        while True:   # a loop, not recursion: a buffer may hold thousands of noise CRs
            rep = self._pop_one()
            if rep is not _SKIPPED:
                return rep

    def _pop_one(self) -> Reply | None | object:
        """:meth:`pop`'s step: a frame, None, or ``_SKIPPED`` when noise up to a CR was skipped."""
        buf = self._buf
        if not buf:
            return None
        if buf[0] == 0xC4:
            if len(buf) < 2:
                return None
            if buf[1] == 0xA5:
                return self._pop_binary()
        if buf[0] == 0xC8 and len(buf) >= 2 and buf[1] == 0xA5:
            return self._pop_extended()
        idx = buf.find(CR)
        k = self._binary_start(len(buf) if idx < 0 else idx)
        if k == -1:
            return None   # a header candidate not complete yet
        if k is not None:
            self._consume(k)
            self.garbage_bytes += k
            return self._pop_binary()
        if idx < 0:
            if len(buf) > MAX_REPLY:
                self.clear()
                raise NdiProtocolError("no CR within the maximum reply length")
            return None
        frame = bytes(buf[:idx])
        self._consume(idx + 1)
        if _last_unprintable(frame) >= len(frame) - 4:   # noise holding a CR, not the end of a reply (above)
            self.garbage_bytes += idx + 1
            return _SKIPPED
        rep: Reply | None = None
        try:
            rep = parse_ascii_frame(frame)
            if _printable(rep.data):
                return rep
        except NdiError as e:
            err = e
        # The one candidate: right after the last byte no reply contains (the rest printable), a linear scan.
        # (CRC-16/ARC starts from 0, so zero bytes before a reply leave its CRC valid: resynchronised too.)
        j = _last_unprintable(frame[:-4]) + 1
        if 0 < j <= len(frame) - 4:
            try:
                tail = parse_ascii_frame(frame[j:])
            except NdiError:
                tail = None
            if tail is not None:
                self.garbage_bytes += j
                return tail
        if rep is not None:
            return rep   # CRC-valid but not printable: the caller's parser says what is wrong with it
        raise err

    def _binary_start(self, limit: int) -> int | None:
        """Offset > 0 of the first binary header (``C4 A5``, header CRC valid) in the buffer before ``limit``;
        -1 when a candidate's header is not complete yet; None when there is none."""
        buf = self._buf
        k = buf.find(b"\xc4\xa5", self._scan, limit + 1)
        while k >= 0:
            if len(buf) < k + 6:
                self._scan = k
                return -1
            if struct.unpack_from("<H", buf, k + 4)[0] == crc16(buf[k:k + 4]):
                return k
            k = buf.find(b"\xc4\xa5", k + 1, limit + 1)
        self._scan = max(1, min(limit, len(buf) - 1))   # bytes searched stay searched (a lone C4 at the end not)
        return None

    def _pop_binary(self) -> Reply | None:
        buf = self._buf
        if len(buf) < 6:
            return None
        (n,) = struct.unpack_from("<H", buf, 2)
        (hcrc,) = struct.unpack_from("<H", buf, 4)
        if hcrc != crc16(buf[:4]):
            # Length cannot be trusted: drop the start bytes so the caller resynchronises.
            self._consume(2)
            raise NdiCrcError("binary reply header CRC mismatch")
        if len(buf) < n + 8:
            return None
        body = bytes(buf[6:6 + n])
        (bcrc,) = struct.unpack_from("<H", buf, 6 + n)
        self._consume(n + 8)
        if bcrc != crc16(body):
            raise NdiCrcError("binary reply body CRC mismatch")
        return Reply(body, True)

    def _pop_extended(self) -> Reply | None:
        buf = self._buf
        if len(buf) < 6:
            return None
        (n,) = struct.unpack_from("<I", buf, 2)
        if n > MAX_REPLY * 64:
            self._consume(2)
            raise NdiProtocolError(f"extended reply length {n} is implausible")
        if len(buf) < n + 6:
            return None
        body = bytes(buf[6:6 + n])
        self._consume(n + 6)
        return Reply(body, True)


_REPLY_BYTES = bytes(range(0x20, 0x7F)) + b"\n"   # what an ASCII reply contains: printable characters and LF


def _printable(b: bytes) -> bool:
    """Only bytes an ASCII reply contains."""
    return not b.translate(None, _REPLY_BYTES)


def _last_unprintable(b: bytes) -> int:
    """Index of the last byte of ``b`` no ASCII reply contains, -1 when there is none."""
    for i in range(len(b) - 1, -1, -1):
        if b[i] not in _REPLY_SET:
            return i
    return -1


_REPLY_SET = frozenset(_REPLY_BYTES)
_SKIPPED = object()   # FrameReader._pop_one: noise up to a CR skipped, look again


def parse_ascii_frame(frame: bytes) -> Reply:
    """Check and strip the CRC of one ASCII reply given without its CR."""
    if len(frame) < 4:
        raise NdiProtocolError(f"ASCII reply too short ({len(frame)} bytes)")
    data, crc_txt = frame[:-4], frame[-4:]
    if not is_hex(crc_txt):
        raise NdiCrcError(f"reply CRC field {crc_txt!r} is not hex")
    got = int(crc_txt, 16)
    if got != crc16(data):
        raise NdiCrcError(f"reply CRC {crc_txt.decode('ascii')} does not match {crc16(data):04X}")
    return Reply(bytes(data), False)


def parse_frame(raw: bytes) -> Reply:
    """Parse exactly one complete frame (ASCII with CR, or binary). Extra bytes are an error."""
    fr = FrameReader()
    fr.feed(raw)
    rep = fr.pop()
    if rep is None:
        raise NdiProtocolError("incomplete reply")
    if fr.pending:
        raise NdiProtocolError(f"{fr.pending} bytes after the reply")
    return rep
