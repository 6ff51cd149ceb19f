"""A real third-party client against the emulator: scikit-surgerynditracker on ndicapi (C).

The emulator runs as its own process (the installed ``vega_emulator``): ndicapy holds the GIL
during some blocking calls (ndiPVWRFromFile), so an in-process server would deadlock.
SKS pings the host first; this machine has no ``ping``, so that one call is stubbed.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from fullperc_common.testing import installed_exe, wait_for

sks = pytest.importorskip("sksurgerynditracker.nditracker")
ndicapy = pytest.importorskip("ndicapy")

CONFIG = Path(__file__).resolve().parents[2] / "fullperc_drivers" / "config" / "emulator_roms"   # synthetic
ALL = ["tool", "base", "tool_b", "tool_c", "tool_d", "tool_e"]
Q_XYZW = np.array([0.1, 0.2, 0.3, np.sqrt(1 - 0.14)])


def pose_of(i):
    return [30.0 * i - 60, -20.0 * i + 10, -1400.0 - 50 * i]


def start_emulator(procs, tmp_path, names, freeze_tag, hidden=()):
    port_file = tmp_path / "port"
    args = [installed_exe("fullperc_eval", "vega_emulator"), "--port", "0", "--port-file", str(port_file),
            "--freeze-tag", freeze_tag]
    for i, n in enumerate(names):
        args += ["--tool", f"{n}={CONFIG / (n + '.rom')}",
                 "--pose", f"{n}=" + ",".join(map(str, pose_of(i) + list(Q_XYZW)))]
    for n in hidden:
        args += ["--hidden", n]
    procs.start(args, name="vega_emulator")
    wait_for(port_file.exists, timeout=20, what="emulator port file")
    return int(port_file.read_text())


def sks_frames(port, names, n=5):
    tr = sks.NDITracker({"tracker type": "vega", "ip address": "127.0.0.1", "port": port,
                         "romfiles": [str(CONFIG / f"{x}.rom") for x in names], "use quaternions": True})
    try:
        tr.start_tracking()
        for _ in range(n):
            out = tr.get_frame()
        mode = tr._capture_string
        tr.stop_tracking()
    finally:
        tr.close()
    return mode, out


@pytest.fixture(autouse=True)
def no_ping(monkeypatch):
    monkeypatch.setattr(sks, "call", lambda *a, **k: 0)


def check(out, names, hidden=()):
    handles, _ts, frames, tracking, quality = out
    assert len(handles) == len(names)
    assert len(set(frames)) == 1  # one device frame for all tools
    for i, n in enumerate(names):
        row = np.asarray(tracking[i]).ravel()
        if n in hidden:
            assert np.all(np.isnan(row))
            continue
        # SKS quaternion rows are (qw, qx, qy, qz, x, y, z): scalar first, as NDI sends it
        np.testing.assert_allclose(row[:4], [Q_XYZW[3], *Q_XYZW[:3]], atol=1e-4)
        np.testing.assert_allclose(row[4:], pose_of(i), atol=0.01)
        assert quality[i] == pytest.approx(0.1, abs=1e-4)


def test_sks_bx_two_tools_with_rom_upload(procs, tmp_path):
    names = ["tool", "base"]
    port = start_emulator(procs, tmp_path, names, "Polaris Vega 010")
    mode, out = sks_frames(port, names)
    assert mode == "BX:0801"
    check(out, names)


@pytest.mark.parametrize("names", [ALL[:3], ALL])
def test_sks_three_or_more_tools(procs, tmp_path, names):
    """With firmware 'Polaris Vega 008' SKS polls TX:0801 (its workaround for >2 tools)."""
    hidden = ("tool_b",) if len(names) > 3 else ()
    port = start_emulator(procs, tmp_path, names, "Polaris Vega 008", hidden)
    mode, out = sks_frames(port, names)
    assert mode == "TX:0801"
    check(out, names, hidden)


def test_ndicapy_bx_three_visible_tools(procs, tmp_path):
    """ndicapi's C BX parser reads our 3-tool BX reply; ndicapy's Python wrapper then fails to
    turn the binary reply into a str (length byte 129 = 0x81 is invalid UTF-8, ndi.md §8.1) -
    exactly the SKS >2-tools bug on real Vegas, reproduced byte for byte."""
    names = ALL[:3]
    port = start_emulator(procs, tmp_path, names, "Polaris Vega 010")
    dev = ndicapy.ndiOpenNetwork("127.0.0.1", port)
    try:
        ndicapy.ndiCommand(dev, "INIT:")
        handles = []
        for n in names:
            ndicapy.ndiCommand(dev, "PHRQ:*********1****")
            h = ndicapy.ndiGetPHRQHandle(dev)
            ndicapy.ndiPVWRFromFile(dev, h, str(CONFIG / f"{n}.rom"))
            ndicapy.ndiCommand(dev, f"PINIT:{h:02X}")
            ndicapy.ndiCommand(dev, f"PENA:{h:02X}D")
            handles.append(h)
        assert ndicapy.ndiGetError(dev) == ndicapy.NDI_OKAY
        ndicapy.ndiCommand(dev, "TSTART:")
        with pytest.raises(UnicodeDecodeError):
            ndicapy.ndiCommand(dev, "BX:0801")
        assert ndicapy.ndiGetError(dev) == ndicapy.NDI_OKAY  # C side: CRCs fine, reply parsed
        for i, h in enumerate(handles):
            t = ndicapy.ndiGetBXTransform(dev, bytes([h]))
            np.testing.assert_allclose(t[:4], [Q_XYZW[3], *Q_XYZW[:3]], atol=1e-6)
            np.testing.assert_allclose(t[4:7], pose_of(i), atol=1e-3)
        ndicapy.ndiCommand(dev, "TSTOP:")
    finally:
        ndicapy.ndiCloseNetwork(dev)
