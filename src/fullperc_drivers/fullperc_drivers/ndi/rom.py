"""NDI passive tool definition (.rom) files: the parts of the layout that are known, and a writer.

Known layout (reference/ndi.md §6, verified there on real NDI ROMs 8700338/339/340/449):
752 bytes, ``NDI\\0`` magic at 0, marker count at byte 28 (0x1C), marker positions as float32 LE
x, y, z triples in millimetres from byte 72 (0x48), manufacturer at 0x244 and the part number
string at 0x250. Real files carry an internal checksum whose location is UNCERTAIN (bytes 4-5
differ per file); our writer stores a CRC-16/ARC of bytes 6..751 at bytes 4-5 — our own
convention, checked only by :func:`read_rom` with ``verify=True``, never required of real files.

``python -m fullperc_drivers.ndi.rom OUTDIR`` (re)writes the .rom files shipped in
``fullperc_drivers/config/emulator_roms`` (:data:`EMULATOR_ROM_DIR`) from the geometries in :data:`TOOLS`. They are
synthetic, for the Vega emulator: a real tracker needs its tool maker's ROMs, which is why they live in a folder
whose name says so (config/emulator_roms/README.md).
"""

from __future__ import annotations

import struct
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .crc import crc16
from .protocol import NdiProtocolError

ROM_SIZE = 752
# Sub-folder of fullperc_drivers' config/ holding the synthetic emulator ROMs (share_path("fullperc_drivers", "config",
# EMULATOR_ROM_DIR)). Every default or demo reference names it, so no path to one of them can pass for a real ROM.
EMULATOR_ROM_DIR = "emulator_roms"
MAGIC = b"NDI\x00"
OFF_CHECKSUM = 4
OFF_MARKER_COUNT = 0x1C
OFF_MARKERS = 0x48
OFF_MANUFACTURER = 0x244
OFF_PART_NUMBER = 0x250
MAX_MARKERS = 20
PART_LEN = 20
MANUFACTURER_LEN = OFF_PART_NUMBER - OFF_MANUFACTURER

# Real NDI passive tool geometries (ndi.md §6), plus our own so tests can run 7 tools.
# name -> (part number, marker positions [mm])
TOOLS: dict[str, tuple[str, list[tuple[float, float, float]]]] = {
    "tool": ("8700339", [(0, 0, 0), (0, 28.59, 41.02), (0, 0, 88.0), (0, -44.32, 40.45)]),
    "base": ("8700449", [(0, 0, 0), (0, 47.38, 28.99), (0, 0, 89.1), (0, -35.36, 35.36)]),
    "tool_b": ("8700340", [(0, 0, 0), (0, 0, 50), (0, 25, 100), (0, -25, 135)]),
    "tool_c": ("8700338", [(0, 0, 0), (0, 25.28, 16.15), (0, 0, 65), (0, -18.65, 29.61)]),
    # Not NDI parts: distinct 4-marker planar geometries (segment lengths differ from the above).
    "tool_d": ("FP-0005", [(0, 0, 0), (0, 32.0, 22.0), (0, 0, 104.0), (0, -30.0, 61.0)]),
    "tool_e": ("FP-0006", [(0, 0, 0), (0, 52.0, 12.0), (0, 10.0, 77.0), (0, -40.0, 20.0)]),
    # The twin's patient reference frame (fullperc_eval.sim.breathing): larger (segments 58-130 mm, each at least 5 mm
    # from the others of the frame and the set unlike every tool above), as a patient reference is.
    "reference": ("FP-0007", [(0, 0, 0), (0, 50.0, 30.0), (0, 0, 130.0), (0, -60.0, 70.0)]),
}


class RomFileError(ValueError):
    """A tool's ROM file cannot be read or is not an NDI tool definition; the message names tool and file.

    Raised at start-up, before anything is sent to a device: a node treats it as fatal (exit 2).
    """


@dataclass(frozen=True)
class RomInfo:
    part_number: str
    manufacturer: str
    markers_mm: np.ndarray  # (n, 3)

    @property
    def marker_count(self) -> int:
        return len(self.markers_mm)


def write_rom(markers_mm, part_number: str, manufacturer: str = "NDI") -> bytes:
    """A 752-byte passive-tool ROM image with the given marker geometry [mm]."""
    pts = np.asarray(markers_mm, dtype=float).reshape(-1, 3)
    if not 3 <= len(pts) <= MAX_MARKERS:
        raise ValueError(f"a passive tool needs 3..{MAX_MARKERS} markers, got {len(pts)}")
    if not np.all(np.isfinite(pts)):
        raise ValueError("marker positions must be finite")
    if len(part_number.encode("ascii")) > PART_LEN or len(manufacturer.encode("ascii")) > MANUFACTURER_LEN:
        raise ValueError("part number / manufacturer too long")
    buf = bytearray(ROM_SIZE)
    buf[0:4] = MAGIC
    buf[OFF_MARKER_COUNT] = len(pts)
    buf[OFF_MARKERS:OFF_MARKERS + 12 * len(pts)] = pts.astype("<f4").tobytes()
    buf[OFF_MANUFACTURER:OFF_MANUFACTURER + len(manufacturer)] = manufacturer.encode("ascii")
    buf[OFF_PART_NUMBER:OFF_PART_NUMBER + len(part_number)] = part_number.encode("ascii")
    struct.pack_into("<H", buf, OFF_CHECKSUM, crc16(buf[6:]))
    return bytes(buf)


def _cstr(b: bytes) -> str:
    return b.split(b"\0", 1)[0].decode("latin-1").strip()


def read_rom(data: bytes, verify: bool = False) -> RomInfo:
    """Parse the known fields of a ROM image (``NdiProtocolError`` if it is not one).

    Accepts the zero-padded 1024-byte image a host writes with PVWR. ``verify`` also checks our
    own writer's checksum (see module docstring), which real NDI files do not satisfy.
    """
    data = bytes(data)
    if len(data) < ROM_SIZE or data[:4] != MAGIC:
        raise NdiProtocolError("not an NDI tool definition (size < 752 or no 'NDI\\0' magic)")
    if len(data) > 1024:
        raise NdiProtocolError("tool definition larger than the 1 KiB virtual SROM")
    n = data[OFF_MARKER_COUNT]
    if not 3 <= n <= MAX_MARKERS:
        raise NdiProtocolError(f"tool definition has {n} markers (3..{MAX_MARKERS} supported)")
    pts = np.frombuffer(data, dtype="<f4", count=3 * n, offset=OFF_MARKERS).astype(float).reshape(n, 3)
    if not np.all(np.isfinite(pts)):
        raise NdiProtocolError("tool definition has non-finite marker positions")
    if verify and struct.unpack_from("<H", data, OFF_CHECKSUM)[0] != crc16(data[6:ROM_SIZE]):
        raise NdiProtocolError("tool definition checksum mismatch")
    return RomInfo(_cstr(data[OFF_PART_NUMBER:OFF_PART_NUMBER + PART_LEN]),
                   _cstr(data[OFF_MANUFACTURER:OFF_PART_NUMBER]), pts)


def write_config_roms(outdir: str | Path) -> list[Path]:
    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, (part, pts) in TOOLS.items():
        p = out / f"{name}.rom"
        p.write_bytes(write_rom(pts, part, "NDI" if part.isdigit() else "FULLPERC"))
        paths.append(p)
    return paths


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 1:
        print("usage: python -m fullperc_drivers.ndi.rom OUTDIR", file=sys.stderr)
        return 2
    for p in write_config_roms(argv[0]):
        print(p)
    return 0


if __name__ == "__main__":
    sys.exit(main())
