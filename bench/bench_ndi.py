"""NDI driver benchmarks: BX parse rate and the polling rate the driver sustains with 6 tools.

* ``ndi_bx_parse_6tools``: replies/s through ``FrameReader`` (both CRCs) + ``parse_bx`` for a
  6-tool BX reply. Baseline (same run): one bare ``struct.unpack`` of the same body, no CRC, no
  validation, no objects - the floor any Python BX decoder pays.
* ``ndi_poll_rate_6tools``: BX requests/s the driver core completes back to back against the
  emulator running in another process over TCP localhost. Baseline: a raw socket loop sending
  the same request and reading the same reply without any parsing.
* ``ndi_frames_at_60hz_6tools``: new device frames/s the driver delivers with its default
  phase-locked polling against a 60 Hz device (baseline: 60).
"""

from __future__ import annotations

import os
import socket
import statistics
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402
from benchlib import emit, median_time  # noqa: E402

from fullperc_drivers.ndi import replies as R  # noqa: E402
from fullperc_drivers.ndi.driver import DriverConfig, NdiDriver, ToolConfig  # noqa: E402
from fullperc_drivers.ndi.protocol import FrameReader, encode_binary_reply, encode_command  # noqa: E402
from fullperc_drivers.ndi.rom import TOOLS  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "src" / "fullperc_drivers" / "config" / "emulator_roms"   # synthetic
NAMES = list(TOOLS)


def bench_parse() -> None:
    tools = [R.ToolTransform(h, "valid", np.array([0.5, 0.5, -0.5, 0.5]), np.array([1.0, 2.0, -1500.0 - h]),
                             0.1, 0x31, 12345) for h in range(1, 7)]
    raw = encode_binary_reply(R.format_bx(R.TrackingData(tools, 0)))
    body = raw[6:-2]
    fmt = struct.Struct("<B" + "BB8fII" * 6 + "H")

    def ours():
        fr = FrameReader()
        fr.feed(raw)
        return R.parse_bx(fr.pop().data)

    def floor():
        return fmt.unpack(body)

    assert len(ours().tools) == 6
    t_ours = median_time(ours, repeats=7, number=2000)
    t_floor = median_time(floor, repeats=7, number=20000)
    emit("ndi_bx_parse_6tools", 1.0 / t_ours, "replies/s", baseline=1.0 / t_floor, bytes=len(raw))


def start_emulator(tmp: Path) -> tuple[subprocess.Popen, int]:
    port_file = tmp / "port"
    args = [sys.executable, "-m", "fullperc_eval.emulators.vega_cli", "--port", "0", "--port-file", str(port_file)]
    for i, n in enumerate(NAMES):
        args += ["--tool", f"{n}={CONFIG / (n + '.rom')}", "--pose", f"{n}={100 * i - 250},0,{-1500 - 30 * i}"]
    p = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    end = time.monotonic() + 30
    while not port_file.exists():
        if time.monotonic() > end or p.poll() is not None:
            raise RuntimeError("emulator did not start")
        time.sleep(0.05)
    return p, int(port_file.read_text())


def driver_rate(port: int, rate_hz: float, seconds: float) -> tuple[float, float]:
    """(BX replies/s, new frames/s) over ``seconds`` after the driver is tracking."""
    new = []
    cfg = DriverConfig(port=port, tools=[ToolConfig(n, (CONFIG / f"{n}.rom").read_bytes()) for n in NAMES],
                       rate_hz=rate_hz)
    d = NdiDriver(cfg, on_frame=lambda fr: new.append(fr.frame_number))
    d.start()
    end = time.monotonic() + 20
    while d.state != "tracking" and time.monotonic() < end:
        time.sleep(0.01)
    time.sleep(0.3)
    f0, n0, t0 = d.counters.frames, len(new), time.monotonic()
    time.sleep(seconds)
    f1, n1, t1 = d.counters.frames, len(new), time.monotonic()
    d.stop()
    if d.counters.crc_errors or d.counters.timeouts:
        raise RuntimeError(f"errors during the benchmark: {d.counters}")
    return (f1 - f0) / (t1 - t0), (n1 - n0) / (t1 - t0)


def raw_rate(port: int, seconds: float) -> float:
    """The same BX request/reply cycle with a bare socket and no parsing (after a minimal setup)."""
    s = socket.create_connection(("127.0.0.1", port))
    s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def ask(raw: bytes) -> bytes:
        s.sendall(raw)
        buf = s.recv(65536)
        while not (buf.endswith(b"\r") or (buf[:2] == b"\xc4\xa5" and len(buf) >= 8
                                             and len(buf) == struct.unpack_from("<H", buf, 2)[0] + 8)):
            buf += s.recv(65536)
        return buf

    ask(encode_command("INIT"))
    for n in NAMES:
        h = int(ask(encode_command("PHRQ", "*********1****"))[:2], 16)
        rom = (CONFIG / f"{n}.rom").read_bytes()
        for p in R.pvwr_params(h, rom):
            ask(encode_command("PVWR", p))
        ask(encode_command("PINIT", f"{h:02X}"))
        ask(encode_command("PENA", f"{h:02X}D"))
    ask(encode_command("TSTART"))
    bx = encode_command("BX", "0001")
    n, t0 = 0, time.monotonic()
    while time.monotonic() - t0 < seconds:
        ask(bx)
        n += 1
    rate = n / (time.monotonic() - t0)
    s.close()
    return rate


def bench_polling() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        p, port = start_emulator(Path(tmp))
        try:
            drv, raw = [], []
            for _ in range(3):
                drv.append(driver_rate(port, 0.0, 2.0)[0])
                raw.append(raw_rate(port, 2.0))
            emit("ndi_poll_rate_6tools", statistics.median(drv), "requests/s", baseline=statistics.median(raw),
                 transport="tcp localhost, emulator in its own process")
            frames = [driver_rate(port, 60.0, 3.0)[1] for _ in range(3)]
            emit("ndi_frames_at_60hz_6tools", statistics.median(frames), "frames/s", baseline=60.0)
        finally:
            p.terminate()
            p.wait(10)


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    bench_parse()
    bench_polling()
