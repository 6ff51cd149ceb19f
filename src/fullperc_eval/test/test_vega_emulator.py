"""The Vega emulator at the byte level, through a plain TCP socket (no fullperc driver involved)."""

from __future__ import annotations

import socket
from pathlib import Path

import numpy as np
import pytest

from fullperc_drivers.ndi import replies as R
from fullperc_drivers.ndi.crc import crc16_hex
from fullperc_drivers.ndi.protocol import FrameReader, NdiCrcError, encode_command
from fullperc_drivers.ndi.rom import read_rom
from fullperc_eval.emulators.vega_device import ToolPose, pyramid_frustum
from fullperc_eval.emulators.vega_server import FaultConfig, VegaEmulator

CONFIG = Path(__file__).resolve().parents[2] / "fullperc_drivers" / "config" / "emulator_roms"   # synthetic
ROMS = {n: (CONFIG / f"{n}.rom").read_bytes() for n in ("tool", "base")}
POSE = ToolPose(np.array([12.5, -7.25, -1500.0]), np.array([0.0, 0.0, 0.6, 0.8]), 0.07)


class Raw:
    """Minimal byte-level client."""

    def __init__(self, port):
        self.s = socket.create_connection(("127.0.0.1", port), timeout=5)
        self.fr = FrameReader()

    def send(self, raw: bytes):
        self.s.sendall(raw)
        while True:
            rep = self.fr.pop()
            if rep is not None:
                return rep
            data = self.s.recv(65536)
            assert data, "emulator closed the connection"
            self.fr.feed(data)

    def cmd(self, name, params="", crc=True):
        return self.send(encode_command(name, params, crc)).text

    def raw_reply(self, raw: bytes) -> bytes:
        self.s.sendall(raw)
        return self.s.recv(65536)


@pytest.fixture
def emu():
    poses = {"tool": POSE, "base": None}
    e = VegaEmulator(lambda t: poses, ROMS).start()
    yield e
    e.stop()


def load(c: Raw, rom: bytes, lower=False) -> int:
    h = int(c.cmd("PHRQ", "*********1****"), 16)
    for i in range(0, 1024, 64):
        chunk = rom[i:i + 64].ljust(64, b"\0").hex()
        c_hex = chunk if lower else chunk.upper()
        assert c.cmd("PVWR", f"{h:02x}{i:04x}{c_hex}" if lower else f"{h:02X}{i:04X}{c_hex}") == "OKAY"
    return h


def test_both_command_forms_and_bad_crc(emu):
    c = Raw(emu.port)
    assert c.raw_reply(b"INIT:E3A5\r") == b"OKAYA896\r"  # byte for byte as a real device
    assert c.raw_reply(b"INIT \r") == b"OKAYA896\r"
    assert c.raw_reply(b"INIT:E3A6\r") == b"ERROR04" + crc16_hex("ERROR04").encode() + b"\r"
    assert c.raw_reply(b"PHSR:0020FF\r") == b"001414\r"
    assert c.cmd("FOO", "1").startswith("ERROR01")


def test_handle_lifecycle_and_phsr(emu):
    c = Raw(emu.port)
    assert c.cmd("TSTART").startswith("ERROR10")  # not initialized
    c.cmd("INIT")
    h1 = load(c, ROMS["tool"])
    h2 = int(c.cmd("PHRQ", "*********1****"), 16)  # allocated, no ROM
    assert R.parse_phsr(c.cmd("PHSR", "01")) == [(h2, 0x000)]
    assert R.parse_phsr(c.cmd("PHSR", "02")) == [(h1, 0x001)]
    assert c.cmd("PINIT", f"{h2:02X}").startswith("ERROR0D")
    assert c.cmd("PHF", f"{h2:02X}") == "OKAY"
    assert c.cmd("PENA", f"{h1:02X}D").startswith("ERROR0E")  # not initialized yet
    assert c.cmd("PINIT", f"{h1:02x}", crc=False) == "OKAY"  # lowercase, space form (SKS / NDI-CPP)
    assert R.parse_phsr(c.cmd("PHSR", "03")) == [(h1, 0x011)]
    assert c.cmd("PENA", f"{h1:02X}X").startswith("ERROR09")
    assert c.cmd("PENA", f"{h1:02x}D") == "OKAY"
    assert R.parse_phsr(c.cmd("PHSR", "04")) == [(h1, 0x031)]
    assert R.parse_phsr(c.cmd("PHSR", "00")) == [(h1, 0x031)]
    assert c.cmd("PHINF", f"{h1:02X}0004").strip() == "8700339"
    assert c.cmd("BX", "0001").startswith("ERROR0C")  # not tracking
    assert c.cmd("TSTART") == "OKAY"
    assert c.cmd("PHRQ", "*********1****").startswith("ERROR0C")  # setup commands refused while tracking
    assert c.cmd("TSTOP") == "OKAY"


def test_rom_upload_is_stored_exactly_and_matched(emu):
    c = Raw(emu.port)
    c.cmd("INIT")
    h = load(c, ROMS["base"], lower=True)
    assert emu.device.loaded_rom(h)[:752] == ROMS["base"]
    assert not any(emu.device.loaded_rom(h)[752:])
    c.cmd("PINIT", f"{h:02X}")
    assert emu.device.handles[h].tool == "base"
    assert read_rom(emu.device.loaded_rom(h)).part_number == "8700449"


def test_tracking_replies_bx_tx_and_missing(emu):
    c = Raw(emu.port)
    c.cmd("INIT")
    ht, hb = load(c, ROMS["tool"]), load(c, ROMS["base"])
    for h in (ht, hb):
        c.cmd("PINIT", f"{h:02X}")
        c.cmd("PENA", f"{h:02X}D")
    c.cmd("TSTART")
    rep = c.send(encode_command("BX", "0801"))
    assert rep.binary
    d = R.parse_bx(rep.data, 0x0801).by_handle()
    np.testing.assert_allclose(d[ht].t_mm, POSE.position_mm)
    np.testing.assert_allclose(d[ht].q_wxyz, [0.8, 0.0, 0.0, 0.6], atol=1e-7)  # scalar first on the wire
    assert d[ht].error_mm == pytest.approx(0.07, abs=1e-7)
    assert d[hb].status == "missing" and d[hb].port_status == 0x31
    assert d[ht].frame_number == d[hb].frame_number
    t = R.parse_tx(c.cmd("TX", "0001")).by_handle()
    np.testing.assert_allclose(t[ht].t_mm, POSE.position_mm, atol=0.005)
    assert t[hb].status == "missing"
    f1 = t[ht].frame_number
    f2 = R.parse_bx(c.send(encode_command("BX", "0001")).data).frame_number
    assert f2 >= f1


def test_outside_frustum_is_missing_unless_0800():
    far = ToolPose(np.array([0.0, 0.0, -3000.0]))
    e = VegaEmulator(lambda t: {"tool": far}, ROMS, frustum=pyramid_frustum()).start()
    try:
        c = Raw(e.port)
        c.cmd("INIT")
        h = load(c, ROMS["tool"])
        c.cmd("PINIT", f"{h:02X}")
        c.cmd("PENA", f"{h:02X}D")
        c.cmd("TSTART")
        assert R.parse_bx(c.send(encode_command("BX", "0001")).data).tools[0].status == "missing"
        t = R.parse_bx(c.send(encode_command("BX", "0801")).data, 0x0801).tools[0]
        assert t.status == "valid" and t.port_status & R.PORT_OUT_OF_VOLUME
    finally:
        e.stop()


def test_frustum_geometry():
    f = pyramid_frustum(950, 2400, 20, 15)  # the margin model's Frustum, in metres
    pts = np.array([[0, 0, -1500], [0, 0, 1500], [0, 0, -900], [0, 0, -2500], [600, 0, -1500], [0, 450, -1500]])
    assert f.contains(pts / 1000.0).tolist() == [True, False, False, False, False, False]
    # the pyramid's lateral faces: |x| <= d tan(20 deg), |y| <= d tan(15 deg) at every depth d
    for d in (950.0, 1200.0, 1700.0, 2400.0):
        x, y = d * np.tan(np.radians(20.0)), d * np.tan(np.radians(15.0))
        inside = np.array([[0.999 * x, 0, -d], [0, 0.999 * y, -d], [1.001 * x, 0, -d], [0, 1.001 * y, -d]])
        assert f.contains(inside / 1000.0).tolist() == [True, True, False, False]
    # as a margin-model Frustum the pyramid is |x| <= d tan(ax), |y| <= d tan(ay), near <= d <= far, everywhere
    rng = np.random.default_rng(0)
    p = np.column_stack([rng.uniform(-900, 900, 20000), rng.uniform(-800, 800, 20000), rng.uniform(-2600, -800, 20000)])
    d = -p[:, 2]
    closed_form = ((d >= 950) & (d <= 2400) & (np.abs(p[:, 0]) <= d * np.tan(np.radians(20.0)))
                   & (np.abs(p[:, 1]) <= d * np.tan(np.radians(15.0))))
    assert f.contains(p / 1000.0).tolist() == closed_form.tolist() and 1000 < closed_form.sum() < 19000


def test_ver_get_set(emu):
    c = Raw(emu.port)
    assert "Freeze Tag: Polaris Vega 010" in c.cmd("VER", "0").split("\n")
    assert R.parse_apirev(c.cmd("APIREV")).family == "G"
    vals = R.parse_get(c.cmd("GET", "Param.Tracking.*"))
    assert vals["Param.Tracking.Selected Volume"] == "0"
    assert c.cmd("SET", "Param.Tracking.Selected Volume=1") == "OKAY"
    assert R.parse_get(c.cmd("GET", "Param.Tracking.Selected Volume")) == {"Param.Tracking.Selected Volume": "1"}
    assert c.cmd("SET", "Features.Firmware.Version=1").startswith("ERROR39")
    assert c.cmd("GET", "No.Such").startswith("ERROR34")
    assert c.cmd("BEEP", "2") == "1"
    assert c.cmd("ECHO", "Testing!", crc=False) == "Testing!"


def test_fault_corrupt_crc_is_detected_by_the_parser():
    e = VegaEmulator(lambda t: {}, ROMS, faults=FaultConfig(corrupt_crc_prob=1.0, seed=1)).start()
    try:
        c = Raw(e.port)
        with pytest.raises(NdiCrcError):
            c.send(b"INIT:E3A5\r")
        assert e.stats.corrupted == 1
    finally:
        e.stop()


def test_fault_drop_closes_the_link(emu):
    c = Raw(emu.port)
    c.cmd("INIT")
    emu.drop_link()
    c.s.settimeout(2)
    try:
        c.s.sendall(b"INIT:E3A5\r")
        assert c.s.recv(100) == b""
    except OSError:
        pass
    Raw(emu.port).cmd("INIT")  # the server keeps accepting
    assert emu.stats.drops == 1


def test_align_frames_puts_frame_times_on_the_given_grid_and_never_back():
    """``align_frames``: the frame times fall on ``ref + k / rate`` (to rounding), the frame number at a given
    time does not go back (it may skip one), and ``TSTART:80`` (frame numbers restart) keeps the grid."""
    from fullperc_eval.emulators.vega_device import VegaDevice

    dev = VegaDevice(ROMS, frame_rate_hz=60.0)
    period = 1e9 / 60.0
    ref = dev.t0_ns + 5_000_000_000 + 7_777_777   # off the emulator's own grid by 7.8 ms, and in its future
    now = dev.t0_ns + 3_210_000_000
    before = dev.frame_number(now)
    dev.align_frames(ref)
    assert before <= dev.frame_number(now) <= before + 1
    for f in (dev.frame_number(now), dev.frame_number(now) + 1, dev.frame_number(now) + 600):
        k = (dev.frame_time_ns(f) - ref) / period
        assert abs(k - round(k)) * period <= 2, f   # nanoseconds
    # frame f is captured at its frame time: the device's clock at that time reads f
    f = dev.frame_number(now)
    assert dev.frame_number(dev.frame_time_ns(f)) == f and dev.frame_time_ns(f) <= now
    dev.handle_line(encode_command("INIT"))
    dev.handle_line(encode_command("TSTART", "80"))
    f = dev.frame_number()
    k = (dev.frame_time_ns(f) - ref) / period
    assert f in (dev.frame_start, dev.frame_start + 1) and abs(k - round(k)) * period <= 2
