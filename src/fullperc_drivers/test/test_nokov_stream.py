"""OMC/Diana stream backends in-process over real UDP sockets, the Diana pipeline, and the Handoff."""

import socket
import struct
import threading
import time

import numpy as np

from fullperc_common.testing import wait_for
from fullperc_drivers.clock_sync import ClockSync
from fullperc_drivers.diana.stream import DianaStreamBackend, DianaStreamPipeline, RawJointState
from fullperc_drivers.handoff import Handoff
from fullperc_drivers.nokov.stream import OmcStreamBackend
from fullperc_drivers.streams import DianaState, OmcBody, OmcFrame, encode_diana, encode_omc

MS = 1_000_000


def _send(port, *datagrams):
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        for d in datagrams:
            s.sendto(d, ("127.0.0.1", port))


def test_omc_stream_backend_decodes_and_counts_garbage():
    got = []
    be = OmcStreamBackend("127.0.0.1", 0, got.append)
    try:
        port = be.address[1]
        good = encode_omc(OmcFrame(42, 7 * 10**9, 0.002, [
            OmcBody(3, "tool", np.array([1.5, -2.0, 3.25]), np.array([0, 0, 0.6, 0.8]), 0.2, False, 0)]))
        before = time.time_ns()
        _send(port, good[:-3], b"", b"\x00" * 200, good, b"FPOM" + struct.pack("<H", 2) + good[6:])
        wait_for(lambda: be.datagrams >= 5, timeout=10, what="datagrams")
        after = time.time_ns()
    finally:
        be.close()
    assert be.decode_errors == 4 and len(got) == 1 and "version" in be.last_error
    f = got[0]
    assert (f.frame_number, f.device_ts_ns, f.latency_s) == (42, 7 * 10**9, np.float32(0.002))
    assert before <= f.recv_ns <= after
    b = f.bodies[0]
    assert (b.id, b.name, b.tracked_flag, b.markers) == (3, "tool", False, 0)
    assert b.position_mm == (1.5, -2.0, 3.25)


def test_diana_stream_backend_and_pipeline():
    got = []
    be = DianaStreamBackend("127.0.0.1", 0, got.append)
    try:
        q = np.linspace(-1, 1, 7)
        _send(be.address[1], encode_diana(DianaState(1, 5 * 10**9, q, q * 0.1)), b"FPDA", encode_diana(
            DianaState(2, 5 * 10**9 + MS, q[:6], q[:6])))
        wait_for(lambda: be.datagrams >= 3, timeout=10, what="datagrams")
    finally:
        be.close()
    assert be.decode_errors == 1 and len(got) == 2
    p = DianaStreamPipeline(ClockSync())
    s = p.process(got[0])
    assert s is not None and np.array_equal(s.q, np.linspace(-1, 1, 7)) and s.sequence == 1
    assert p.process(got[1]) is None and p.counters.invalid == 1


def test_diana_pipeline_offsets_gaps_duplicates_nan():
    p = DianaStreamPipeline(ClockSync())
    off, d = -5 * 10**9, 30_000
    q = np.zeros(7)

    def raw(seq, t, qq=q):
        return RawJointState(seq, t - off, t + d, qq, np.zeros(7))

    t = 10**15
    assert p.process(raw(1, t)).stamp_ns == t + d
    assert p.process(raw(4, t + MS)).stamp_ns == t + MS + d  # 2 and 3 missing
    assert p.process(raw(4, t + 2 * MS)) is None  # duplicate
    assert p.process(raw(3, t + 3 * MS)) is None  # late/out of order
    bad = q.copy()
    bad[0] = np.nan
    assert p.process(raw(5, t + 4 * MS, bad)) is None
    c = p.counters
    assert (c.samples, c.dropped, c.duplicates, c.invalid) == (2, 2, 2, 1)


def test_handoff_bounded_never_raises_and_notifies_from_threads():
    calls = []
    h = Handoff(maxlen=3, notify=lambda: calls.append(1))
    threads = [threading.Thread(target=lambda i=i: h.put(i)) for i in range(10)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(h) == 3 and h.overflow == 7 and len(calls) == 10
    assert len(h.drain()) == 3 and len(h) == 0

    def boom():
        raise RuntimeError("executor gone")

    h2 = Handoff(notify=boom)
    h2.put(1)  # must not raise
    assert h2.notify_errors == 1 and h2.drain() == [1]
