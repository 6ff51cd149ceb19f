"""Tool definition files: the writer, the reader, and the emulator .rom files shipped in config/emulator_roms/."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from fullperc_drivers.ndi.protocol import NdiProtocolError
from fullperc_drivers.ndi.rom import ROM_SIZE, TOOLS, read_rom, write_rom

CONFIG = Path(__file__).resolve().parents[1] / "config" / "emulator_roms"   # synthetic

# ndi.md §6, geometries of real NDI tools (copied from the reference, not from rom.py).
NDI_GEOMETRIES = {
    "8700339": [(0, 0, 0), (0, 28.59, 41.02), (0, 0, 88.0), (0, -44.32, 40.45)],
    "8700340": [(0, 0, 0), (0, 0, 50), (0, 25, 100), (0, -25, 135)],
    "8700338": [(0, 0, 0), (0, 25.28, 16.15), (0, 0, 65), (0, -18.65, 29.61)],
    "8700449": [(0, 0, 0), (0, 47.38, 28.99), (0, 0, 89.1), (0, -35.36, 35.36)],
}


def test_known_offsets():
    rom = write_rom([(1, 2, 3), (4, 5, 6), (7, 8, 9)], "8700339")
    assert len(rom) == ROM_SIZE == 752
    assert rom[:4] == b"NDI\x00"
    assert rom[0x1C] == 3
    np.testing.assert_array_equal(np.frombuffer(rom, "<f4", 9, 0x48), np.arange(1, 10, dtype="<f4"))
    assert rom[0x250:0x257] == b"8700339" and rom[0x244:0x247] == b"NDI"


@pytest.mark.parametrize("name", sorted(TOOLS))
def test_shipped_roms(name):
    data = (CONFIG / f"{name}.rom").read_bytes()
    info = read_rom(data, verify=True)
    part = TOOLS[name][0]
    assert info.part_number == part
    if part in NDI_GEOMETRIES:
        np.testing.assert_allclose(info.markers_mm, NDI_GEOMETRIES[part], atol=1e-4)
    # the padded image a host writes with PVWR reads the same
    assert read_rom(data.ljust(1024, b"\0")).part_number == part


def test_shipped_roms_are_distinguishable():
    """Tools must differ in their inter-marker distances, or a tracker could confuse them."""
    sigs = []
    for name in TOOLS:
        p = read_rom((CONFIG / f"{name}.rom").read_bytes()).markers_mm
        d = np.sort(np.linalg.norm(p[:, None] - p[None], axis=-1)[np.triu_indices(len(p), 1)])
        sigs.append(d)
    for i in range(len(sigs)):
        for j in range(i + 1, len(sigs)):
            assert np.max(np.abs(sigs[i] - sigs[j])) > 2.0


def test_rejects_non_roms():
    with pytest.raises(NdiProtocolError):
        read_rom(b"XYZ" + bytes(800))
    with pytest.raises(NdiProtocolError):
        read_rom(b"NDI\x00" + bytes(100))
    bad = bytearray(write_rom([(0, 0, 0), (1, 0, 0), (0, 1, 0)], "X"))
    bad[0x1C] = 1
    with pytest.raises(NdiProtocolError):
        read_rom(bytes(bad))
    with pytest.raises(ValueError):
        write_rom([(0, 0, 0), (1, 0, 0)], "X")
