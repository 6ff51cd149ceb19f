"""``omc_driver`` and ``diana_state`` health across processes: frozen frame numbers and refused samples.

The installed executables receive a UDP stream that this test shapes phase by phase (a sender thread): normal
frames, then the same frame number (sequence) over and over, then non-finite poses / joint values, then normal
again. The ``/diagnostics`` level must leave OK with the reason in the message, and return to OK only once good
output flows again. Liveness bounds only (``wait_for``).
"""

from __future__ import annotations

import socket
import sys
import threading
import time
from pathlib import Path

import numpy as np

from fullperc_common.testing import side_by_side_fixture

sys.path.insert(0, str(Path(__file__).parent))
from test_diana_state import Listener as DianaListener  # noqa: E402
from test_omc_driver import Listener, free_udp_port  # noqa: E402

# Test modules are imported here, in the main thread, never inside a scenario: side_by_side runs scenarios in
# threads, and an import there has pytest rewrite the module with ast.parse, which the CPython 3.11.7 of CI does not
# make thread-safe ("SystemError: AST constructor recursion depth mismatch", seen in CI).

OK, WARN, ERROR = 0, 1, 2
# each fault phase lasts until the level left OK, which takes the health ladder's stale_after_s: 1 s instead of the
# default 2 s (10 stream periods at least; every wait below is a condition with a liveness bound)
STALE_AFTER = "health.stale_after_s:=1.0"


class Sender(threading.Thread):
    """Sends ``make(k, mode)`` every 10 ms to ``port``; ``mode`` is switched by the test."""

    def __init__(self, port: int, make) -> None:
        super().__init__(daemon=True)
        self.port, self.make = port, make
        self.mode = "normal"
        self._halt = threading.Event()

    def run(self) -> None:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            k = 0
            while not self._halt.wait(0.01):
                k += 1
                s.sendto(self.make(k, self.mode), ("127.0.0.1", self.port))

    def stop(self) -> None:
        self._halt.set()
        self.join(2)


def _wait_level(lis: Listener, name: str, level: int, *needles: str, timeout: float = 30.0) -> str:
    from fullperc_common.diagnostics import as_level
    from fullperc_common.testing import wait_for

    def ok():
        lis.spin()
        st, _ = lis.last_status(name)
        return st is not None and as_level(st.level) == level and all(n in st.message for n in needles)
    wait_for(ok, timeout=timeout, what=f"{name} level {level} with {needles} (last: "
                                       f"{getattr(lis.last_status(name)[0], 'message', None)})")
    return lis.last_status(name)[0].message


def _omc_driver_frozen_frames_and_refused_poses(procs, rclpy_context):
    from fullperc_common.testing import installed_exe, wait_for
    from fullperc_drivers.streams import OmcBody, OmcFrame, encode_omc

    frozen_at = {}

    def make(k, mode):
        fno = 5000 + k
        if mode == "frozen":
            fno = frozen_at.setdefault("f", fno)
        else:
            frozen_at.clear()
        pos = np.full(3, np.nan) if mode == "nan" else np.array([100.0, 200.0, 300.0 + k % 50])
        q = np.array([0.0, 0.0, 0.0, 1.0])
        return encode_omc(OmcFrame(fno, time.time_ns(), 0.002, [OmcBody(1, "base", pos, q, 0.1, True, 4),
                                                               OmcBody(2, "tool", pos + 10, q, 0.1, True, 4)]))

    port = free_udp_port()
    node = procs.start([installed_exe("fullperc_drivers", "omc_driver"), "--ros-args", "-p", f"stream_port:={port}",
                        "-p", "bodies:=[base, tool]", "-p", "diagnostics_period_s:=0.5", "-p", STALE_AFTER])
    lis = Listener(rclpy_context)
    sender = Sender(port, make)
    sender.start()
    try:
        wait_for(lambda: (lis.spin(), len(lis.poses["base"]) > 20)[1], timeout=40, what="OMC poses")
        _wait_level(lis, "omc", OK, "receiving at")
        sender.mode = "frozen"
        msg = _wait_level(lis, "omc", ERROR, "frame number frozen")
        assert "no new frames for" in msg
        sender.mode = "normal"
        _wait_level(lis, "omc", OK)
        sender.mode = "nan"
        msg = _wait_level(lis, "omc", ERROR, "every pose refused")
        assert "non-finite" in msg
        sender.mode = "normal"
        _wait_level(lis, "omc", OK)
        assert node.poll() is None
    finally:
        sender.stop()
        lis.close()


def _diana_state_frozen_sequence_and_refused_samples(procs, rclpy_context):
    from fullperc_common.testing import installed_exe, wait_for
    from fullperc_drivers.streams import DianaState, encode_diana

    frozen_at = {}

    def make(k, mode):
        seq = 100 + k
        if mode == "frozen":
            seq = frozen_at.setdefault("s", seq)
        else:
            frozen_at.clear()
        q = np.full(7, np.nan) if mode == "nan" else np.linspace(-0.5, 0.5, 7) + 0.001 * (k % 100)
        return encode_diana(DianaState(seq, time.time_ns(), q, np.zeros(7)))

    port = free_udp_port()
    node = procs.start([installed_exe("fullperc_drivers", "diana_state"), "--ros-args", "-p", f"stream_port:={port}",
                        "-p", "diagnostics_period_s:=0.5", "-p", STALE_AFTER])
    lis = DianaListener(rclpy_context)
    sender = Sender(port, make)
    sender.start()
    try:
        wait_for(lambda: (lis.spin(), len(lis.js) > 20)[1], timeout=40, what="joint states")
        _wait_level(lis, "diana", OK, "receiving at")
        sender.mode = "frozen"
        msg = _wait_level(lis, "diana", ERROR, "frame number frozen")
        assert "no new joint states for" in msg
        sender.mode = "normal"
        _wait_level(lis, "diana", OK)
        sender.mode = "nan"
        msg = _wait_level(lis, "diana", ERROR, "every joint state refused")
        assert "non-finite joint values" in msg
        sender.mode = "normal"
        _wait_level(lis, "diana", OK, timeout=30)
        assert node.poll() is None
    finally:
        sender.stop()
        lis.close()


scenarios = side_by_side_fixture(
    _omc_driver_frozen_frames_and_refused_poses,
    _diana_state_frozen_sequence_and_refused_samples)


def test_omc_driver_frozen_frames_and_refused_poses(scenarios, request):
    scenarios.result(request.node.name)


def test_diana_state_frozen_sequence_and_refused_samples(scenarios, request):
    scenarios.result(request.node.name)
