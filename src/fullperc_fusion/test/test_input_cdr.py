"""input_cdr: a serialized PoseStamped or TrackingQuality read directly equals rclpy's deserializer bit for bit; any
record off the fixed layout goes to the deserializer instead (accepted or refused as before); no input makes the direct
readers raise."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped
from hypothesis import given, settings
from hypothesis import strategies as st
from rclpy.serialization import deserialize_message, serialize_message

from fullperc_fusion.input_cdr import CDR_LE, pose_from_cdr, pose_stamped_fields, quality_fields, quality_from_cdr
from fullperc_msgs.msg import TrackingQuality


def _msg(frame: str, sec: int, nsec: int, v) -> PoseStamped:
    m = PoseStamped()
    m.header.frame_id = frame
    m.header.stamp.sec, m.header.stamp.nanosec = sec, nsec
    p, q = m.pose.position, m.pose.orientation
    p.x, p.y, p.z, q.x, q.y, q.z, q.w = (float(x) for x in v)
    return m


def _same_bits(a: float, b: float) -> bool:
    return struct.pack("<d", a) == struct.pack("<d", b)


@pytest.mark.parametrize("frame", ["", "o", "omc", "ots_", "base_link", "a_frame_name_of_23_chars", "ü-frame"])
def test_every_frame_length_and_alignment_equals_the_deserializer(frame):
    """The pose starts at the next 8-byte boundary after the frame name: every length mod 8 is covered."""
    rng = np.random.default_rng(len(frame))
    v = rng.normal(size=7)
    data = serialize_message(_msg(frame, 1_700_000_000, 123_456_789, v))
    t_ns, vals = pose_stamped_fields(data)
    ref = deserialize_message(data, PoseStamped)
    assert t_ns == 1_700_000_000 * 1_000_000_000 + 123_456_789
    rp, rq = ref.pose.position, ref.pose.orientation
    assert all(_same_bits(a, b) for a, b in zip(vals, (rp.x, rp.y, rp.z, rq.x, rq.y, rq.z, rq.w), strict=True))


@given(sec=st.integers(-2**31, 2**31 - 1), nsec=st.integers(0, 2**32 - 1), frame=st.text(max_size=40),
       v=st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=7, max_size=7))
@settings(max_examples=300, deadline=None)
def test_random_messages_equal_the_deserializer(sec, nsec, frame, v):
    """Any stamp (negative seconds too), any frame name, any float -- NaN and inf are passed on as they are: the
    node's own checks refuse them, as they did the deserializer's values."""
    frame = frame.replace("\x00", "")
    data = serialize_message(_msg(frame, sec, nsec, v))
    t_ns, p, q = pose_from_cdr(data)
    assert t_ns == sec * 1_000_000_000 + nsec
    got = [*p.tolist(), *q.tolist()]
    assert all(_same_bits(a, b) or (math.isnan(a) and math.isnan(b)) for a, b in zip(got, v, strict=True))


def test_records_off_the_layout_go_to_the_deserializer():
    data = serialize_message(_msg("omc", 5, 6, [1, 2, 3, 0, 0, 0, 1]))
    assert pose_stamped_fields(data) is not None and data[:4] == CDR_LE
    with_options = data[:2] + b"\x00\x01" + data[4:]          # encapsulation options set
    trailing = data + b"\x00" * 8                               # a length that does not add up
    no_nul = data[:15 + 4] + b"x" + data[20:]                  # frame_id without its NUL
    big_endian = b"\x00\x00\x00\x00" + data[4:]                 # CDR big endian
    for bad in (with_options, trailing, no_nul, big_endian, data[:16], b""):
        assert pose_stamped_fields(bad) is None, bad
    # what the deserializer makes of them is what the node gets: the options are ignored by it, the rest refused
    t_ns, p, _ = pose_from_cdr(with_options)
    assert t_ns == 5_000_000_006 and p.tolist() == [1.0, 2.0, 3.0]
    with pytest.raises(Exception):   # noqa: B017 - rclpy's deserializer raises its own error type for bad CDR
        pose_from_cdr(data[:30])


def _quality(frame: str, body: str, sec: int, nsec: int, visible: bool, fit: float, number: int, markers: int,
             latency: float = 0.004, port: int = 0x31) -> TrackingQuality:
    m = TrackingQuality()
    m.header.frame_id, m.body = frame, body
    m.header.stamp.sec, m.header.stamp.nanosec = sec, nsec
    m.visible, m.fit_error, m.frame_number, m.markers_used, m.latency, m.port_status = (
        visible, fit, number, markers, latency, port)
    return m


def _fields_of(m: TrackingQuality) -> tuple:
    return (m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec, bool(m.visible), float(m.fit_error),
            int(m.frame_number), int(m.markers_used))


@pytest.mark.parametrize("frame", ["o", "omc", "ots_", "a_frame"])
@pytest.mark.parametrize("body", ["b", "tool", "base_", "instrument"])
def test_quality_every_string_length_equals_the_deserializer(frame, body):
    """The strings' lengths move every later field through its 4-byte alignment: each combination mod 4."""
    data = serialize_message(_quality(frame, body, 1_700_000_000, 5, True, 2.5e-4, 123_456, 7))
    ref = deserialize_message(data, TrackingQuality)
    assert quality_fields(data) == _fields_of(ref)
    assert quality_fields(data)[1:] == (True, float(ref.fit_error), 123_456, 7)


@given(sec=st.integers(-2**31, 2**31 - 1), nsec=st.integers(0, 2**32 - 1), frame=st.text(max_size=20),
       body=st.text(max_size=20), visible=st.booleans(), fit=st.floats(width=32, allow_nan=False),
       number=st.integers(0, 2**32 - 1), markers=st.integers(0, 2**16 - 1), latency=st.floats(width=32),
       port=st.integers(0, 2**32 - 1))
@settings(max_examples=300, deadline=None)
def test_random_quality_messages_equal_the_deserializer(sec, nsec, frame, body, visible, fit, number, markers,
                                                        latency, port):
    m = _quality(frame.replace("\x00", ""), body.replace("\x00", ""), sec, nsec, visible, fit, number, markers,
                 latency, port)
    data = serialize_message(m)
    assert quality_from_cdr(data) == _fields_of(deserialize_message(data, TrackingQuality))


def test_quality_records_off_the_layout_go_to_the_deserializer():
    data = serialize_message(_quality("omc", "tool", 5, 6, False, -1.0, 9, 0))
    assert quality_fields(data) == (5_000_000_006, False, -1.0, 9, 0)
    off_vis = 16 + 4 + 4 + 5   # after "omc\0" (16..20), body length (20..24) and "tool\0"
    assert data[off_vis] == 0 and len(data) == 52
    bool_two = data[:off_vis] + b"\x02" + data[off_vis + 1:]
    for bad in (data[:2] + b"\x00\x01" + data[4:], data + b"\x00" * 4, bool_two, data[:20], b""):
        assert quality_fields(bad) is None, bad
    with pytest.raises(Exception):   # noqa: B017 - rclpy's deserializer raises its own error type for bad CDR
        quality_from_cdr(data[:30])


@given(st.binary(max_size=120))
@settings(max_examples=500, deadline=None)
def test_no_bytes_make_the_direct_readers_raise(data):
    got = pose_stamped_fields(data)
    assert got is None or (isinstance(got[0], int) and len(got[1]) == 7)
    q = quality_fields(data)
    assert q is None or (len(q) == 5 and isinstance(q[1], bool))
