"""Round trips and rejection of the simulator stream formats."""

import numpy as np
import pytest

from fullperc_drivers.streams import (
    DianaState,
    OmcBody,
    OmcFrame,
    StreamDecodeError,
    decode_diana,
    decode_omc,
    encode_diana,
    encode_omc,
)


def _frame():
    return OmcFrame(7, 123_456_789, 0.004, [
        OmcBody(1, "base", np.array([1.0, 2.0, 3.0]), np.array([0, 0, 0, 1.0]), 0.12, True, 4),
        OmcBody(2, "tool", np.array([4.0, 5.0, 6.5]), np.array([0, 0.6, 0, 0.8]), 0.3, False, 0),
    ])


def test_omc_round_trip():
    f = decode_omc(encode_omc(_frame()))
    assert (f.frame_number, f.timestamp_ns) == (7, 123_456_789)
    assert f.latency_s == pytest.approx(0.004)
    assert [b.name for b in f.bodies] == ["base", "tool"]
    assert np.allclose(f.bodies[1].position_mm, [4, 5, 6.5])
    assert np.allclose(f.bodies[1].quat_xyzw, [0, 0.6, 0, 0.8])
    assert f.bodies[0].tracked and not f.bodies[1].tracked and f.bodies[0].markers == 4


def test_diana_round_trip():
    s = decode_diana(encode_diana(DianaState(3, 99, np.arange(7.0), -np.arange(7.0))))
    assert s.sequence == 3 and s.timestamp_ns == 99
    assert np.array_equal(s.q, np.arange(7.0)) and np.array_equal(s.dq, -np.arange(7.0))


@pytest.mark.parametrize("cut", [0, 3, 10, 25, 40])
def test_truncated_omc_rejected(cut):
    with pytest.raises(StreamDecodeError):
        decode_omc(encode_omc(_frame())[:cut])


def test_garbled_rejected():
    data = bytearray(encode_omc(_frame()))
    data[0] = 0
    with pytest.raises(StreamDecodeError):
        decode_omc(bytes(data))
    with pytest.raises(StreamDecodeError):
        decode_diana(b"FPDA" + b"\x01\x00" + b"\xff\xff" + bytes(12))
    with pytest.raises(StreamDecodeError):
        decode_diana(encode_omc(_frame()))
