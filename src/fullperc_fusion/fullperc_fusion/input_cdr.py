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

TrackedBodies (``inputs: frames``): the same header, ``latency`` (float32, aligned to 4), the number of bodies
(uint32), then per body: ``name`` (uint32 length aligned to 4, the bytes with their NUL), ``visible`` (one byte),
``pose`` (7 float64, aligned to 8), ``fit_error`` (float32), ``frame_number`` (uint32), ``markers_used`` (uint16),
``port_status`` (uint32, aligned to 4); the record ends after the last body.

A record off its layout (big-endian CDR, encapsulation options, a length that does not add up, a string without its
NUL, a bool byte other than 0 or 1) is not guessed at: :func:`pose_from_cdr`, :func:`quality_from_cdr` and
:func:`bodies_from_cdr` give it to rclpy's deserializer, which accepts or rejects it as before. The values are the
deserializer's bit for bit (``test_input_cdr.py``, ``test_input_cdr_bodies.py`` compare them over random messages).
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
_BODY_TAIL = struct.Struct("<7dfIH")   # pose, fit_error, frame_number, markers_used (at the aligned pose)
BodySample = tuple[str, bool, tuple[float, ...], float, int, int]   # name, visible, pose (p xyz, q xyzw), fit_error,
#                                                                     frame_number, markers_used


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


def bodies_fields(data: bytes) -> tuple[int, list[BodySample]] | None:
    """(stamp [ns], one :data:`BodySample` per body) of a TrackedBodies in the fixed little-endian layout (module
    docstring); None for any other record."""
    if len(data) < 25 or data[:4] != CDR_LE:
        return None
    sec, nsec, n = _HEAD.unpack_from(data, 4)
    off = cdr_align(16 + n, 4) + 4   # after the string and latency: the number of bodies
    if n < 1 or off + 4 > len(data) or data[15 + n] != 0:
        return None
    (count,) = _U32.unpack_from(data, off)
    off += 4
    bodies: list[BodySample] = []
    for _ in range(count):
        off = cdr_align(off, 4)
        if off + 4 > len(data):
            return None
        (b,) = _U32.unpack_from(data, off)
        vis = off + 4 + b
        pose = cdr_align(vis + 1, 8)
        end = pose + _BODY_TAIL.size
        if b < 1 or end > len(data) or data[vis - 1] != 0 or data[vis] > 1:
            return None
        name = data[off + 4:vis - 1].decode("utf-8", "replace")
        *p, fit, number, markers = _BODY_TAIL.unpack_from(data, pose)
        bodies.append((name, data[vis] == 1, tuple(p), fit, number, markers))
        off = cdr_align(end, 4) + 4   # port_status
    if off != len(data):
        return None
    return sec * 1_000_000_000 + nsec, bodies


def bodies_from_cdr(data: bytes) -> tuple[int, list[BodySample]]:
    """:func:`bodies_fields` of a serialized TrackedBodies, a record off the layout through rclpy's deserializer
    (whose error, for a record it cannot read, propagates as before)."""
    got = bodies_fields(data)
    if got is not None:
        return got
    from rclpy.serialization import deserialize_message

    from fullperc_common.ros_conv import stamp_to_ns
    from fullperc_msgs.msg import TrackedBodies

    m = deserialize_message(data, TrackedBodies)
    return stamp_to_ns(m.header.stamp), [
        (b.name, bool(b.visible), (b.pose.position.x, b.pose.position.y, b.pose.position.z, b.pose.orientation.x,
                                   b.pose.orientation.y, b.pose.orientation.z, b.pose.orientation.w),
         float(b.fit_error), int(b.frame_number), int(b.markers_used)) for b in m.bodies]
