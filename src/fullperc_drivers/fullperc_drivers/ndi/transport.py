"""Byte transports to an NDI device: TCP (Polaris Vega, port 8765) and serial (Spectra/Vicra).

Both expose the same small interface used by :class:`~.driver.NdiClient`: ``open``, ``close``,
``write``, ``read(timeout)`` (returns what arrived, b"" on timeout, raises :class:`NdiLinkError`
when the link is gone), ``drain(quiet)``. Every read has a timeout.

Serial follows reference/ndi.md §1.1: 9600 8N1 after power-up or a serial break (the device then
says ``RESETBE6F``); ``COMM`` raises the rate, the device answers ``OKAY`` at the old rate and the
host switches its own port ~100 ms later. :func:`baud_code` maps rates to COMM digits.
"""

from __future__ import annotations

import select
import socket
import time

from .protocol import NdiError

DEFAULT_TCP_PORT = 8765
COMM_BAUD_CODES = {9600: "0", 14400: "1", 19200: "2", 38400: "3", 57600: "4", 115200: "5",
                   921600: "6", 1228739: "7", 230400: "A"}
COMM_CODE_BAUD = {v: k for k, v in COMM_BAUD_CODES.items()}


class NdiLinkError(NdiError):
    """The link to the device is down (closed, reset, unreachable) or never came up."""


def baud_code(baud: int) -> str:
    try:
        return COMM_BAUD_CODES[int(baud)]
    except KeyError as e:
        raise ValueError(f"baud rate {baud} is not one the NDI COMM command knows "
                         f"({sorted(COMM_BAUD_CODES)})") from e


class Transport:
    """Interface; see module docstring."""

    name = "transport"

    def open(self) -> None:
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError

    @property
    def is_open(self) -> bool:
        raise NotImplementedError

    def write(self, data: bytes) -> None:
        raise NotImplementedError

    def read(self, timeout: float) -> bytes:
        raise NotImplementedError

    def drain(self, quiet: float = 0.02, limit: float = 0.5) -> int:
        """Discard input until nothing arrives for ``quiet`` s (at most ``limit`` s); bytes dropped."""
        n = 0
        end = time.monotonic() + limit
        while time.monotonic() < end:
            chunk = self.read(quiet)
            if not chunk:
                break
            n += len(chunk)
        return n


class TcpTransport(Transport):
    name = "tcp"

    def __init__(self, host: str, port: int = DEFAULT_TCP_PORT, connect_timeout: float = 2.0) -> None:
        self.host = host
        self.port = int(port)
        self.connect_timeout = connect_timeout
        self._sock: socket.socket | None = None

    def open(self) -> None:
        self.close()
        try:
            s = socket.create_connection((self.host, self.port), timeout=self.connect_timeout)
        except OSError as e:
            raise NdiLinkError(f"cannot connect to {self.host}:{self.port}: {e}") from e
        s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        s.setblocking(False)
        self._sock = s

    def close(self) -> None:
        if self._sock is not None:
            try:
                self._sock.close()
            finally:
                self._sock = None

    @property
    def is_open(self) -> bool:
        return self._sock is not None

    def _s(self) -> socket.socket:
        if self._sock is None:
            raise NdiLinkError("TCP link is not open")
        return self._sock

    def write(self, data: bytes) -> None:
        s = self._s()
        view = memoryview(data)
        end = time.monotonic() + self.connect_timeout
        while view:
            try:
                n = s.send(view)
                view = view[n:]
            except BlockingIOError:
                if time.monotonic() > end:
                    raise NdiLinkError("TCP send timed out") from None
                select.select([], [s], [], 0.05)
            except OSError as e:
                raise NdiLinkError(f"TCP send failed: {e}") from e

    def read(self, timeout: float) -> bytes:
        s = self._s()
        try:
            r, _, _ = select.select([s], [], [], max(0.0, timeout))
            if not r:
                return b""
            data = s.recv(65536)
        except BlockingIOError:
            return b""
        except OSError as e:
            raise NdiLinkError(f"TCP receive failed: {e}") from e
        if not data:
            raise NdiLinkError("device closed the TCP connection")
        return data


class SerialTransport(Transport):
    """pyserial port; opened at 9600 8N1 (the device's rate after reset)."""

    name = "serial"

    def __init__(self, device: str, reset_timeout: float = 7.0) -> None:
        self.device = device
        self.reset_timeout = reset_timeout
        self._port = None

    def open(self) -> None:
        import serial  # pyserial; imported lazily so TCP-only use does not need it

        self.close()
        try:
            self._port = serial.Serial(self.device, 9600, bytesize=8, parity="N", stopbits=1,
                                       timeout=0, write_timeout=2.0, rtscts=False, xonxoff=False)
        except (OSError, serial.SerialException) as e:
            raise NdiLinkError(f"cannot open serial port {self.device}: {e}") from e

    def close(self) -> None:
        if self._port is not None:
            try:
                self._port.close()
            except OSError:
                pass
            self._port = None

    @property
    def is_open(self) -> bool:
        return self._port is not None

    @property
    def baudrate(self) -> int:
        return int(self._p().baudrate)

    def _p(self):
        if self._port is None:
            raise NdiLinkError("serial port is not open")
        return self._port

    def set_baud(self, baud: int) -> None:
        try:
            self._p().baudrate = int(baud)
        except (OSError, ValueError) as e:
            raise NdiLinkError(f"cannot set {self.device} to {baud} baud: {e}") from e

    def send_break(self, duration: float = 0.25) -> None:
        """Serial break: the device resets to 9600 8N1 and replies RESET (host must be at 9600)."""
        p = self._p()
        try:
            p.reset_input_buffer()
            p.baudrate = 9600
            p.send_break(duration)
        except OSError as e:
            raise NdiLinkError(f"serial break failed: {e}") from e

    def write(self, data: bytes) -> None:
        import serial

        try:
            self._p().write(data)
        except (OSError, serial.SerialException) as e:
            raise NdiLinkError(f"serial write failed: {e}") from e

    def read(self, timeout: float) -> bytes:
        import serial

        p = self._p()
        try:
            fd = p.fileno()
            r, _, _ = select.select([fd], [], [], max(0.0, timeout))
            if not r:
                return b""
            n = p.in_waiting
            data = p.read(n or 1)
        except (OSError, serial.SerialException, TypeError) as e:
            raise NdiLinkError(f"serial read failed: {e}") from e
        return data
