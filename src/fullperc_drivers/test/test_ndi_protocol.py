"""Protocol core against the test vectors of reference/ndi.md (CRCs, real captures, BX bytes).

Every expected value here is copied from the reference notes (real device traces, the CNQT TX
capture, the hand-verified BX example), never computed by our own code.
"""

from __future__ import annotations

import numpy as np
import pytest

from fullperc_drivers.ndi import replies as R
from fullperc_drivers.ndi.crc import crc16, crc16_hex
from fullperc_drivers.ndi.protocol import (
    FrameReader,
    NdiCrcError,
    NdiDeviceError,
    NdiProtocolError,
    Reply,
    check_status,
    decode_command,
    encode_ascii_reply,
    encode_binary_reply,
    encode_command,
    parse_frame,
    parse_okay,
)

# ndi.md §1.3: command strings and their CRCs (MV trace + recomputation).
COMMAND_CRCS = [
    ("INIT:", "E3A5"), ("VER:0", "65EE"), ("PHSR:00", "20FF"), ("PINIT:02", "30AA"), ("PENA:02D", "9D3B"),
    ("BX:1803", "3D6C"), ("GET:Device.*", "722D"), ("SET:Param.Tracking.Illuminator Rate=2", "237A"),
    ("GETINFO:Features.Firmware.Version", "0492"), ("SFLIST:03", "500F"), ("PHRQ:*********1****", "A4C1"),
    ("TSTART:", "5423"), ("TSTOP:", "2C14"),
]

# ndi.md §1.4: complete ASCII replies as sent by devices.
ASCII_REPLIES = [
    (b"OKAYA896\r", b"OKAY"), (b"RESETBE6F\r", b"RESET"), (b"1D4C1\r", b"1"), (b"001414\r", b"00"),
    (b"010A001C1B5\r", b"010A001"), (b"040A01F0B01F0C01F0D01F2DDB\r", b"040A01F0B01F0C01F0D01F"),
    (b"Testing!A81C\r", b"Testing!"), (b"Info.Timeout.PINIT=5\n96A7\r", b"Info.Timeout.PINIT=5\n"),
    (b"022BA94\r", b"022"), (b"WARNING7423\r", b"WARNING"), (b"ERROR016BC2\r", b"ERROR01"),
    (b"ERROR046802\r", b"ERROR04"), (b"ERROR0D8C03\r", b"ERROR0D"), (b"WARNING06018D\r", b"WARNING06"),
]

# ndi.md §3: real TX 0009 reply (CNQT), CRC stripped.
TX_CAPTURE = ("0201+07082-04513-01855-05101+041595-057080-190190+02477000000310000014D040+032681-029273-196806"
              "+038254-031402-195542+036870-036707-194443+037965-041486-193249\n02+02762-01462-00466+09487"
              "+033067-022295-195013+01564000000310000014D040+033067-022310-195004+027787-023550-195330"
              "+030728-017309-196164+023842-018192-196965\n0000")

# ndi.md §4: BX examples (one valid handle; same handle missing).
BX_VALID = bytes.fromhex("c4a52d003043" "01" "0101" "0000803f000000000000000000000000000028410000a2c10080bbc48fc2f53d"
                         "31000000" "d2040000" "0000" "0cb6")
BX_MISSING = bytes.fromhex("c4a50d002983010202310000 00d3040000000043a7".replace(" ", ""))

# ndi.md §2: a real PVWR line from the NDI Track trace (MV), CRC 610B.
PVWR_LINE = ("PVWR:0200004E444900AF12000001000000000000010000000002DC32355A00000004000000040000000000403F"
             "000000000000000000000000000000000000000000000000610B")


def test_crc16_arc_check_value():
    assert crc16(b"123456789") == 0xBB3D


@pytest.mark.parametrize(("text", "crc"), COMMAND_CRCS)
def test_command_crc_vectors(text, crc):
    assert crc16_hex(text) == crc
    name, params = text.split(":", 1)
    assert encode_command(name, params) == f"{text}{crc}\r".encode()


def test_crc_of_data_followed_by_its_crc_is_zero():
    for data in (b"OKAY", bytes(range(40)), b"\xc4\xa5\x2d\x00"):
        c = crc16(data)
        assert crc16(data + bytes([c & 0xFF, c >> 8])) == 0


def test_space_form_has_no_crc():
    assert encode_command("PHSR", "01", crc=False) == b"PHSR 01\r"
    assert encode_command("TSTART", "", crc=False) == b"TSTART \r"


def test_decode_both_command_forms_and_real_pvwr():
    c = decode_command(PVWR_LINE.encode() + b"\r")
    assert (c.name, c.crc_form) == ("PVWR", True)
    assert c.params == PVWR_LINE[5:-4]
    assert decode_command(b"PINIT:0a" + crc16_hex("PINIT:0a").encode() + b"\r").params == "0a"
    assert decode_command(b"PHSR 02\r") == type(c)("PHSR", "02", False)
    assert decode_command(b"INIT\r") == type(c)("INIT", "", False)
    bad = PVWR_LINE[:-1] + ("C" if PVWR_LINE[-1] != "C" else "D")
    with pytest.raises(NdiCrcError):
        decode_command(bad.encode() + b"\r")


@pytest.mark.parametrize(("raw", "data"), ASCII_REPLIES)
def test_ascii_reply_vectors(raw, data):
    rep = parse_frame(raw)
    assert rep == Reply(data, False)
    assert encode_ascii_reply(data) == raw


def test_corrupted_ascii_reply_is_a_crc_error():
    with pytest.raises(NdiCrcError):
        parse_frame(b"OKAYA897\r")
    with pytest.raises(NdiCrcError):
        parse_frame(b"OKAXA896\r")


def test_okay_warning_error():
    assert parse_okay(parse_frame(b"OKAYA896\r")) is None
    assert parse_okay(parse_frame(b"WARNING06018D\r")) == 0x06
    assert parse_okay(parse_frame(b"WARNING7423\r")) == 0
    with pytest.raises(NdiDeviceError) as ei:
        parse_okay(parse_frame(b"ERROR0D8C03\r"), "PINIT")
    assert ei.value.code == 0x0D
    assert "ERROR0D" in str(ei.value) and "no tool assigned" in str(ei.value) and "PINIT" in str(ei.value)
    with pytest.raises(NdiDeviceError) as ei:
        check_status(parse_frame(b"ERROR046802\r"))
    assert ei.value.code == 4 and "CRC" in ei.value.description


def test_tx_real_capture():
    d = R.parse_tx(TX_CAPTURE, R.OPT_TRANSFORMS | R.OPT_MARKERS)
    assert d.system_status == 0
    assert [t.handle for t in d.tools] == [1, 2]
    t1 = d.tools[0]
    np.testing.assert_allclose(t1.q_wxyz, [0.7082, -0.4513, -0.1855, -0.5101])
    np.testing.assert_allclose(t1.t_mm, [415.95, -570.80, -1901.90])
    assert t1.error_mm == pytest.approx(0.2477)
    assert t1.port_status == 0x31 and t1.frame_number == 0x14D
    assert t1.markers_mm.shape == (4, 3)
    np.testing.assert_allclose(t1.markers_mm[0], [326.81, -292.73, -1968.06])
    np.testing.assert_allclose(t1.markers_mm[3], [379.65, -414.86, -1932.49])
    assert t1.markers_oov == (False,) * 4
    t2 = d.tools[1]
    np.testing.assert_allclose(t2.q_wxyz, [0.2762, -0.1462, -0.0466, 0.9487])
    np.testing.assert_allclose(t2.t_mm, [330.67, -222.95, -1950.13])
    assert t2.frame_number == t1.frame_number == d.frame_number
    # the emulator's formatter writes the capture back byte for byte
    assert R.format_tx(d, R.OPT_TRANSFORMS | R.OPT_MARKERS) == TX_CAPTURE


def test_quaternion_order_is_converted_scalar_first_to_ros():
    """NDI sends (q0, qx, qy, qz); ROS wants (x, y, z, w). Pinned on the real TX capture."""
    t1 = R.parse_tx(TX_CAPTURE, R.OPT_TRANSFORMS | R.OPT_MARKERS).tools[0]
    np.testing.assert_allclose(t1.q_xyzw, [-0.4513, -0.1855, -0.5101, 0.7082])
    b = R.parse_bx(parse_frame(BX_VALID).data).tools[0]
    np.testing.assert_allclose(b.q_xyzw, [0.0, 0.0, 0.0, 1.0])


def test_bx_examples_parse_exactly():
    rep = parse_frame(BX_VALID)
    assert rep.binary and len(rep.data) == 0x2D
    d = R.parse_bx(rep.data, R.OPT_TRANSFORMS)
    (t,) = d.tools
    assert (t.handle, t.status, t.port_status, t.frame_number) == (1, "valid", 0x31, 1234)
    np.testing.assert_allclose(t.q_wxyz, [1, 0, 0, 0])
    np.testing.assert_allclose(t.t_mm, [10.5, -20.25, -1500.0])
    assert t.error_mm == pytest.approx(0.12, abs=1e-7)
    assert encode_binary_reply(R.format_bx(d)) == BX_VALID

    m = R.parse_bx(parse_frame(BX_MISSING).data, R.OPT_TRANSFORMS | R.OPT_NOT_NORMALLY_REPORTED)
    (t,) = m.tools
    # the bytes carry handle 0x02 (ndi.md's caption says "same handle"; the bytes are what counts)
    assert (t.handle, t.status, t.port_status, t.frame_number, t.q_wxyz) == (2, "missing", 0x31, 1235, None)
    assert encode_binary_reply(R.format_bx(m)) == BX_MISSING


def test_bx_body_length_formula():
    """ndi.md §4: n = 1 + 42 k + 10 m + 2 for k valid and m missing handles."""
    tools = [R.ToolTransform(h, "valid", np.array([1.0, 0, 0, 0]), np.zeros(3), 0.1, 0x31, 7) for h in (1, 2, 3)]
    tools += [R.ToolTransform(h, "missing", port_status=0x31, frame_number=7) for h in (4, 5)]
    body = R.format_bx(R.TrackingData(tools, 0))
    assert len(body) == 1 + 42 * 3 + 10 * 2 + 2


def test_binary_header_and_body_crc_errors():
    bad_body = bytearray(BX_VALID)
    bad_body[20] ^= 1
    with pytest.raises(NdiCrcError):
        parse_frame(bytes(bad_body))
    bad_head = bytearray(BX_VALID)
    bad_head[4] ^= 1
    with pytest.raises(NdiCrcError):
        parse_frame(bytes(bad_head))


def _bytewise(fr: FrameReader, data: bytes) -> list:
    """The frames ``fr`` pops when ``data`` is fed one byte at a time."""
    out = []
    for b in data:
        fr.feed(bytes([b]))
        r = fr.pop()
        if r is not None:
            out.append(r)
    return out


def test_frame_reader_splits_a_stream_fed_byte_by_byte():
    stream = BX_VALID + b"OKAYA896\r" + BX_MISSING + b"Info.Timeout.PINIT=5\n96A7\r"
    out = _bytewise(FrameReader(), stream)
    assert [r.binary for r in out] == [True, False, True, False]
    assert out[1].data == b"OKAY" and out[3].data == b"Info.Timeout.PINIT=5\n"


def test_error_to_a_binary_command_is_ascii():
    fr = FrameReader()
    fr.feed(b"ERROR0C" + crc16_hex("ERROR0C").encode() + b"\r")
    with pytest.raises(NdiDeviceError) as ei:
        check_status(fr.pop(), "BX")
    assert ei.value.code == 0x0C


def test_phsr_phrq_ver_apirev_get():
    assert R.parse_phsr("00") == []
    assert R.parse_phsr("040A01F0B01F0C01F0D01F") == [(0x0A, 0x1F), (0x0B, 0x1F), (0x0C, 0x1F), (0x0D, 0x1F)]
    assert R.parse_phsr("010A001") == [(0x0A, 0x001)]
    assert R.format_phsr([(0x0A, 0x001)]) == "010A001"
    assert R.parse_phrq("01") == 1 and R.parse_phrq("0a") == 10
    v = R.parse_ver("Polaris Vega Control\nFreeze Tag: Polaris Vega 008\nFreeze Date: 2019")
    assert v.freeze_tag == "Polaris Vega 008"
    assert R.parse_apirev("G.001.005") == R.ApiRevision("G", 1, 5, "G.001.005")
    assert R.parse_apirev("G.003").major == 3
    assert R.parse_get("Info.Timeout.PINIT=5\n") == {"Info.Timeout.PINIT": "5"}
    assert R.parse_get("A.b=1\nA.c=x y") == {"A.b": "1", "A.c": "x y"}
    for bad, fn in (("0", R.parse_phsr), ("0101", R.parse_phsr), ("1", R.parse_phrq), ("G.1.5", R.parse_apirev),
                    ("novalue", R.parse_get)):
        with pytest.raises(NdiProtocolError):
            fn(bad)


def test_pvwr_chunks_match_the_real_trace_format():
    rom = bytes.fromhex(PVWR_LINE[11:-4])  # the 64 data bytes of the traced chunk at address 0
    (p,) = R.pvwr_params(2, rom)
    assert encode_command("PVWR", p) == PVWR_LINE.encode() + b"\r"
    assert len(R.pvwr_params(1, bytes(752))) == 12
    assert len(R.pvwr_params(1, bytes(752), pad_to=1024)) == 16
    with pytest.raises(NdiProtocolError):
        R.pvwr_params(1, bytes(1100))


@pytest.mark.parametrize("garbage", [b"\x00", b"\xff\x13\x9a", b"\xc4\x01\x02\x03\x04\x05\x06",
                                     b"\x01\xc4\xa5\x00\x00\x00\x00z", bytes(range(0x80, 0x90))])
def test_garbage_before_a_binary_reply_is_skipped_and_counted(garbage):
    """A binary reply behind line noise is read (it used to wait for a CR that never came: a read timeout),
    the noise counted; a fake header (C4 A5 with a wrong header CRC) in the noise is not taken for one."""
    for feed in ("whole", "bytewise"):
        fr = FrameReader()
        if feed == "whole":
            fr.feed(garbage + BX_VALID + b"OKAYA896\r")
            out = [fr.pop(), fr.pop()]
        else:
            out = _bytewise(fr, garbage + BX_VALID + b"OKAYA896\r")
        assert [r.binary for r in out] == [True, False] and out[0].data == parse_frame(BX_VALID).data
        assert fr.garbage_bytes == len(garbage) and fr.pending == 0 and fr.pop() is None


@pytest.mark.parametrize("garbage", [b"\x00", b"\xfe\x01", b"ab\x9c"])
def test_garbage_before_an_ascii_reply_is_skipped_after_a_byte_no_reply_contains(garbage):
    for feed in ("whole", "bytewise"):
        fr = FrameReader()
        data = garbage + b"OKAYA896\r" + BX_VALID
        if feed == "whole":
            fr.feed(data)
            out = [fr.pop(), fr.pop()]
        else:
            out = _bytewise(fr, data)
        assert out[0].data == b"OKAY" and out[1].binary and fr.garbage_bytes == len(garbage)


def test_a_corrupted_ascii_reply_is_not_cut_to_a_shorter_one():
    """Printable bytes before a reply, or a reply whose own bytes are wrong: no resynchronisation inside it (a
    suffix of a corrupted TX reply must never pass as a reply), the CRC error as before."""
    for data in (b"xOKAYA896\r", b"OKAZA896\r", b"ab" + b"OKAYA896\r"):
        fr = FrameReader()
        fr.feed(data)
        with pytest.raises(NdiCrcError):
            fr.pop()
        assert fr.garbage_bytes == 0


@pytest.mark.parametrize("noise", [b"\r", b"\x01\r", b"ab\x9c\r", b"\x93\r\x80", b"OKAY\xff\r\xfe", b"\r\r\r\x00"])
def test_noise_holding_a_cr_is_skipped_and_the_reply_behind_it_read(noise):
    """Noise with a CR in it ends a "frame" that cannot be a reply (a byte no reply contains among the last four,
    or fewer than four bytes): skipped as garbage, and the ASCII or binary reply behind it is read -- it used to be a
    CRC error, after which the client dropped the reply with the buffer and repeated the command (CI: a stray read
    timeout when the reply's tail came after the drain)."""
    for reply in (b"OKAYA896\r", BX_VALID):
        for feed in ("whole", "bytewise"):
            fr = FrameReader()
            if feed == "whole":
                fr.feed(noise + reply)
                out = [fr.pop()]
            else:
                out = _bytewise(fr, noise + reply)
            assert len(out) == 1 and out[0].binary == (reply == BX_VALID), (feed, out)
            assert fr.garbage_bytes == len(noise) and fr.pending == 0 and fr.pop() is None


def test_thousands_of_noise_crs_do_not_exhaust_the_stack():
    fr = FrameReader()
    fr.feed(b"\x00\r" * 50_000 + b"OKAYA896\r")
    assert fr.pop().data == b"OKAY" and fr.garbage_bytes == 100_000
