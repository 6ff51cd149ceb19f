"""input_cdr for TrackedBodies (fusion_node ``inputs: frames``): a serialized frame read directly equals rclpy's
deserializer bit for bit, for any number of bodies and any name lengths (every alignment); a record off the layout
goes to the deserializer; no bytes make the direct reader raise."""

from __future__ import annotations

import math
import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from rclpy.serialization import deserialize_message, serialize_message

from fullperc_fusion.input_cdr import bodies_fields, bodies_from_cdr
from fullperc_msgs.msg import TrackedBodies, TrackedBody


def _frame(frame: str, sec: int, nsec: int, bodies: list[tuple], latency: float = 0.004) -> TrackedBodies:
    m = TrackedBodies()
    m.header.frame_id = frame
    m.header.stamp.sec, m.header.stamp.nanosec = sec, nsec
    m.latency = latency
    for name, visible, v, fit, number, markers, port in bodies:
        b = TrackedBody(name=name, visible=visible, fit_error=fit, frame_number=number, markers_used=markers,
                        port_status=port)
        p, q = b.pose.position, b.pose.orientation
        p.x, p.y, p.z, q.x, q.y, q.z, q.w = (float(x) for x in v)
        m.bodies.append(b)
    return m


def _reference(data: bytes) -> tuple:
    m = deserialize_message(data, TrackedBodies)
    return m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec, [
        (b.name, bool(b.visible), (b.pose.position.x, b.pose.position.y, b.pose.position.z, b.pose.orientation.x,
                                   b.pose.orientation.y, b.pose.orientation.z, b.pose.orientation.w),
         float(b.fit_error), int(b.frame_number), int(b.markers_used)) for b in m.bodies]


def _same(a, b) -> bool:
    """Equal, floats compared by their bits (a NaN is passed on as it is)."""
    if isinstance(a, float):
        return struct.pack("<d", a) == struct.pack("<d", b) or (math.isnan(a) and math.isnan(b))
    if isinstance(a, (tuple, list)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    return a == b and type(a) is type(b)


@pytest.mark.parametrize("frame", ["o", "omc", "ots_", "a_frame"])
@pytest.mark.parametrize("names", [[], ["tool"], ["b", "base_", "instrument"], ["tool", "ots_rig", "x"]])
def test_every_name_length_equals_the_deserializer(frame, names):
    """Each body's name moves its pose through the 8-byte alignment and its port_status through the 4-byte one: every
    length mod 8 over the names, and zero bodies."""
    bodies = [(n, k % 2 == 0, [0.1 * k + j for j in range(7)], 2.5e-4 * k, 1000 + k, k, 0x31 * k)
              for k, n in enumerate(names)]
    data = serialize_message(_frame(frame, 1_700_000_000, 5, bodies))
    got = bodies_fields(data)
    assert got is not None and _same(got, _reference(data))
    assert [b[0] for b in got[1]] == names and got[0] == 1_700_000_000_000_000_005


_BODY = st.tuples(st.text(max_size=12).map(lambda s: s.replace("\x00", "")), st.booleans(),
                  st.lists(st.floats(), min_size=7, max_size=7), st.floats(width=32), st.integers(0, 2**32 - 1),
                  st.integers(0, 2**16 - 1), st.integers(0, 2**32 - 1))


@given(sec=st.integers(-2**31, 2**31 - 1), nsec=st.integers(0, 2**32 - 1),
       frame=st.text(max_size=20).map(lambda s: s.replace("\x00", "")), bodies=st.lists(_BODY, max_size=5),
       latency=st.floats(width=32))
@settings(max_examples=300, deadline=None)
def test_random_frames_equal_the_deserializer(sec, nsec, frame, bodies, latency):
    data = serialize_message(_frame(frame, sec, nsec, bodies, latency))
    assert _same(bodies_from_cdr(data), _reference(data))


def test_records_off_the_layout_go_to_the_deserializer():
    data = serialize_message(_frame("omc", 5, 6, [("tool", True, [1, 2, 3, 0, 0, 0, 1], 1e-4, 9, 4, 0)]))
    assert bodies_fields(data) is not None
    vis = 16 + 4 + 4 + 4 + 4 + 5   # stamp and frame_id length, "omc\0", latency, count, name length, "tool\0"
    assert data[vis] == 1
    bool_two = data[:vis] + b"\x02" + data[vis + 1:]
    no_nul = data[:vis - 1] + b"x" + data[vis:]
    more_bodies = data[:24] + struct.pack("<I", 2) + data[28:]   # the count says two, one follows
    for bad in (data[:2] + b"\x00\x01" + data[4:], data + b"\x00" * 4, bool_two, no_nul, more_bodies, data[:30],
                b"\x00\x00\x00\x00" + data[4:], b""):
        assert bodies_fields(bad) is None, bad
    t_ns, bodies = bodies_from_cdr(data[:2] + b"\x00\x01" + data[4:])   # options: the deserializer ignores them
    assert t_ns == 5_000_000_006 and bodies[0][:2] == ("tool", True) and bodies[0][2][:3] == (1.0, 2.0, 3.0)
    with pytest.raises(Exception):   # noqa: B017 - rclpy's deserializer raises its own error type for bad CDR
        bodies_from_cdr(more_bodies)


@given(st.binary(max_size=200))
@settings(max_examples=500, deadline=None)
def test_no_bytes_make_the_direct_reader_raise(data):
    got = bodies_fields(data)
    assert got is None or (isinstance(got[0], int) and all(len(b) == 6 for b in got[1]))
