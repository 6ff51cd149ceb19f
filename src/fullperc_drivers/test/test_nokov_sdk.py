"""The ctypes NOKOV backend against a C test double compiled here (same flat C API and struct layouts).

The double (test/c/fake_nokov_sdk.c) plays a scripted scenario from its own C thread: "base" described
from the start, "tool" appearing later (descriptions + RigidBodyChange notification), "tool" lost for a
span (UNDEFINED sentinel), a frame-number gap, device timestamps on CLOCK_MONOTONIC (offset from the host
realtime clock). The truth (capture time on the host clock, positions) comes from the C side.
"""

from __future__ import annotations

import ctypes
import shutil
import subprocess
import threading
from pathlib import Path

import numpy as np
import pytest

from fullperc_common.testing import wait_for
from fullperc_drivers.nokov import sdk
from fullperc_drivers.nokov.frames import FramePipeline

C_DIR = Path(__file__).parent / "c"
FRAMES, APPEAR, LOST_FROM, LOST_TO, GAP_AT, GAP = 240, 40, 100, 120, 180, 3


def compile_double(src: Path, out: Path) -> Path:
    gcc = shutil.which("gcc")
    if gcc is None:
        pytest.skip("gcc not installed: cannot build the C test double of the vendor SDK")
    subprocess.run([gcc, "-shared", "-fPIC", "-O1", "-pthread", "-Wall", "-o", str(out), str(src), "-lm"],
                   check=True, capture_output=True)
    return out


@pytest.fixture(scope="module")
def fake_lib_path(tmp_path_factory) -> Path:
    return compile_double(C_DIR / "fake_nokov_sdk.c", tmp_path_factory.mktemp("nokov") / "libfake_nokov.so")


@pytest.fixture
def fake(fake_lib_path):
    lib = ctypes.CDLL(str(fake_lib_path))
    lib.FakeNokov_Configure.argtypes = [ctypes.c_int] * 7 + [ctypes.c_longlong, ctypes.c_float, ctypes.c_char_p]
    lib.FakeNokov_TruthCaptureNs.restype = ctypes.c_longlong
    lib.FakeNokov_BodyPositionMm.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.POINTER(ctypes.c_double)]
    lib.FakeNokov_Layout.argtypes = [ctypes.c_char_p]
    lib.FakeNokov_Layout.restype = ctypes.c_long
    lib.FakeNokov_Configure(FRAMES, 200, APPEAR, LOST_FROM, LOST_TO, GAP_AT, GAP, 1000, 0.004, b"10.1.1.198")
    return lib


class Collector:
    def __init__(self):
        self.frames = []
        self.lock = threading.Lock()

    def __call__(self, f):
        with self.lock:
            self.frames.append(f)


def test_struct_layouts_match_c(fake):
    for name, cls in sdk.STRUCTS.items():
        assert ctypes.sizeof(cls) == fake.FakeNokov_Layout(name.encode()), name
    for spec in ["sFrameOfMocapData.nRigidBodies", "sFrameOfMocapData.RigidBodies", "sFrameOfMocapData.fLatency",
                 "sFrameOfMocapData.iTimeStamp", "sFrameOfMocapData.params", "sRigidBodyData.MeanError",
                 "sRigidBodyData.params", "sNotifyMsg.nTimeStamp"]:
        struct, fld = spec.split(".")
        assert getattr(sdk.STRUCTS[struct], fld).offset == fake.FakeNokov_Layout(spec.encode()), spec


def test_wrong_library_path_names_the_path(tmp_path):
    bad = tmp_path / "nowhere" / "libnokov_sdk.so"
    with pytest.raises(sdk.NokovSdkError, match=str(bad)):
        sdk.NokovSdkBackend(str(bad), "10.1.1.198", lambda f: None)
    not_so = tmp_path / "libnokov_sdk.so"
    not_so.write_text("not an ELF file")
    with pytest.raises(sdk.NokovSdkError, match="cannot load.*" + str(not_so)):
        sdk.NokovSdkBackend(str(not_so), "10.1.1.198", lambda f: None)


def test_library_without_sdk_symbols_is_rejected(tmp_path):
    src = tmp_path / "other.c"
    src.write_text("int something(void) { return 1; }\n")
    so = compile_double(src, tmp_path / "libother.so")
    with pytest.raises(sdk.NokovSdkError, match=f"{so}.*CreateClient"):
        sdk.NokovSdkBackend(str(so), "10.1.1.198", lambda f: None)


def test_scenario_names_sentinels_gaps_units_and_stamps(fake, fake_lib_path):
    col = Collector()
    be = sdk.NokovSdkBackend(str(fake_lib_path), "10.1.1.198", col, timestamp_unit_ns=1000, latency_unit_s=1.0)
    try:
        assert be.version == "2.5.53.12"
        wait_for(lambda: fake.FakeNokov_Emitted() >= FRAMES, timeout=30, what="the double to play all frames")
        wait_for(lambda: len(col.frames) >= FRAMES, timeout=10, what="all frames delivered")
    finally:
        be.close()
    assert be.callback_errors == 0 and be.connected is False
    assert be.names == {1: "base", 2: "tool"}
    assert be.name_refreshes >= 2 and be.notifications >= 1  # at connect, and after the RigidBodyChange

    pipe = FramePipeline()
    out = []
    for raw in col.frames:
        for b in raw.bodies:  # names as the node resolves them at drain time
            b.name = b.name or be.name_of(b.id)
        out.append(pipe.process(raw))
    assert all(f is not None for f in out)
    assert pipe.counters.dropped == GAP and pipe.counters.duplicates == 0

    pos = (ctypes.c_double * 3)()
    errors_ns = []
    for k, f in enumerate(out):
        assert f.frame_number == fake.FakeNokov_FrameNumber(k)
        by_name = {b.name: b for b in f.bodies}
        assert by_name["base"].tracked
        fake.FakeNokov_BodyPositionMm(1, k, pos)
        np.testing.assert_allclose(by_name["base"].position_m, np.array(pos) / 1000.0, atol=1e-6)
        assert abs(np.linalg.norm(by_name["base"].quat_xyzw) - 1) < 1e-9
        tool = by_name.get("tool")
        if k < APPEAR:
            assert len(f.bodies) == 1
        elif tool is not None:
            if LOST_FROM <= k < LOST_TO:
                assert not tool.tracked and tool.reason == "sentinel" and tool.position_m is None
            else:
                assert tool.tracked
                fake.FakeNokov_BodyPositionMm(2, k, pos)
                np.testing.assert_allclose(tool.position_m, np.array(pos) / 1000.0, atol=1e-6)
        if k >= 10:
            errors_ns.append(f.stamp_ns - fake.FakeNokov_TruthCaptureNs(k))
    # The late body gets its name once descriptions are refreshed: a few frames right after it appears may
    # still be unnamed (refresh runs on the worker thread), but never more than a handful.
    unnamed = sum(1 for f in out for b in f.bodies if b.name == "")
    assert unnamed <= 20
    assert sum(1 for f in out[APPEAR + 20:] for b in f.bodies if b.name == "tool") == FRAMES - APPEAR - 20
    errors_ns = np.array(errors_ns)
    assert np.all(np.abs(errors_ns) < 1_000_000), f"stamp error range {errors_ns.min()}..{errors_ns.max()} ns"


def test_wrong_server_retries_with_backoff_and_reports(fake, fake_lib_path):
    col = Collector()
    be = sdk.NokovSdkBackend(str(fake_lib_path), "10.9.9.9", col, backoff_s=(0.02, 0.05))
    try:
        wait_for(lambda: be.connect_attempts >= 3, timeout=10, what="connection retries")
        assert not be.connected and "Network" in be.last_error and "10.9.9.9" in be.last_error
        assert col.frames == []
    finally:
        be.close()


def test_callback_errors_never_reach_c(fake, fake_lib_path):
    fake.FakeNokov_Configure(400, 200, 5, 1000, 1000, 1000, 0, 1000, 0.004, b"10.1.1.198")

    def boom(_frame):
        raise RuntimeError("consumer failed")

    be = sdk.NokovSdkBackend(str(fake_lib_path), "10.1.1.198", boom)
    try:
        # frames played before the SDK connection and the names are up never reach the consumer, so
        # count the errors that do: every consumer failure is caught and counted, none reaches C
        wait_for(lambda: be.callback_errors >= 30, timeout=20, what="consumer errors")
        wait_for(lambda: fake.FakeNokov_Emitted() >= 400, timeout=20, what="frames played")
    finally:
        be.close()
    assert be.callback_errors >= 30 and "consumer failed" in be.last_error


def test_implausible_latency_unit_is_counted_not_used(fake, fake_lib_path):
    fake.FakeNokov_Configure(20, 200, 5, 1000, 1000, 1000, 0, 1000, 0.004, b"10.1.1.198")
    col = Collector()
    be = sdk.NokovSdkBackend(str(fake_lib_path), "10.1.1.198", col, timestamp_unit_ns=1000, latency_unit_s=1000.0)
    try:
        wait_for(lambda: len(col.frames) >= 20, timeout=20, what="frames")
    finally:
        be.close()
    pipe = FramePipeline()
    for raw in col.frames:
        pipe.process(raw)
    assert pipe.counters.bad_latency == 20
