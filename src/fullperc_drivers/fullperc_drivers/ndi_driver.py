"""``ndi_driver`` node: NDI Polaris (Vega over TCP, Spectra/Vicra over serial) -> ROS topics.

A thin node around the ROS-free :class:`fullperc_drivers.ndi.driver.NdiDriver`: the driver thread only puts
:class:`FrameResult` and :class:`DriverEvent` into a :class:`~fullperc_drivers.handoff.Handoff`; the executor
drains it, publishes, logs and feeds the health ladder (:class:`fullperc_common.health.Health`). For every
device frame and configured tool it publishes ``<topic_prefix>/<tool>/quality`` (fullperc_msgs/TrackingQuality)
and, only when the tool is tracked, ``<topic_prefix>/<tool>/pose`` (PoseStamped, frame ``ots``, metres,
quaternion x y z w), and then ``<topic_prefix>/bodies`` (fullperc_msgs/TrackedBodies): every tool of that frame
in one message, with the stamp, pose and quality fields of its per-tool messages, in the same order. ``header.stamp``
is the frame's acquisition time: the device frame number mapped to the host clock (see ``FrameClock``), minus
``device_latency_s``. A missing tool gets ``visible: false`` and no pose — never a stale or NaN one (all zeros in
``bodies``).

Health (``/diagnostics``, status ``ndi_driver: link``; the rule is in :mod:`fullperc_common.health`): ERROR when
no new frame arrived for ``health.stale_after_s`` (not connected / reconnecting / frame number frozen), or when
every pose was refused; WARN per tool not seen or refused for that long, per tool the device refused (its ROM),
and for repeated reconnects; OK only while every enabled tool's poses flow. The console gets the reason the
device cannot be reached and every tool the device refuses, throttled. Its values carry the driver's counters,
among them ``skipped_frames``: device frames never read (BX answers the newest frame, so a late poll skips some),
which a consumer counting ``frame_number`` gaps of the quality topic cannot tell from messages lost on the way.

Parameters (defaults in brackets; units and comments in ``config/ndi_vega.yaml``): transport [tcp] | serial;
host [127.0.0.1]; port [8765]; serial_device [/dev/ttyUSB0]; baud [115200]; tools [tool, base]; tool_roms
[emulator_roms/tool.rom, emulator_roms/base.rom]: the synthetic ROMs of the Vega emulator -- a real tracker needs
its tool maker's ROMs, and the node WARNs when it uploads an emulator ROM to anything but a TCP device on this
host (relative paths are looked up in share/fullperc_drivers/config; every file is checked at start: exit 2 naming
a file that is not an NDI tool definition); tool_priorities [] (S/D/B per tool, default D); mode [BX] | TX;
reply_option [1] (0x0001; 0x0801 also reports out-of-volume tools); rate_hz [60.0];
frame_rate_hz [60.0]; device_latency_s [0.0]; volume [-1: keep]; read_timeout_s [0.5]; frame_id [ots];
topic_prefix [ots: relative, /ots in the default namespace]; qos_depth [2000]; health.stale_after_s [2.0];
health.reconnect_window_s [10.0]; health.max_reconnects [3]. Every parameter is read-only (:mod:`.node_common`).
"""

from __future__ import annotations

import logging
import os
import sys
from pathlib import Path

from geometry_msgs.msg import Pose, PoseStamped
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy

from fullperc_common import ros_conv
from fullperc_common.diagnostics import Diagnostics
from fullperc_common.health import Health
from fullperc_common.node_main import run_node
from fullperc_common.params import ParameterError, declare_fixed
from fullperc_common.share import share_path
from fullperc_common.subscribers import SubscriberLog
from fullperc_msgs.msg import TrackedBodies, TrackingQuality

from .handoff import ExecutorWake, Handoff
from .ndi.driver import DriverConfig, DriverEvent, FrameResult, NdiDriver, ToolConfig
from .ndi.rom import EMULATOR_ROM_DIR, RomFileError
from .node_common import HEALTH_PERIOD_S, ConsoleThrottle, HealthReport, declare_health, tracked_body

FATAL = (ParameterError, RomFileError)


def resolve_rom(tool: str, path: str) -> Path:
    """An absolute or existing path as given; otherwise the file of that name in fullperc_drivers' config/."""
    p = Path(os.path.expanduser(path))
    if p.is_absolute() or p.exists():
        return p
    try:
        return share_path("fullperc_drivers", "config", path)
    except FileNotFoundError as e:
        raise ParameterError(f"parameter 'tool_roms': ROM file for tool '{tool}' not found: {e}") from e


def is_emulator_rom(path: Path) -> bool:
    """True for a file in fullperc_drivers' ``config/emulator_roms``: the synthetic ROMs written for the Vega
    emulator, which a real tracker must never be given (the node says so when it uploads one)."""
    return path.resolve().parent.name == EMULATOR_ROM_DIR and path.resolve().parent.parent.name == "config"


def is_loopback(host: str) -> bool:
    """``host`` names this machine (where the emulator runs; a real Vega is never on the loopback)."""
    return host in ("localhost", "::1") or host.startswith("127.")


def tool_topic(prefix: str, tool: str, what: str) -> str:
    """``<prefix>/<tool>/<what>``: relative (resolved in the node's namespace) unless ``prefix`` starts with ``/``.

    An empty prefix gives the relative ``<tool>/<what>`` and ``/`` the absolute ``/<tool>/<what>``.
    """
    return prefix_topic(prefix, f"{tool}/{what}")


def prefix_topic(prefix: str, name: str) -> str:
    """``<prefix>/<name>`` by the rules of :func:`tool_topic` (``bodies``: ``ots/bodies``, ``/bodies`` for ``/``)."""
    head = prefix.rstrip("/")
    if head:
        return f"{head}/{name}"
    return f"/{name}" if prefix.startswith("/") else name


class NdiDriverNode(Node):
    def __init__(self) -> None:
        super().__init__("ndi_driver")
        transport = declare_fixed(self, "transport", "tcp", lambda v: v in ("tcp", "serial"), "tcp or serial")
        host = declare_fixed(self, "host", "127.0.0.1")
        port = declare_fixed(self, "port", 8765, lambda v: 0 < v < 65536, "TCP port")
        serial_device = declare_fixed(self, "serial_device", "/dev/ttyUSB0")
        baud = declare_fixed(self, "baud", 115200, lambda v: v in (9600, 14400, 19200, 38400, 57600, 115200,
                                                                     230400, 921600, 1228739), "a COMM rate")
        names = list(declare_fixed(self, "tools", ["tool", "base"], lambda v: len(v) > 0, "at least one tool"))
        roms = list(declare_fixed(self, "tool_roms", [f"{EMULATOR_ROM_DIR}/tool.rom", f"{EMULATOR_ROM_DIR}/base.rom"]))
        prios = list(declare_fixed(self, "tool_priorities", [""]))
        mode = declare_fixed(self, "mode", "BX", lambda v: v in ("BX", "TX"), "BX or TX")
        option = declare_fixed(self, "reply_option", 1, lambda v: v in (0x0001, 0x0801, 0x0009, 0x0809),
                               "0x0001, 0x0801, 0x0009 or 0x0809")
        rate = declare_fixed(self, "rate_hz", 60.0, lambda v: v >= 0, ">= 0")
        frame_rate = declare_fixed(self, "frame_rate_hz", 60.0, lambda v: v > 0, "> 0")
        latency = declare_fixed(self, "device_latency_s", 0.0, lambda v: 0 <= v < 1, "0 <= latency < 1 s")
        volume = declare_fixed(self, "volume", -1)
        read_timeout = declare_fixed(self, "read_timeout_s", 0.5, lambda v: v > 0, "> 0")
        self.frame_id = declare_fixed(self, "frame_id", "ots")
        prefix = declare_fixed(self, "topic_prefix", "ots")
        depth = declare_fixed(self, "qos_depth", 2000, lambda v: v > 0, "> 0")   # config/ndi_vega.yaml: why
        health_cfg = declare_health(self)
        if len(roms) != len(names):
            raise ParameterError(f"parameter 'tool_roms' needs one ROM per tool ({len(names)}), got {len(roms)}")
        prios = [p for p in prios if p]
        if prios and len(prios) != len(names):
            raise ParameterError("parameter 'tool_priorities' must be empty or have one entry per tool")
        if any(p not in ("S", "D", "B") for p in prios):
            raise ParameterError(f"parameter 'tool_priorities' = {prios!r} is invalid: S, D or B per tool")
        tools = []
        for i, (n, r) in enumerate(zip(names, roms, strict=True)):
            path = resolve_rom(n, r)
            if not path.is_file():
                raise ParameterError(f"parameter 'tool_roms': ROM file for tool '{n}' not found: {path}")
            tools.append(ToolConfig.from_file(n, path, prios[i] if prios else "D"))  # RomFileError: fatal
        self.cfg = DriverConfig(transport=transport, host=host, port=port, serial_device=serial_device,
                                baud=baud, tools=tools, mode=mode, reply_option=option, rate_hz=rate,
                                frame_rate_hz=frame_rate, device_latency_s=latency,
                                volume=None if volume < 0 else volume, read_timeout_s=read_timeout)
        try:
            self.cfg.validate()
        except ValueError as e:
            raise ParameterError(str(e)) from e
        self.roms = {t.name: t.source for t in tools}

        qos = QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE)
        self.pose_pubs = {n: self.create_publisher(PoseStamped, tool_topic(prefix, n, "pose"), qos) for n in names}
        self.qual_pubs = {n: self.create_publisher(TrackingQuality, tool_topic(prefix, n, "quality"), qos)
                          for n in names}
        self.bodies_pub = self.create_publisher(TrackedBodies, prefix_topic(prefix, "bodies"), qos)
        self.where = f"{host}:{port}" if transport == "tcp" else f"{serial_device}@{baud}"
        self.diag = Diagnostics(self, hardware_id=f"ndi {self.where}")
        self.health = Health(names, health_cfg, item_kind="tool", output="pose", frame="frame",
                             ok_text=f"tracking {len(names)} tool{'s' if len(names) != 1 else ''}")
        self.health.link_down("connecting")
        self.console = ConsoleThrottle(self.get_logger, period_s=5.0)
        self.report = HealthReport(self.diag, "link", self.health, self.console)
        self.refused = 0
        self.published = 0
        self._dups_seen = 0
        # The driver thread only hands items over; publishing, logging and health run on the executor.
        self._wake = ExecutorWake(self, self._drain)
        self.handoff: Handoff[FrameResult | DriverEvent] = Handoff(maxlen=1024, notify=self._wake)
        # The driver's own log lines would reach stderr through Python's last-resort handler; the node says
        # everything the operator needs (throttled) through its ROS logger instead.
        logging.getLogger("fullperc.ndi").addHandler(logging.NullHandler())
        self.driver = NdiDriver(self.cfg, on_frame=self.handoff.put, on_event=self.handoff.put)
        self._health_timer = self.create_timer(HEALTH_PERIOD_S, self._update_diag)
        self.subscribers = SubscriberLog(self, lambda: {**self.pose_pubs, "": self.bodies_pub})   # bodies too
        self._update_diag()
        self.driver.start()
        self.get_logger().info(f"NDI driver: {transport} {self.where}, tools {names}, {mode} {option:04X}")
        if emulator := [t.name for t in tools if is_emulator_rom(Path(t.source))]:
            log = self.get_logger().info if transport == "tcp" and is_loopback(host) else self.get_logger().warning
            log(f"tools {emulator}: fullperc's synthetic emulator ROMs ({EMULATOR_ROM_DIR}/); a real tracker needs "
                "its tool maker's ROM files in tool_roms (docs/hardware.md)")

    # ---- executor side ------------------------------------------------------------------------------
    def _drain(self) -> None:
        for item in self.handoff.drain():
            if isinstance(item, FrameResult):
                self._publish(item)
            else:
                self._event(item)

    def _event(self, ev: DriverEvent) -> None:
        if ev.kind == "tool_refused":
            rom = self.roms.get(ev.tool, "")
            self.health.item_failed(ev.tool, f"{ev.detail}; ROM {rom}" if rom else ev.detail)
            self.console(f"refused:{ev.tool}", f"tool '{ev.tool}' (ROM {rom}) {ev.detail}; "
                                               f"the other tools keep tracking")
            return
        if ev.state == "tracking":
            self.health.link_up()
            for name in self.roms:
                if name in ev.tools:
                    self.health.item_ok(name)
            self.console("tracking", f"tracking at {self.where}: {ev.detail}", level="info")
        elif ev.state == "reconnecting":
            self.health.link_down(ev.detail)
            if ev.link_lost:
                text = f"NDI link to {self.where} lost: {ev.detail}; reconnecting"
            else:
                text = f"cannot bring up the NDI device at {self.where}: {ev.detail}; retrying"
            self.console("link", text)

    def _publish(self, fr: FrameResult) -> None:
        self.health.frame(fr.frame_number)
        stamp = ros_conv.ns_to_stamp(fr.stamp_ns)
        latency = max(0.0, (fr.recv_ns - fr.stamp_ns) / 1e9)
        out = TrackedBodies(latency=latency)  # the frame in one message: each tool as its quality (and pose) says
        out.header.stamp = stamp
        out.header.frame_id = self.frame_id
        for name, s in fr.tools.items():
            q = TrackingQuality()
            q.header.stamp = stamp
            q.header.frame_id = self.frame_id
            q.body = name
            q.frame_number = s.frame_number & 0xFFFFFFFF
            q.port_status = s.port_status & 0xFFFFFFFF
            q.latency = latency
            q.markers_used = s.markers
            q.fit_error = -1.0
            visible = s.visible
            pose = Pose()  # all zeros unless visible
            if visible:
                try:
                    msg = ros_conv.pose_stamped(fr.stamp_ns, self.frame_id, s.position_m, s.quat_xyzw)
                except ValueError as e:
                    self.refused += 1
                    visible = False
                    self.health.refused(name, str(e))
                else:
                    self.pose_pubs[name].publish(msg)
                    pose = msg.pose
                    self.published += 1
                    self.health.good(name)
                    q.fit_error = float(s.fit_error_m)
            elif s.refused:
                self.refused += 1
                self.health.refused(name, s.refused)
            q.visible = visible
            self.qual_pubs[name].publish(q)
            out.bodies.append(tracked_body(q, pose))
        if out.bodies:
            self.bodies_pub.publish(out)

    def _update_diag(self) -> None:
        self._wake.catch_up()   # what came before the node was spinning (ExecutorWake)
        d = self.driver
        dups = d.counters.duplicate_frames
        if dups > self._dups_seen:
            self.health.repeated(dups - self._dups_seen, d.last_frame_number)
        self._dups_seen = dups
        durations = [(b - a) / 1e9 for a, b in d.reconnect_log]
        values = {"state": d.state, "firmware": d.firmware, "last_error": d.last_error,
                  "poses_published": self.published, "poses_refused": self.refused,
                  "frame_clock_resets": d.clock.resets,
                  "reconnect_durations_s": " ".join(f"{x:.3f}" for x in durations),
                  "max_reconnect_s": f"{max(durations):.3f}" if durations else "",
                  "handles": " ".join(f"{n}={h:02X}" for n, h in d.handles.items()),
                  "refused_tools": " ".join(sorted(d.refused)), "queue_overflow": self.handoff.overflow}
        values.update(d.counters.as_dict())
        self.report.publish(values)

    def close(self) -> None:
        """Stop the driver thread (TSTOP, close the link, join) before the node goes: no callback runs after."""
        self.handoff.notify = None
        self._health_timer.cancel()
        self.driver.stop()


def main(args: list[str] | None = None) -> int:
    return run_node(NdiDriverNode, "ndi_driver", FATAL, args, params_file=("fullperc_drivers", "ndi_vega.yaml"))


if __name__ == "__main__":
    sys.exit(main())
