"""Property/fuzz test: random and mutated replies thrown at every parser.

Only the protocol core's own error type (``NdiError``) may escape; anything else (IndexError,
struct.error, UnicodeDecodeError, ValueError from int(), ...) is a bug.
"""

from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fullperc_drivers.ndi import replies as R
from fullperc_drivers.ndi.protocol import (
    FrameReader,
    NdiError,
    check_status,
    decode_command,
    encode_ascii_reply,
    encode_binary_reply,
    parse_frame,
    parse_okay,
)
from fullperc_drivers.ndi.rom import TOOLS, read_rom, write_rom

_q = np.array([0.5, 0.5, -0.5, 0.5])
_TOOLS = [R.ToolTransform(1, "valid", _q, np.array([1.5, -2.25, -1500.0]), 0.1, 0x31, 77,
                          np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [7.0, 8.0, 9.0]]), (False, True, False)),
          R.ToolTransform(2, "missing", port_status=0x31, frame_number=77, markers_mm=np.zeros((0, 3))),
          R.ToolTransform(3, "disabled")]
_DATA = R.TrackingData(_TOOLS, 0x0100)
OPTIONS = [R.OPT_TRANSFORMS, R.OPT_TRANSFORMS | R.OPT_MARKERS, 0x0801, R.OPT_MARKERS]
SEEDS = ([encode_binary_reply(R.format_bx(_DATA, o)) for o in OPTIONS]
         + [encode_ascii_reply(R.format_tx(_DATA, o)) for o in OPTIONS]
         + [b"OKAYA896\r", b"WARNING06018D\r", b"ERROR0D8C03\r", encode_ascii_reply("040A01F0B01F0C01F0D01F"),
            encode_ascii_reply("Freeze Tag: Polaris Vega 008\nX: y"), encode_ascii_reply("G.003.004"),
            encode_ascii_reply("A=1\nB=2")])


def parse_everything(raw: bytes) -> None:
    """Run every parser the driver uses on ``raw``; only NdiError may come out."""
    fr = FrameReader()
    fr.feed(raw)
    for _ in range(8):
        try:
            rep = fr.pop()
        except NdiError:
            continue
        if rep is None:
            break
        for fn in (lambda r: check_status(r), lambda r: parse_okay(r)):
            try:
                fn(rep)
            except NdiError:
                pass
        for o in OPTIONS:
            for fn in (R.parse_bx, lambda d, o=o: R.parse_tx(d.decode("latin-1"), o)):
                try:
                    fn(rep.data, o) if fn is R.parse_bx else fn(rep.data)
                except NdiError:
                    pass
        text = rep.data.decode("latin-1")
        for fn in (R.parse_phsr, R.parse_phrq, R.parse_ver, R.parse_apirev, R.parse_get):
            try:
                fn(text)
            except NdiError:
                pass
    for fn in (parse_frame, decode_command, read_rom):
        try:
            fn(raw)
        except NdiError:
            pass


@st.composite
def mutated(draw):
    raw = bytearray(draw(st.sampled_from(SEEDS)))
    for _ in range(draw(st.integers(1, 6))):
        op = draw(st.sampled_from(["flip", "set", "insert", "delete", "truncate"]))
        if not raw:
            break
        i = draw(st.integers(0, len(raw) - 1))
        if op == "flip":
            raw[i] ^= 1 << draw(st.integers(0, 7))
        elif op == "set":
            raw[i] = draw(st.integers(0, 255))
        elif op == "insert":
            raw[i:i] = draw(st.binary(min_size=1, max_size=8))
        elif op == "delete":
            del raw[i]
        else:
            del raw[i:]
    return bytes(raw)


def recrc(raw: bytes) -> bytes:
    """Re-frame a mutated reply with a valid CRC so the mutation reaches the payload parsers."""
    if raw[:2] == b"\xc4\xa5":
        return encode_binary_reply(raw[6:-2] if len(raw) >= 8 else raw)
    return encode_ascii_reply(raw.rstrip(b"\r")[:-4] if len(raw) > 5 else raw)


FUZZ = settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@FUZZ
@given(st.binary(max_size=600))
def test_random_bytes(raw):
    parse_everything(raw)


@FUZZ
@given(mutated())
def test_mutated_replies(raw):
    parse_everything(raw)


@FUZZ
@given(mutated())
def test_mutated_payloads_with_valid_crc(raw):
    parse_everything(recrc(raw))


@FUZZ
@given(st.binary(max_size=300).map(lambda b: encode_binary_reply(b)))
def test_random_binary_bodies_with_valid_crc(raw):
    parse_everything(raw)


@FUZZ
@given(st.text(alphabet="0123456789ABCDEF+-MISNGDABLEUOC\n", max_size=300).map(encode_ascii_reply))
def test_random_ascii_bodies_with_valid_crc(raw):
    parse_everything(raw)


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 751), st.integers(0, 255))
def test_mutated_rom(pos, val):
    rom = bytearray(write_rom(TOOLS["tool"][1], TOOLS["tool"][0]))
    rom[pos] = val
    try:
        read_rom(bytes(rom), verify=True)
    except NdiError:
        pass
