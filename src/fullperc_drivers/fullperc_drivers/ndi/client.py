"""NDI command client: request/response over a transport with CRC checks, timeouts and retries.

:class:`NdiClient` sends one command, reads its CRC-checked reply and repeats it (``max_retries``)
after a CRC error, a garbled reply or a timeout, counting each in :class:`Counters`; a device
``ERRORxx`` raises :class:`~.protocol.NdiDeviceError` at once (it is an answer, not a link fault).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

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
from .transport import NdiLinkError, Transport, baud_code

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
    skipped_frames: int = 0  # device frames never read: frame-number gaps between delivered frames (the poll
    #                          came late; not counted across a bring-up or a counter that goes back)
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
    garbage_bytes: int = 0  # skipped before a reply that was then read (protocol.FrameReader)

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
                if self._frames.garbage_bytes:
                    self.counters.garbage_bytes += self._frames.garbage_bytes
                    self._frames.garbage_bytes = 0
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

    def okay(self, name: str, params: str = "", timeout: float | None = None, retry: bool = True) -> None:
        warn = parse_okay(self.raw(name, params, timeout, retry), name)
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
        self._mode_change("TSTART")

    def tstop(self) -> None:
        self._mode_change("TSTOP")

    def _mode_change(self, name: str) -> None:
        """TSTART / TSTOP. When the OKAY came back garbled (or not at all) the command is repeated, and the repeat
        finds the device already in the new mode: ERROR0C (invalid in the current mode) then means the first one
        took effect, not a failure (it used to fail the bring-up, which re-loaded every tool)."""
        retries = self.counters.retries
        try:
            self.okay(name, "")
        except NdiDeviceError as e:
            if e.code != 0x0C or self.counters.retries == retries:
                raise
            log.info("NDI %s repeated after an unread OKAY answered ERROR0C: the first one took effect", name)

    def comm(self, baud: int, retry: bool = True) -> None:
        """``retry=False``: once -- a garbled OKAY means the device has most likely switched already, and a repeat
        at the old rate would meet silence (the driver's serial bring-up and shutdown)."""
        self.okay("COMM", f"{baud_code(baud)}0000", retry=retry)

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
