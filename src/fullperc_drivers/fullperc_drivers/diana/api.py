"""Diana backend ``diana_api``: the vendor ``DianaApi`` library (``libDianaApi.so``) through ctypes.

Signatures from ``DianaAPI.h`` (vendor SDK as shipped in public repos, see reference/diana_eval.md §1.3);
the header is ``#pragma pack(1)``:

    typedef struct _SrvNetSt { char SrvIp[32]; unsigned short LocHeartbeatPort, LocRobotStatePort,
                               LocSrvPort, LocRealtimeSrvPort, LocPassThroughSrvPort; } srv_net_st;
    void initSrvNetInfo(srv_net_st*);                                   (optional, newer SDKs)
    int  initSrv(FNCERRORCALLBACK fnError, FNCSTATECALLBACK fnState, srv_net_st* pinfo);
    int  destroySrv(const char* strIpAddress);
    int  getJointPos(double joints[7], const char* strIpAddress);
    int  getTcpPos(double pose[6], const char* strIpAddress);           (x y z [m], rotation vector [rad])
    int  getDH(double a[7], double alpha[7], double d[7], double theta[7], const char* strIpAddress);
    int  getLastError(const char*); const char* formatError(int, const char*);

Return value 0 = success (vendor examples test ``!= 0`` / ``< 0``). Both callbacks are passed as NULL: the
``StrRobotStateInfo`` layout differs between SDK versions (v2.5 vs v2.16 vs v2.19 add fields), so decoding
it would bind us to one firmware; ``getJointPos`` reads the same push-stream cache instead. The controller
pushes no hardware timestamp, so samples are stamped with the host time of the read; the cached value is
at most one push period old (``setPushPeriod``; 10 ms in the examples) — ``age_compensation_s`` can
subtract a known mean age. Connecting (``initSrv`` may block) runs on a worker thread with exponential
back-off; reads are non-blocking cache reads and run on the executor.
"""

from __future__ import annotations

import ctypes
import threading
import time
from ctypes import POINTER, Structure, c_char, c_char_p, c_double, c_int, c_ushort, c_void_p

import numpy as np

from ..diana_kinematics import N_JOINTS
from ..vendor_lib import load_vendor_library
from . import JointSample


class srv_net_st(Structure):
    _pack_ = 1
    _fields_ = [("SrvIp", c_char * 32), ("LocHeartbeatPort", c_ushort), ("LocRobotStatePort", c_ushort),
                ("LocSrvPort", c_ushort), ("LocRealtimeSrvPort", c_ushort), ("LocPassThroughSrvPort", c_ushort)]


_REQUIRED = ("initSrv", "destroySrv", "getJointPos")
DoubleArr7 = c_double * 7


class DianaApiError(RuntimeError):
    """The DianaApi library cannot be loaded/used; the message names the library path."""


_SIGNATURES = {
    "initSrv": ([c_void_p, c_void_p, POINTER(srv_net_st)], c_int),
    "destroySrv": ([c_char_p], c_int),
    "getJointPos": ([POINTER(c_double), c_char_p], c_int),
    "initSrvNetInfo": ([POINTER(srv_net_st)], None),  # optional from here on
    "getTcpPos": ([POINTER(c_double), c_char_p], c_int),
    "getDH": ([POINTER(c_double)] * 4 + [c_char_p], c_int),
    "getLastError": ([c_char_p], c_int),
    "formatError": ([c_int, c_char_p], c_char_p),
}


def load_library(path: str) -> ctypes.CDLL:
    """Load ``libDianaApi.so`` from ``path`` and declare the functions we call; clear errors naming the path."""
    return load_vendor_library(path, what="DianaApi", parameter="api_library", file_name="libDianaApi.so",
                               signatures=_SIGNATURES, required=_REQUIRED, error=DianaApiError)


class DianaApiBackend:
    """Connects with initSrv (worker thread, back-off), reads joints/TCP from the SDK cache on demand."""

    name = "diana_api"

    def __init__(self, library: str, robot_ip: str, read_tcp: bool = True, age_compensation_s: float = 0.0,
                 backoff_s: tuple[float, float] = (0.5, 8.0), reconnect_after_failures: int = 50) -> None:
        self.lib = load_library(library)
        self.library = library
        self.ip = robot_ip
        self._ip_b = robot_ip.encode()
        self.read_tcp = read_tcp and hasattr(self.lib, "getTcpPos")
        self.age_ns = int(age_compensation_s * 1e9)
        self.backoff = backoff_s
        self.reconnect_after = reconnect_after_failures
        self.connected = False
        self.last_error = ""
        self.connect_attempts = 0
        self.read_failures = 0
        self.invalid = 0
        self._consecutive_failures = 0
        self._net = srv_net_st()
        self._q = DoubleArr7()
        self._tcp = (c_double * 6)()
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._worker = threading.Thread(target=self._run, name="diana-api", daemon=True)
        self._worker.start()

    def _error_text(self, rc: int) -> str:
        txt = f"code {rc}"
        try:
            if hasattr(self.lib, "getLastError") and hasattr(self.lib, "formatError"):
                e = self.lib.getLastError(self._ip_b)
                msg = self.lib.formatError(e, self._ip_b)
                txt = f"code {rc}, last error {e}: {msg.decode(errors='replace') if msg else ''}"
        except Exception:  # noqa: BLE001 - diagnostics only
            pass
        return txt

    def _connect(self) -> None:
        delay = self.backoff[0]
        while not self._stop.is_set():
            self.connect_attempts += 1
            if hasattr(self.lib, "initSrvNetInfo"):
                self.lib.initSrvNetInfo(ctypes.byref(self._net))
            self._net.SrvIp = self._ip_b[:31]
            for port in ("LocHeartbeatPort", "LocRobotStatePort", "LocSrvPort", "LocRealtimeSrvPort",
                         "LocPassThroughSrvPort"):
                setattr(self._net, port, 0)  # 0 = let the OS choose (all vendor examples)
            rc = self.lib.initSrv(None, None, ctypes.byref(self._net))
            if rc == 0:
                self.connected = True
                self.last_error = ""
                self._consecutive_failures = 0
                return
            self.last_error = f"initSrv({self.ip}) failed: {self._error_text(rc)}; retry in {delay:.1f} s"
            if self._stop.wait(delay):
                return
            delay = min(delay * 2, self.backoff[1])

    def _run(self) -> None:
        while not self._stop.is_set():
            if not self.connected:
                self._connect()
            self._wake.wait()
            self._wake.clear()

    def _reconnect(self) -> None:
        self.connected = False
        try:
            self.lib.destroySrv(self._ip_b)
        except Exception:  # noqa: BLE001
            pass
        self._wake.set()

    def read_dh(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
        """The controller's DH table (a, alpha, d, theta; m, rad) via getDH, or None if unavailable."""
        if not (self.connected and hasattr(self.lib, "getDH")):
            return None
        arrs = [DoubleArr7() for _ in range(4)]
        rc = self.lib.getDH(*arrs, self._ip_b)
        if rc != 0:
            self.last_error = f"getDH failed: {self._error_text(rc)}"
            return None
        out = tuple(np.array(a[:], dtype=float) for a in arrs)
        if not all(np.all(np.isfinite(a)) for a in out):
            self.last_error = "getDH returned non-finite values"
            return None
        return out  # type: ignore[return-value]

    def read(self) -> JointSample | None:
        """One sample from the SDK cache (called from the node's timer), or None."""
        if not self.connected:
            return None
        stamp = time.time_ns() - self.age_ns
        rc = self.lib.getJointPos(self._q, self._ip_b)
        if rc != 0:
            self.read_failures += 1
            self._consecutive_failures += 1
            self.last_error = f"getJointPos failed: {self._error_text(rc)}"
            if self._consecutive_failures >= self.reconnect_after:
                self.last_error += "; reconnecting"
                self._reconnect()
            return None
        self._consecutive_failures = 0
        q = np.array(self._q[:], dtype=float)
        if q.shape != (N_JOINTS,) or not np.all(np.isfinite(q)):
            self.invalid += 1
            self.last_error = "getJointPos returned non-finite values"
            return None
        tcp = None
        if self.read_tcp and self.lib.getTcpPos(self._tcp, self._ip_b) == 0:
            tcp = np.array(self._tcp[:], dtype=float)
            if not np.all(np.isfinite(tcp)):
                tcp = None
        return JointSample(stamp, q, None, -1, tcp)

    def close(self) -> None:
        self._stop.set()
        self._wake.set()
        self._worker.join(timeout=5.0)
        if self.connected:
            self.lib.destroySrv(self._ip_b)
        self.connected = False
