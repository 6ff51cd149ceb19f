"""Live serving of a simulated task: the device streams the drivers read, on 127.0.0.1 by default.

The whole task is first simulated offline (:func:`fullperc_eval.sim.runner.run_task`, a few seconds), then
played out against the host clock at ``speed`` (1.0 = real time; 2.0 = the world runs twice as fast,
and every time stamp, latency and rate is scaled with it so downstream sees a consistent, faster world).
So live and offline data are the same measurements.

Streams (wire formats: :mod:`fullperc_drivers.streams`):
  * OMC: one UDP datagram per frame (``encode_omc``) to ``omc_addr`` (default 127.0.0.1:3883), sent
    ``latency`` after capture; ``timestamp_ns`` is the capture time on the device clock (host clock +
    ``device_clock_offset_ns``), ``latency_s`` capture -> send, bodies ``base``, ``ots_rig``, ``tool`` (and the
    extra targets', ``instrument`` and ``reference``) with the ids of scene.yaml, position in mm, quaternion x y z w,
    mean marker error in mm, tracked flag, markers used (untracked bodies carry zeros and tracked = 0: no NaN on the
    wire);
  * Diana: one UDP datagram per joint-state sample (``encode_diana``) to ``diana_addr`` (default
    127.0.0.1:3884), stamped with the sample time on the device clock;
  * NDI Vega: the Combined-API emulator (:class:`fullperc_eval.emulators.vega_server.VegaEmulator`) on TCP
    ``vega_port`` (default 8765; 0 = any free port, reported on stdout), fed with the OTS model's
    measurements: the simulated Vega frame of the emulator's frame time, MISSING when the model did not see the
    tool. Once the task clock is set, the emulator's frames are put on the simulated Vega's sample times
    (``VegaDevice.align_frames``), so each frame carries the pose of its own capture time, as a real Vega's does.

Stdout gets JSON lines: a ``start`` record (t0 of the task on the host clock, speed, ports), region changes
of the true target path, a ``vega_bump`` record when the run has one (its time, size, host time), and an ``end``
record — enough to align ground truth with recorded data.
"""

from __future__ import annotations

import json
import socket
import sys
import threading
import time
from collections.abc import Callable

import numpy as np

from fullperc_common.share import share_path
from fullperc_drivers.ndi.rom import EMULATOR_ROM_DIR
from fullperc_drivers.streams import DianaState, OmcBody, OmcFrame, encode_diana, encode_omc
from fullperc_eval.emulators.vega_device import ToolPose
from fullperc_eval.emulators.vega_server import VegaEmulator
from fullperc_fusion.margin.layout import Frustum

from .run import SimRun
from .scene import OMC_BODIES

_REGION = {1: "BVV", 2: "GVV", 3: "PVV"}
_ALIGN_TOLERANCE_NS = 1_000   # rounding between the host and the simulation clocks (a few ns); frames are >= 1 ms apart


def _roms(extra: dict[str, str] | None = None) -> dict[str, bytes]:
    """The NDI tool definitions the driver uploads (fullperc_drivers/config/emulator_roms/{tool,base}.rom, and
    ``extra``: tool name -> ROM file there, the extra targets'); missing ones left out."""
    out: dict[str, bytes] = {}
    for name, file in {"tool": "tool.rom", "base": "base.rom", **(extra or {})}.items():
        try:
            out[name] = share_path("fullperc_drivers", "config", EMULATOR_ROM_DIR, file).read_bytes()
        except FileNotFoundError:
            pass
    return out


class LiveServer:
    """Plays a :class:`SimRun` out on the device streams in (scaled) real time.

    ``frustum``: the Vega emulator's measurement volume (the layout's, in the ``ots`` frame); None: the emulator's
    default pyramid.
    """

    def __init__(self, run: SimRun, speed: float = 1.0, omc_addr: tuple[str, int] = ("127.0.0.1", 3883),
                 diana_addr: tuple[str, int] = ("127.0.0.1", 3884), vega_port: int | None = 8765,
                 vega_host: str = "127.0.0.1", device_clock_offset_ns: int = 0, frustum: Frustum | None = None,
                 log: Callable[[dict], None] | None = None) -> None:
        if not speed > 0:
            raise ValueError(f"speed must be > 0, got {speed}")
        self.run = run
        self.speed = float(speed)
        self.omc_addr = omc_addr
        self.diana_addr = diana_addr
        self.vega_port = vega_port
        self.vega_host = vega_host
        self.offset = int(device_clock_offset_ns)
        self.frustum = frustum
        self.log = log or (lambda rec: print(json.dumps(rec), flush=True))
        self.t0_host_ns = 0
        self.vega = None
        self._stop = threading.Event()
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sent = {"omc": 0, "diana": 0}
        self._ids = {n: i + 1 for i, n in enumerate(OMC_BODIES)}
        # the extra targets (sim.targets: the hand-held instrument, the patient reference): their ids and NDI tools
        extra = run.info.get("extra_targets") or {}
        self._ids.update({n: int(e["omc_id"]) for n, e in extra.items()})
        self._extra_roms = {n: str(e["rom_file"]) for n, e in extra.items()}

    # ------------------------------------------------------------------------------------------ clock
    def host_ns(self, t_sim_ns) -> int:
        return self.t0_host_ns + int(round(int(t_sim_ns) / self.speed))

    def sim_ns(self, t_host_ns: int) -> int:
        return int(round((t_host_ns - self.t0_host_ns) * self.speed))

    # ------------------------------------------------------------------------------------------- vega
    def _vega_source(self, t_host_ns: int) -> dict:
        if not self.t0_host_ns:  # the task clock has not started: nothing in view yet
            return {}
        ots = self.run.ots
        # the latest sample at or before the frame time; with the frames aligned they coincide, up to a few ns of
        # rounding between the two clocks, which must not select the sample a whole period earlier
        k = int(np.searchsorted(ots.t_ns, self.sim_ns(t_host_ns) + _ALIGN_TOLERANCE_NS, side="right")) - 1
        if k < 0:
            return {}
        out: dict = {}
        for name, s in ots.tools.items():
            if s.visible[k]:
                out[name] = ToolPose(position_mm=s.position[k] * 1000.0, quat_xyzw=s.quat_xyzw[k].copy(),
                                     error_mm=float(s.rms[k] * 1000.0))
            else:
                out[name] = None
        return out

    def _start_vega(self) -> None:
        if self.vega_port is None:
            return
        kw = {}
        if self.frustum is not None:
            kw["frustum"] = self.frustum
        self.vega = VegaEmulator(pose_source=self._vega_source, tools=_roms(self._extra_roms),
                                 frame_rate_hz=float(self.run.info.get("ots_rate_hz", 60.0)) * self.speed,
                                 host=self.vega_host, port=int(self.vega_port), **kw).start()
        self._align_vega()

    def _align_vega(self) -> None:
        """Put the emulator's frames on the simulated Vega's sample times of this task's clock (when it is set)."""
        if self.vega is not None and self.t0_host_ns and len(self.run.ots.t_ns):
            self.vega.device.align_frames(self.host_ns(self.run.ots.t_ns[0]))

    # ----------------------------------------------------------------------------------------- frames
    def omc_datagram(self, i: int) -> bytes:
        o = self.run.omc
        bodies = []
        for name, s in o.bodies.items():
            ok = bool(s.tracked[i])
            bodies.append(OmcBody(id=self._ids.get(name, 0), name=name,
                                  position_mm=s.position[i] * 1000.0 if ok else np.zeros(3),
                                  quat_xyzw=s.quat_xyzw[i] if ok else np.array([0.0, 0.0, 0.0, 1.0]),
                                  mean_error_mm=float(s.mean_error[i] * 1000.0) if ok else 0.0, tracked=ok,
                                  markers=int(s.markers_used[i])))
        return encode_omc(OmcFrame(frame_number=int(o.frame_number[i]),
                                   timestamp_ns=self.host_ns(o.t_ns[i]) + self.offset,
                                   latency_s=o.latency_s / self.speed, bodies=bodies))

    def diana_datagram(self, i: int) -> bytes:
        d = self.run.diana
        return encode_diana(DianaState(sequence=i, timestamp_ns=self.host_ns(d.t_ns[i]) + self.offset,
                                       q=d.q[i], dq=d.dq[i] * self.speed))

    def _events(self) -> list[tuple[int, int, int]]:
        """(send time [sim ns], kind, index) sorted; kind 0 = OMC, 1 = Diana, 2 = region change, 3 = Vega bump."""
        o, d = self.run.omc, self.run.diana
        lat = int(round(o.latency_s * 1e9))
        ev = [(int(t) + lat, 0, i) for i, t in enumerate(o.t_ns)]
        ev += [(int(t), 1, i) for i, t in enumerate(d.t_ns)]
        reg = self.run.truth.region
        ev += [(int(self.run.truth.t_ns[i]), 2, i) for i in range(len(reg)) if i == 0 or reg[i] != reg[i - 1]]
        bump = self.run.info.get("vega_bump")
        if bump:
            ev.append((int(round(bump["at_s"] * 1e9)), 3, 0))
        ev.sort()
        return ev

    # ------------------------------------------------------------------------------------------- run
    def serve(self, start_delay_s: float = 0.5, loops: int = 1, wait_for_tracking_s: float = 0.0) -> None:
        """Play the run ``loops`` times (0 = until :meth:`stop`); blocks.

        With ``wait_for_tracking_s`` > 0 the first task waits (at most that long) until a client has put the
        Vega emulator into tracking mode before ``start_delay_s`` begins: a recording or a fusion node that
        starts with the devices then sees the task from its first sample, however long the driver took to
        come up on a loaded machine.
        """
        if self.vega is None:
            self._start_vega()
        if wait_for_tracking_s > 0 and self.vega is not None:
            end = time.monotonic() + wait_for_tracking_s
            while not self.vega.device.tracking and time.monotonic() < end:
                if self._stop.wait(0.02):
                    break
            self.log({"event": "tracking" if self.vega.device.tracking else "tracking_timeout",
                      "waited_s": round(wait_for_tracking_s - max(0.0, end - time.monotonic()), 3)})
        try:
            n = 0
            while not self._stop.is_set() and (loops == 0 or n < loops):
                self._serve_once(start_delay_s)
                n += 1
        finally:
            self.close()

    def _serve_once(self, start_delay_s: float) -> None:
        self.t0_host_ns = time.time_ns() + int(start_delay_s * 1e9)
        self._align_vega()
        self.log({"event": "start", "task": self.run.task, "seed": self.run.seed, "t0_host_ns": self.t0_host_ns,
                  "speed": self.speed, "duration_s": self.run.duration_s, "omc": list(self.omc_addr),
                  "diana": list(self.diana_addr), "vega_port": None if self.vega is None else self.vega.port,
                  "device_clock_offset_ns": self.offset})
        for t_send, kind, i in self._events():
            if self._stop.is_set():
                return
            wait = (self.host_ns(t_send) - time.time_ns()) / 1e9
            if wait > 0 and self._stop.wait(wait):
                return
            try:
                if kind == 0:
                    self._sock.sendto(self.omc_datagram(i), self.omc_addr)
                    self.sent["omc"] += 1
                elif kind == 1:
                    self._sock.sendto(self.diana_datagram(i), self.diana_addr)
                    self.sent["diana"] += 1
                elif kind == 3:
                    b = self.run.info["vega_bump"]
                    self.log({"event": "vega_bump", **b, "t_host_ns": self.host_ns(t_send)})
                else:
                    r = int(self.run.truth.region[i])
                    self.log({"event": "region", "t_s": round(self.run.truth.t_ns[i] / 1e9, 3),
                              "t_host_ns": self.host_ns(self.run.truth.t_ns[i]), "region": _REGION.get(r, "UNKNOWN")})
            except OSError as e:  # nobody listening on a UDP port is not fatal; report and go on
                print(f"sim: send failed: {e}", file=sys.stderr, flush=True)
        self.log({"event": "end", "task": self.run.task, "sent": dict(self.sent)})

    def stop(self) -> None:
        self._stop.set()

    def close(self) -> None:
        if self.vega is not None:
            self.vega.stop()
            self.vega = None
        self._sock.close()
