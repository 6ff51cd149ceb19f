"""fusion_node's input messages read straight from their CDR bytes, without rclpy's deserializer.

Why: rclpy turns each received PoseStamped into a Python message -- six nested objects, every field through a
type-checking setter -- and fusion_node then reads seven floats and a stamp back out of it; a TrackingQuality the
same for five fields. That costs ~20 µs per message here, at 1,280 pose and 640 quality messages per second for one
target some 4 % of a core for nothing (``bench/bench_node_cost.py`` measures the node against a bare rclpy node).
A subscription made with ``raw=True`` hands over the serialized message, whose layout is fixed (the same ones
``fullperc_eval.bag.fast_decode`` reads in bulk from bags). PoseStamped:

    0   encapsulation: 00 01 00 00 (CDR, little endian, no options)
    4   header.stamp.sec (int32), 8: header.stamp.nanosec (uint32)
    12  header.frame_id: uint32 length n (with its NUL), then n bytes
    ..  pose.position x y z, pose.orientation x y z w: 7 float64, aligned to 8 bytes from byte 4

TrackingQuality: the same header, then ``body`` (uint32 length aligned to 4, the bytes with their NUL), ``visible``
(one byte, 0 or 1), ``fit_error`` (float32, aligned to 4), ``frame_number`` (uint32), ``markers_used`` (uint16),
``latency`` (float32, aligned to 4), ``port_status`` (uint32), the record ending there.

A record off its layout (big-endian CDR, encapsulation options, a length that does not add up, a string without its
NUL, a bool byte other than 0 or 1) is not guessed at: :func:`pose_from_cdr` and :func:`quality_from_cdr` give it to
rclpy's deserializer, which accepts or rejects it as before. The values are the deserializer's bit for bit
(``test_input_cdr.py`` compares them over random messages).
"""

from __future__ import annotations

import struct

import numpy as np

CDR_LE = b"\x00\x01\x00\x00"
_HEAD = struct.Struct("<iII")     # stamp sec, nanosec, frame_id length (at byte 4)
_POSE = struct.Struct("<7d")      # position xyz, orientation xyzw
POSE_BYTES = _POSE.size
_U32 = struct.Struct("<I")
_QUALITY = struct.Struct("<fIH")  # fit_error, frame_number, markers_used (at the aligned fit_error)


def cdr_align(off: int, a: int) -> int:
    """``off`` (from the start of the record) rounded up to ``a`` bytes, counted from the CDR body at byte 4."""
    return 4 + -(-(off - 4) // a) * a


def quality_layout(slen: int, blen: int) -> tuple[int, int, int, int, int, int, int]:
    """Offsets of the fields of a TrackingQuality record whose frame_id and body take ``slen`` / ``blen`` bytes (with
    their NUL): (body length, visible, fit_error, frame_number, markers_used, latency, port_status); the record ends
    4 bytes after the last. The one statement of the layout: :func:`quality_fields` here and the evaluator's bulk
    decoder (``fullperc_eval.bag.fast_decode``) read it."""
    off_blen = cdr_align(16 + slen, 4)
    off_vis = off_blen + 4 + blen
    off_fit = cdr_align(off_vis + 1, 4)
    off_num = off_fit + 4
    off_mk = off_num + 4
    off_lat = cdr_align(off_mk + 2, 4)
    off_port = off_lat + 4
    return off_blen, off_vis, off_fit, off_num, off_mk, off_lat, off_port


def pose_stamped_fields(data: bytes) -> tuple[int, tuple[float, ...]] | None:
    """(stamp [ns], (px, py, pz, qx, qy, qz, qw)) of a PoseStamped in the fixed little-endian layout (module
    docstring); None for any other record (the caller deserializes it the general way)."""
    if len(data) < 17 or data[:4] != CDR_LE:
        return None
    sec, nsec, n = _HEAD.unpack_from(data, 4)
    off = cdr_align(16 + n, 8)   # after the string
    if n < 1 or off + POSE_BYTES != len(data) or data[15 + n] != 0:
        return None
    return sec * 1_000_000_000 + nsec, _POSE.unpack_from(data, off)


def pose_from_cdr(data: bytes) -> tuple[int, np.ndarray, np.ndarray]:
    """(stamp [ns], p, q xyzw) of a serialized PoseStamped: the fixed layout read directly, anything else through
    rclpy's deserializer (whose error, for a record it cannot read, propagates as before)."""
    got = pose_stamped_fields(data)
    if got is None:
        from geometry_msgs.msg import PoseStamped
        from rclpy.serialization import deserialize_message

        from fullperc_common.ros_conv import pose_to_pq, stamp_to_ns

        msg = deserialize_message(data, PoseStamped)
        p, q = pose_to_pq(msg.pose)
        return stamp_to_ns(msg.header.stamp), p, q
    t_ns, v = got
    return t_ns, np.array(v[:3]), np.array(v[3:])


def quality_fields(data: bytes) -> tuple[int, bool, float, int, int] | None:
    """(stamp [ns], visible, fit_error, frame_number, markers_used) of a TrackingQuality in the fixed little-endian
    layout (module docstring); None for any other record."""
    if len(data) < 17 or data[:4] != CDR_LE:
        return None
    sec, nsec, n = _HEAD.unpack_from(data, 4)
    off_blen = cdr_align(16 + n, 4)
    if n < 1 or off_blen + 4 > len(data) or data[15 + n] != 0:
        return None
    (b,) = _U32.unpack_from(data, off_blen)
    _, off_vis, off_fit, _, _, _, off_port = quality_layout(n, b)
    if b < 1 or off_port + 4 != len(data) or data[off_vis - 1] != 0 or data[off_vis] > 1:
        return None
    fit, number, markers = _QUALITY.unpack_from(data, off_fit)
    return sec * 1_000_000_000 + nsec, data[off_vis] == 1, fit, number, markers


def quality_from_cdr(data: bytes) -> tuple[int, bool, float, int, int]:
    """:func:`quality_fields` of a serialized TrackingQuality, a record off the layout through rclpy's deserializer
    (whose error, for a record it cannot read, propagates as before)."""
    got = quality_fields(data)
    if got is not None:
        return got
    from rclpy.serialization import deserialize_message

    from fullperc_common.ros_conv import stamp_to_ns
    from fullperc_msgs.msg import TrackingQuality

    m = deserialize_message(data, TrackingQuality)
    return stamp_to_ns(m.header.stamp), bool(m.visible), float(m.fit_error), int(m.frame_number), int(m.markers_used)
