"""OMC backend ``nokov_sdk``: the vendor's ``libnokov_sdk.so`` through ctypes (flat C API).

Struct layouts are transcribed field for field from ``NokovSDKTypes.h`` ("version 1.3.0.12", shipped in
NOKOV-MOCAP/mocap_nokov ``deps/nokov_sdk/include``); the flat C API (a client handle first) is the one the
vendor's own Python (``nokovsdk.py``) and C# wrappers call: ``CreateClient(void**)``, ``Initialize(h, ip)``,
``SetDataCallback(h, cb, user)``, ``SetNotifyMsgCallback(h, cb, user)``, ``GetDataDescriptions(h,
sDataDescriptions**)``, ``Uninitialize(h)``, ``DestroyClient(h)``, ``NokovVersion(h, uchar[4])``.
Newer SDKs append ``FrameExtendData`` after ``params`` in ``sFrameOfMocapData``; we only read frames the
SDK owns through a pointer, so a trailing extension does not move any field we read.

Behaviour (reference/nokov_mocap.md §1, §6):
* names are not in frames: they are resolved from the data descriptions at connect time, again when the
  SDK notifies a rigid-body change (``RigidBodyChange``), and when a frame carries an unknown id;
* positions are millimetres (converted to metres by :class:`~.frames.FramePipeline`); a lost body keeps
  coming with ``UNDEFINED`` (999999.9999) coordinates — handled as "not tracked" by the pipeline;
* ``params`` bit semantics are UNCERTAIN for NOKOV (NatNet: bit0 = tracking valid), so the flag test is
  opt-in: ``valid_flag_mask`` (0 = ignore the flags);
* ``iTimeStamp`` and ``fLatency`` units are UNCERTAIN (one fork treats iTimeStamp as ms; NatNet's fLatency
  is seconds) — both are parameters; an implausible latency is counted by the pipeline, not used.

Threading: the SDK calls ``_on_data``/``_on_notify`` on its own thread; they copy what they need and hand
it on through ``on_frame`` (a :class:`~fullperc_drivers.handoff.Handoff` in the node) and never raise.
Blocking SDK calls (Initialize can wait seconds for the server, GetDataDescriptions asks the server) run on
the backend's worker thread, so the ROS executor never blocks; it reconnects with exponential back-off.
"""

from __future__ import annotations

import ctypes
import threading
import time
from collections.abc import Callable
from ctypes import (
    CFUNCTYPE,
    POINTER,
    Structure,
    Union,
    c_char,
    c_char_p,
    c_float,
    c_int,
    c_longlong,
    c_short,
    c_ubyte,
    c_uint,
    c_ulonglong,
    c_void_p,
)

from ..vendor_lib import load_vendor_library
from .frames import RawBody, RawFrame

MAX_MODELS = 200
MAX_RIGIDBODIES = 1000
MAX_NAMELENGTH = 256
MAX_SKELETONS = 100
MAX_SKELRIGIDBODIES = 200
MAX_LABELED_MARKERS = 1000
MAX_ANALOG_CHANNELS = 32
MAX_MSG_LENGTH = 100
UNDEFINED = 999999.9999

Descriptor_MarkerSet, Descriptor_RigidBody, Descriptor_Skeleton, Descriptor_ForcePlate = 0, 1, 2, 3
RigidBodyChange, SkeletonChange = 1, 2
ERROR_CODES = {0: "OK", 1: "Internal", 2: "External", 3: "Network", 4: "Other"}

MarkerData = c_float * 3


class sMarker(Structure):
    _fields_ = [("ID", c_int), ("x", c_float), ("y", c_float), ("z", c_float), ("size", c_float),
                ("params", c_short)]


class sMarkerSetDescription(Structure):
    _fields_ = [("szName", c_char * MAX_NAMELENGTH), ("nMarkers", c_int), ("szMarkerNames", POINTER(c_char_p))]


class sMarkerSetData(Structure):
    _fields_ = [("szName", c_char * MAX_NAMELENGTH), ("nMarkers", c_int), ("Markers", POINTER(MarkerData))]


class sRigidBodyDescription(Structure):
    _fields_ = [("szName", c_char * MAX_NAMELENGTH), ("ID", c_int), ("parentID", c_int),
                ("offsetx", c_float), ("offsety", c_float), ("offsetz", c_float),
                ("qx", c_float), ("qy", c_float), ("qz", c_float), ("qw", c_float)]


class sRigidBodyData(Structure):
    _fields_ = [("ID", c_int), ("x", c_float), ("y", c_float), ("z", c_float),
                ("qx", c_float), ("qy", c_float), ("qz", c_float), ("qw", c_float),
                ("nMarkers", c_int), ("Markers", POINTER(MarkerData)), ("MarkerIDs", POINTER(c_int)),
                ("MarkerSizes", POINTER(c_float)), ("MeanError", c_float), ("params", c_short)]


class sSkeletonDescription(Structure):
    _fields_ = [("szName", c_char * MAX_NAMELENGTH), ("skeletonID", c_int), ("nRigidBodies", c_int),
                ("RigidBodies", sRigidBodyDescription * MAX_SKELRIGIDBODIES)]


class sSkeletonData(Structure):
    _fields_ = [("skeletonID", c_int), ("nRigidBodies", c_int), ("RigidBodyData", POINTER(sRigidBodyData))]


class sForcePlateDescription(Structure):
    _fields_ = [("ID", c_int), ("scale", c_int), ("fWidth", c_float), ("fLength", c_float),
                ("Position", c_float * 3), ("Electrical", c_float * 3), ("Orientation", (c_float * 3) * 3),
                ("fCalMat", (c_float * 8) * 8), ("fCorners", (c_float * 3) * 4), ("iPlateType", c_int),
                ("iChannelDataType", c_int), ("nChannels", c_int),
                ("szChannelNames", (c_char * MAX_NAMELENGTH) * MAX_ANALOG_CHANNELS)]


class _DescriptionData(Union):
    _fields_ = [("MarkerSetDescription", POINTER(sMarkerSetDescription)),
                ("RigidBodyDescription", POINTER(sRigidBodyDescription)),
                ("SkeletonDescription", POINTER(sSkeletonDescription)),
                ("ForcePlateDescription", POINTER(sForcePlateDescription)),
                ("MarkerSetData", POINTER(sMarkerSetData))]


class sDataDescription(Structure):
    _fields_ = [("type", c_int), ("Data", _DescriptionData)]


class sDataDescriptions(Structure):
    _fields_ = [("nDataDescriptions", c_int), ("arrDataDescriptions", sDataDescription * MAX_MODELS)]


class sFrameOfMocapData(Structure):
    _fields_ = [("iFrame", c_int), ("nMarkerSets", c_int), ("MocapData", sMarkerSetData * MAX_MODELS),
                ("nOtherMarkers", c_int), ("OtherMarkers", POINTER(MarkerData)),
                ("nRigidBodies", c_int), ("RigidBodies", sRigidBodyData * MAX_RIGIDBODIES),
                ("nSkeletons", c_int), ("Skeletons", sSkeletonData * MAX_SKELETONS),
                ("nLabeledMarkers", c_int), ("LabeledMarkers", sMarker * MAX_LABELED_MARKERS),
                ("nAnalogdatas", c_int), ("Analogdata", c_float * MAX_ANALOG_CHANNELS),
                ("fLatency", c_float), ("Timecode", c_uint), ("TimecodeSubframe", c_uint),
                ("iTimeStamp", c_longlong), ("params", c_short)]


class sNotifyMsg(Structure):
    _fields_ = [("nType", c_int), ("nValue", c_int), ("nParam1", c_int), ("nParam2", c_int), ("nParam3", c_int),
                ("nParam4", c_int), ("nTimeStamp", c_ulonglong), ("sMsg", c_char * MAX_MSG_LENGTH)]


DATA_CALLBACK = CFUNCTYPE(None, POINTER(sFrameOfMocapData), c_void_p)
NOTIFY_CALLBACK = CFUNCTYPE(None, POINTER(sNotifyMsg), c_void_p)

STRUCTS = {"sMarker": sMarker, "sMarkerSetData": sMarkerSetData, "sRigidBodyDescription": sRigidBodyDescription,
           "sRigidBodyData": sRigidBodyData, "sSkeletonData": sSkeletonData,
           "sSkeletonDescription": sSkeletonDescription, "sForcePlateDescription": sForcePlateDescription,
           "sDataDescription": sDataDescription, "sDataDescriptions": sDataDescriptions,
           "sFrameOfMocapData": sFrameOfMocapData, "sNotifyMsg": sNotifyMsg}

_REQUIRED = ("CreateClient", "DestroyClient", "Initialize", "Uninitialize", "SetDataCallback",
             "GetDataDescriptions")


class NokovSdkError(RuntimeError):
    """The SDK library cannot be loaded/used; the message names the library path."""


_SIGNATURES = {
    "CreateClient": ([POINTER(c_void_p)], c_int),
    "DestroyClient": ([c_void_p], c_int),
    "Initialize": ([c_void_p, c_char_p], c_int),
    "Uninitialize": ([c_void_p], c_int),
    "SetDataCallback": ([c_void_p, DATA_CALLBACK, c_void_p], c_int),
    "GetDataDescriptions": ([c_void_p, POINTER(POINTER(sDataDescriptions))], c_int),
    "SetNotifyMsgCallback": ([c_void_p, NOTIFY_CALLBACK, c_void_p], c_int),  # optional
    "NokovVersion": ([c_void_p, POINTER(c_ubyte)], None),  # optional
}


def load_library(path: str) -> ctypes.CDLL:
    """Load ``libnokov_sdk.so`` from ``path`` and declare the flat C API; clear errors naming the path."""
    return load_vendor_library(path, what="NOKOV SDK", parameter="sdk_library", file_name="libnokov_sdk.so",
                               signatures=_SIGNATURES, required=_REQUIRED, error=NokovSdkError)


def read_descriptions(lib: ctypes.CDLL, handle: c_void_p) -> dict[int, str]:
    """Rigid-body id -> name from ``GetDataDescriptions``.

    The returned block is not freed: the flat API's ownership rule is undocumented (the vendor's Python
    wrapper never frees it), a double free would crash, and refreshes are rare.
    """
    p = POINTER(sDataDescriptions)()
    rc = lib.GetDataDescriptions(handle, ctypes.byref(p))
    if rc != 0 or not p:
        raise NokovSdkError(f"GetDataDescriptions failed ({ERROR_CODES.get(rc, rc)})")
    d = p.contents
    names: dict[int, str] = {}
    for i in range(max(0, min(d.nDataDescriptions, MAX_MODELS))):
        desc = d.arrDataDescriptions[i]
        if desc.type == Descriptor_RigidBody and desc.Data.RigidBodyDescription:
            rb = desc.Data.RigidBodyDescription.contents
            names[int(rb.ID)] = rb.szName.decode("utf-8", errors="replace")
    return names


class NokovSdkBackend:
    """Connects through the SDK, resolves names, delivers :class:`RawFrame` from the SDK thread."""

    name = "nokov_sdk"

    def __init__(self, library: str, server: str, on_frame: Callable[[RawFrame], None],
                 timestamp_unit_ns: int = 1_000_000, latency_unit_s: float = 1.0, valid_flag_mask: int = 0,
                 backoff_s: tuple[float, float] = (0.5, 8.0), on_event: Callable[[], None] | None = None) -> None:
        self.lib = load_library(library)
        self.library = library
        self.server = server
        self._on_frame = on_frame
        self._on_event = on_event
        self.ts_unit_ns = int(timestamp_unit_ns)
        self.lat_unit_s = float(latency_unit_s)
        self.mask = int(valid_flag_mask)
        self.backoff = backoff_s
        self.names: dict[int, str] = {}
        self.version = ""
        self.connected = False
        self.last_error = ""
        self.connect_attempts = 0
        self.name_refreshes = 0
        self.notifications = 0
        self.callback_errors = 0
        self._handle = c_void_p()
        rc = self.lib.CreateClient(ctypes.byref(self._handle))
        if rc != 0 or not self._handle:
            raise NokovSdkError(f"CreateClient failed in '{library}' ({ERROR_CODES.get(rc, rc)})")
        if hasattr(self.lib, "NokovVersion"):
            v = (c_ubyte * 4)()
            self.lib.NokovVersion(self._handle, v)
            self.version = ".".join(str(x) for x in v)
        # Keep the ctypes thunks alive as long as the SDK may call them.
        self._data_cb = DATA_CALLBACK(self._on_data)
        self._notify_cb = NOTIFY_CALLBACK(self._on_notify)
        self.lib.SetDataCallback(self._handle, self._data_cb, None)
        if hasattr(self.lib, "SetNotifyMsgCallback"):
            self.lib.SetNotifyMsgCallback(self._handle, self._notify_cb, None)
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._want_refresh = False
        self._want_reconnect = False
        self._last_unknown_refresh = 0.0
        self._worker = threading.Thread(target=self._run, name="nokov-sdk", daemon=True)
        self._worker.start()

    # ---- SDK thread -------------------------------------------------------------------------------
    def _on_data(self, pframe, _user) -> None:
        try:
            recv_ns = time.time_ns()
            if not pframe:
                return
            f = pframe.contents
            names = self.names
            bodies = []
            unknown = False
            for i in range(max(0, min(f.nRigidBodies, MAX_RIGIDBODIES))):
                rb = f.RigidBodies[i]
                name = names.get(rb.ID, "")
                unknown |= not name
                flag = bool(rb.params & self.mask) if self.mask else True
                bodies.append(RawBody(int(rb.ID), name, (rb.x, rb.y, rb.z), (rb.qx, rb.qy, rb.qz, rb.qw),
                                      float(rb.MeanError), flag, int(rb.nMarkers)))
            frame = RawFrame(int(f.iFrame) & 0xFFFFFFFF, int(f.iTimeStamp) * self.ts_unit_ns,
                             float(f.fLatency) * self.lat_unit_s, recv_ns, bodies)
            if unknown and time.monotonic() - self._last_unknown_refresh > 0.5:
                self._last_unknown_refresh = time.monotonic()
                self.request_refresh()
            self._on_frame(frame)
        except Exception as e:  # noqa: BLE001 - never raise into C
            self.callback_errors += 1
            self.last_error = f"data callback: {e}"

    def _on_notify(self, pmsg, _user) -> None:
        try:
            self.notifications += 1
            if pmsg and pmsg.contents.nType == RigidBodyChange:
                self.request_refresh()
        except Exception as e:  # noqa: BLE001 - never raise into C
            self.callback_errors += 1
            self.last_error = f"notify callback: {e}"

    # ---- worker thread ----------------------------------------------------------------------------
    def request_refresh(self) -> None:
        self._want_refresh = True
        self._wake.set()

    def request_reconnect(self) -> None:
        """Called by the node when frames stop arriving: Uninitialize and connect again."""
        self._want_reconnect = True
        self._wake.set()

    def name_of(self, body_id: int) -> str:
        return self.names.get(body_id, "")

    def _event(self) -> None:
        if self._on_event is not None:
            try:
                self._on_event()
            except Exception:  # noqa: BLE001
                pass

    def _connect(self) -> None:
        delay = self.backoff[0]
        while not self._stop.is_set():
            self.connect_attempts += 1
            rc = self.lib.Initialize(self._handle, self.server.encode())
            if rc == 0:
                self.connected = True
                self.last_error = ""
                self._want_refresh = True
                self._event()
                return
            self.last_error = f"Initialize({self.server}) failed: {ERROR_CODES.get(rc, rc)}; retry in {delay:.1f} s"
            self._event()
            if self._stop.wait(delay):
                return
            delay = min(delay * 2, self.backoff[1])

    def _refresh(self) -> None:
        self._want_refresh = False
        try:
            self.names = read_descriptions(self.lib, self._handle)  # replaced wholesale: readers never lock
            self.name_refreshes += 1
        except NokovSdkError as e:
            self.last_error = str(e)
        self._event()

    def _run(self) -> None:
        self._connect()
        while not self._stop.is_set():
            if self._want_reconnect:
                self._want_reconnect = False
                self.connected = False
                self.lib.Uninitialize(self._handle)
                self._connect()
            if self._want_refresh and self.connected:
                self._refresh()
            self._wake.wait()
            self._wake.clear()

    def close(self) -> None:
        self._stop.set()
        self._wake.set()
        self._worker.join(timeout=5.0)
        try:
            self.lib.SetDataCallback(self._handle, DATA_CALLBACK(), None)
            if hasattr(self.lib, "SetNotifyMsgCallback"):
                self.lib.SetNotifyMsgCallback(self._handle, NOTIFY_CALLBACK(), None)
            self.lib.Uninitialize(self._handle)
            self.lib.DestroyClient(self._handle)
        finally:
            self.connected = False
