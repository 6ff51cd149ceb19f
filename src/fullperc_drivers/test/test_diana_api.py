"""The ctypes DianaApi backend against a C test double compiled here (DianaAPI.h signatures, packed srv_net_st).

The double computes the vendor-style TCP pose (x y z + rotation vector) with its own C implementation of
the modified-DH chain, so comparing it with our pinocchio FK checks two independent implementations.
"""

from __future__ import annotations

import ctypes
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fullperc_common.testing import wait_for
from fullperc_drivers.diana import api
from fullperc_drivers.diana_kinematics import DianaKinematics

C_DIR = Path(__file__).parent / "c"
IP = "192.168.10.75"


def compile_double(src: Path, out: Path) -> Path:
    gcc = shutil.which("gcc")
    if gcc is None:
        pytest.skip("gcc not installed: cannot build the C test double of the vendor SDK")
    subprocess.run([gcc, "-shared", "-fPIC", "-O1", "-Wall", "-o", str(out), str(src), "-lm"],
                   check=True, capture_output=True)
    return out


@pytest.fixture(scope="module")
def lib_path(tmp_path_factory) -> Path:
    return compile_double(C_DIR / "fake_diana_api.c", tmp_path_factory.mktemp("diana") / "libfake_diana.so")


@pytest.fixture
def fake(lib_path):
    lib = ctypes.CDLL(str(lib_path))
    lib.FakeDiana_Configure.argtypes = [ctypes.c_char_p]
    lib.FakeDiana_SetJoints.argtypes = [ctypes.POINTER(ctypes.c_double)]
    lib.FakeDiana_SetD1.argtypes = [ctypes.c_double]
    lib.FakeDiana_Configure(IP.encode())
    return lib


def _set_q(fake, q):
    fake.FakeDiana_SetJoints((ctypes.c_double * 7)(*q))


def test_srv_net_struct_is_packed_like_the_header(fake):
    assert ctypes.sizeof(api.srv_net_st) == fake.FakeDiana_SrvNetSize() == 42


def test_wrong_library_path_names_the_path(tmp_path):
    bad = tmp_path / "sdk" / "libDianaApi.so"
    with pytest.raises(api.DianaApiError, match=str(bad)):
        api.DianaApiBackend(str(bad), IP)
    garbage = tmp_path / "libDianaApi.so"
    garbage.write_bytes(b"\x7fELF garbage")
    with pytest.raises(api.DianaApiError, match="cannot load.*" + str(garbage)):
        api.DianaApiBackend(str(garbage), IP)


def test_reads_joints_and_vendor_tcp_matches_our_fk(fake, lib_path):
    be = api.DianaApiBackend(str(lib_path), IP)
    try:
        wait_for(lambda: be.connected, timeout=10, what="initSrv")
        assert [fake.FakeDiana_SeenPort(i) for i in range(5)] == [0] * 5
        kin = DianaKinematics()
        rng = np.random.default_rng(7)
        lo, hi = kin.joint_limits
        for _ in range(25):
            q = rng.uniform(lo, hi)
            _set_q(fake, q)
            s = be.read()
            assert s is not None and np.array_equal(s.q, q) and s.dq is None
            T = kin.fk(s.q)
            np.testing.assert_allclose(s.vendor_tcp[:3], T[:3, 3], atol=1e-9)
            R_vendor = Rotation.from_rotvec(s.vendor_tcp[3:]).as_matrix()
            np.testing.assert_allclose(R_vendor, T[:3, :3], atol=1e-6)
    finally:
        be.close()
    assert fake.FakeDiana_DestroyCalls() == 1


def test_controller_dh_table_is_read_in_vendor_order(fake, lib_path):
    fake.FakeDiana_SetD1(-0.2866)  # controller's calibrated base height differs by 1 mm
    be = api.DianaApiBackend(str(lib_path), IP)
    try:
        wait_for(lambda: be.connected, timeout=10, what="initSrv")
        a, alpha, d, theta = be.read_dh()
    finally:
        be.close()
    assert d[0] == pytest.approx(-0.2866) and a[3] == pytest.approx(0.065) and theta[5] == pytest.approx(np.pi)
    q = np.array([0.2, 0.3, -0.1, 1.2, 0.4, -0.5, 0.6])
    moved = DianaKinematics.from_getdh(a, alpha, d, theta).fk(q)[:3, 3] - DianaKinematics().fk(q)[:3, 3]
    assert np.linalg.norm(moved) == pytest.approx(0.001, abs=1e-9)


def test_unreachable_robot_retries_and_reports(fake, lib_path):
    be = api.DianaApiBackend(str(lib_path), "192.168.10.99", backoff_s=(0.02, 0.05))
    try:
        wait_for(lambda: fake.FakeDiana_InitCalls() >= 3, timeout=10, what="initSrv retries")
        assert not be.connected and be.read() is None
        assert "192.168.10.99" in be.last_error and "robot unreachable" in be.last_error
    finally:
        be.close()


def test_failed_and_bad_reads_are_counted_then_reconnect(fake, lib_path):
    be = api.DianaApiBackend(str(lib_path), IP, reconnect_after_failures=3, backoff_s=(0.02, 0.05))
    try:
        wait_for(lambda: be.connected, timeout=10, what="initSrv")
        _set_q(fake, [0.1] * 7)
        fake.FakeDiana_SetNaN(1)
        assert be.read() is None and be.invalid == 1
        fake.FakeDiana_SetNaN(0)
        fake.FakeDiana_FailReads(3)
        assert [be.read() for _ in range(3)] == [None, None, None]
        assert be.read_failures == 3 and "lost robot state" in be.last_error
        wait_for(lambda: fake.FakeDiana_InitCalls() >= 2 and be.connected, timeout=10, what="reconnect")
        s = be.read()
        assert s is not None and np.allclose(s.q, 0.1)
    finally:
        be.close()
