"""The links around a :class:`~.vega_device.VegaDevice`: a TCP server, a pty for the serial path, fault injection.

Fault injection (:class:`FaultConfig`): corrupt a reply's CRC with probability p, prepend garbage
bytes, delay replies, and drop the link every N seconds (TCP: close every client socket; serial:
the device power-cycles back to 9600 baud and is silent for ``drop_silence_s``).

Serial over a pty: :meth:`VegaEmulator.open_pty` returns the slave path for pyserial. The emulated
device checks the host's line rate (the pty's termios) and ignores bytes sent at the wrong rate,
like a UART producing framing errors. A serial break cannot be seen through a pty, so closing the
port (hang-up) is treated as the break a host sends before reconnecting: the device resets to
9600 baud. It binds 127.0.0.1 by default.
"""

from __future__ import annotations

import os
import random
import select
import socket
import termios
import threading
import time
import tty
from dataclasses import dataclass

from fullperc_drivers.ndi.protocol import encode_ascii_reply

from .vega_device import PoseSource, VegaDevice


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

