"""Wire formats of the simulator's UDP streams (OMC frames and Diana joint state).

The OMC datagram mirrors the NOKOV SDK frame (``sFrameOfMocapData``/``sRigidBodyData``, see
reference/nokov_mocap.md): frame number, device timestamp, latency, and per rigid body its id,
name, position in millimetres, quaternion (x y z w), mean marker error and a tracking flag.
Device units (mm) stay on the wire; the drivers convert to SI. All little-endian, no padding.

Both decoders raise :class:`StreamDecodeError` (and nothing else) on any malformed datagram,
so a driver can count and skip it.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

import numpy as np

OMC_MAGIC = b"FPOM"
DIANA_MAGIC = b"FPDA"
VERSION = 1

# magic, version, n_bodies, frame_number, device timestamp [ns, device clock], latency [s]
_OMC_HEAD = struct.Struct("<4sHHIqf")
# id, name, x y z [mm], qx qy qz qw, mean error [mm], tracked, markers used
_OMC_BODY = struct.Struct("<i32s3d4dfBH")
# magic, version, n_joints, sequence, device timestamp [ns]
_DIANA_HEAD = struct.Struct("<4sHHIq")
MAX_BODIES = 64
MAX_JOINTS = 16


class StreamDecodeError(ValueError):
    """A datagram that is not a valid frame of the expected stream."""


@dataclass
class OmcBody:
    id: int
    name: str
    position_mm: np.ndarray  # (3,)
    quat_xyzw: np.ndarray  # (4,)
    mean_error_mm: float
    tracked: bool
    markers: int = 0


@dataclass
class OmcFrame:
    frame_number: int
    timestamp_ns: int  # device clock
    latency_s: float
    bodies: list[OmcBody] = field(default_factory=list)


@dataclass
class DianaState:
    sequence: int
    timestamp_ns: int  # device clock
    q: np.ndarray  # joint positions [rad]
    dq: np.ndarray  # joint velocities [rad/s]


def encode_omc(frame: OmcFrame) -> bytes:
    parts = [_OMC_HEAD.pack(OMC_MAGIC, VERSION, len(frame.bodies), frame.frame_number & 0xFFFFFFFF,
                            int(frame.timestamp_ns), float(frame.latency_s))]
    for b in frame.bodies:
        name = b.name.encode("utf-8")[:31]
        parts.append(_OMC_BODY.pack(int(b.id), name, *map(float, b.position_mm), *map(float, b.quat_xyzw),
                                    float(b.mean_error_mm), 1 if b.tracked else 0, int(b.markers)))
    return b"".join(parts)


def decode_omc(data: bytes) -> OmcFrame:
    if len(data) < _OMC_HEAD.size:
        raise StreamDecodeError(f"OMC datagram too short ({len(data)} bytes)")
    magic, ver, n, fno, ts, lat = _OMC_HEAD.unpack_from(data, 0)
    if magic != OMC_MAGIC:
        raise StreamDecodeError(f"bad OMC magic {magic!r}")
    if ver != VERSION:
        raise StreamDecodeError(f"unsupported OMC stream version {ver}")
    if n > MAX_BODIES or len(data) != _OMC_HEAD.size + n * _OMC_BODY.size:
        raise StreamDecodeError(f"OMC datagram length {len(data)} does not match {n} bodies")
    frame = OmcFrame(frame_number=fno, timestamp_ns=ts, latency_s=lat)
    off = _OMC_HEAD.size
    for _ in range(n):
        bid, name, x, y, z, qx, qy, qz, qw, err, tracked, markers = _OMC_BODY.unpack_from(data, off)
        off += _OMC_BODY.size
        try:
            sname = name.rstrip(b"\0").decode("utf-8")
        except UnicodeDecodeError as e:
            raise StreamDecodeError(f"OMC body name is not UTF-8: {name!r}") from e
        frame.bodies.append(OmcBody(bid, sname, np.array([x, y, z]), np.array([qx, qy, qz, qw]),
                                    err, bool(tracked), markers))
    return frame


def encode_diana(state: DianaState) -> bytes:
    q = np.asarray(state.q, dtype="<f8")
    dq = np.asarray(state.dq, dtype="<f8")
    if q.shape != dq.shape or q.ndim != 1:
        raise ValueError("q and dq must be 1-D arrays of the same length")
    head = _DIANA_HEAD.pack(DIANA_MAGIC, VERSION, q.size, state.sequence & 0xFFFFFFFF, int(state.timestamp_ns))
    return head + q.tobytes() + dq.tobytes()


def decode_diana(data: bytes) -> DianaState:
    if len(data) < _DIANA_HEAD.size:
        raise StreamDecodeError(f"Diana datagram too short ({len(data)} bytes)")
    magic, ver, n, seq, ts = _DIANA_HEAD.unpack_from(data, 0)
    if magic != DIANA_MAGIC:
        raise StreamDecodeError(f"bad Diana magic {magic!r}")
    if ver != VERSION:
        raise StreamDecodeError(f"unsupported Diana stream version {ver}")
    if n > MAX_JOINTS or len(data) != _DIANA_HEAD.size + 16 * n:
        raise StreamDecodeError(f"Diana datagram length {len(data)} does not match {n} joints")
    arr = np.frombuffer(data, dtype="<f8", offset=_DIANA_HEAD.size)
    return DianaState(seq, ts, arr[:n].astype(float), arr[n:].astype(float))
