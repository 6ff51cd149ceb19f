"""The records of a simulated bag serialised in bulk: CDR (little endian) of whole topics at once, with numpy.

Why: :func:`.dataset.write_bag` built a rosbags message object per message and serialised each one (~40 k messages
per task bag): about half of writing a bag, which ``make dataset``, ``make accuracy`` and the tests do for every
simulated or synthetic recording. Every message of a topic has the same layout here (the frame_id, body and joint
names are the topic's), so a topic's records are one (n, length) byte array filled column by column:

    0   encapsulation 00 01 00 00, 4 stamp.sec int32, 8 stamp.nanosec uint32, 12 frame_id (uint32 length with the
        NUL, the bytes, NUL), then each field aligned to its size counted from byte 4; a string or a sequence is a
        uint32 length (aligned to 4) and its elements (aligned to their size, only when there are any)

-- what rosbags' serialiser writes, padding bytes zero. ``write_bag`` checks each topic's first record against
rosbags' own serialisation before it uses a topic's bulk records (else it serialises that bag message by message),
and ``test_twin_profiles.py`` pins every record of a bag equal to the per-message path.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

CDR_LE = np.frombuffer(b"\x00\x01\x00\x00", np.uint8)


def _align(off: int, size: int) -> int:
    """``off`` rounded up to a multiple of ``size`` counted from the CDR body at byte 4."""
    return 4 + -(-(off - 4) // size) * size


class _Layout:
    """Offsets of a record's fields, laid out one after another as rosbags' serialiser places them."""

    def __init__(self, frame_id: str) -> None:
        self.fixed: list[tuple[int, bytes]] = [(0, CDR_LE.tobytes())]   # constant bytes: (offset, bytes)
        self.off = 12
        self.string(frame_id)

    def string(self, s: str) -> None:
        data = s.encode() + b"\x00"
        self.off = _align(self.off, 4)
        self.fixed.append((self.off, len(data).to_bytes(4, "little") + data))
        self.off += 4 + len(data)

    def count(self, n: int) -> None:
        self.off = _align(self.off, 4)
        self.fixed.append((self.off, n.to_bytes(4, "little")))
        self.off += 4

    def field(self, size: int, k: int = 1) -> int:
        """Offset of ``k`` values of ``size`` bytes (aligned to ``size``)."""
        self.off = _align(self.off, size)
        at = self.off
        self.off += size * k
        return at

    def rows(self, t_ns: np.ndarray) -> np.ndarray:
        """(n, length) records with the constant bytes and the stamps filled in."""
        t = np.asarray(t_ns, np.int64)
        out = np.zeros((len(t), self.off), np.uint8)
        for at, data in self.fixed:
            out[:, at:at + len(data)] = np.frombuffer(data, np.uint8)
        _put(out, 4, t // 1_000_000_000, "<i4")
        _put(out, 8, t % 1_000_000_000, "<u4")
        return out


def _put(rows: np.ndarray, at: int, values, dtype: str) -> None:
    """Write ``values`` ((n,) or (n, k)) as ``dtype`` at byte ``at`` of every row."""
    if not len(rows):
        return
    v = np.ascontiguousarray(np.asarray(values).astype(dtype, copy=False)).reshape(len(rows), -1)
    rows[:, at:at + v.shape[1] * v.itemsize] = v.view(np.uint8)


def _split(rows: np.ndarray) -> list[bytes]:
    flat, n = rows.tobytes(), rows.shape[1]
    return [flat[i:i + n] for i in range(0, len(flat), n)]


def pose_stamped(t_ns: np.ndarray, frame_id: str, p: np.ndarray, q: np.ndarray) -> list[bytes]:
    """geometry_msgs/PoseStamped records: position (n, 3), orientation x y z w (n, 4), float64."""
    lay = _Layout(frame_id)
    at = lay.field(8, 7)
    rows = lay.rows(t_ns)
    _put(rows, at, np.concatenate([np.asarray(p, float).reshape(-1, 3), np.asarray(q, float).reshape(-1, 4)], 1),
         "<f8")
    return _split(rows)


def tracking_quality(t_ns: np.ndarray, frame_id: str, body: str, visible: np.ndarray, fit_error: np.ndarray,
                     frame_number: np.ndarray, markers_used: np.ndarray, latency: float,
                     port_status: int) -> list[bytes]:
    """fullperc_msgs/TrackingQuality records: ``fit_error`` float32 values, ``frame_number`` / ``markers_used`` in
    their wire ranges (uint32 / uint16), one ``latency`` (float32) and ``port_status`` for the topic."""
    lay = _Layout(frame_id)
    lay.string(body)
    at_vis, at_fit, at_num, at_mk = lay.field(1), lay.field(4), lay.field(4), lay.field(2)
    at_lat, at_port = lay.field(4), lay.field(4)
    rows = lay.rows(t_ns)
    _put(rows, at_vis, np.asarray(visible, bool), "u1")
    _put(rows, at_fit, fit_error, "<f4")
    _put(rows, at_num, frame_number, "<u4")
    _put(rows, at_mk, markers_used, "<u2")
    _put(rows, at_lat, np.full(len(rows), latency, np.float32), "<f4")
    _put(rows, at_port, np.full(len(rows), port_status, np.int64), "<u4")
    return _split(rows)


def joint_state(t_ns: np.ndarray, frame_id: str, names: Sequence[str], position: np.ndarray,
                velocity: np.ndarray | None) -> list[bytes]:
    """sensor_msgs/JointState records: ``position`` (n, len(names)), ``velocity`` the same or None (empty), effort
    empty."""
    lay = _Layout(frame_id)
    lay.count(len(names))
    for name in names:
        lay.string(name)
    k = len(names)
    lay.count(k)
    at_pos = lay.field(8, k) if k else None
    kv = 0 if velocity is None else k
    lay.count(kv)
    at_vel = lay.field(8, kv) if kv else None
    lay.count(0)
    rows = lay.rows(t_ns)
    if at_pos is not None:
        _put(rows, at_pos, np.asarray(position, float).reshape(len(rows), k), "<f8")
    if at_vel is not None:
        _put(rows, at_vel, np.asarray(velocity, float).reshape(len(rows), k), "<f8")
    return _split(rows)
