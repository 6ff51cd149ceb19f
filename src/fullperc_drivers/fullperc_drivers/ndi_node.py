"""``ndi_driver`` node: NDI Polaris (Vega over TCP, Spectra/Vicra over serial) -> ROS topics.

A thin wrapper around :class:`fullperc_drivers.ndi.driver.NdiDriver`. For every device frame and
configured tool it publishes ``<topic_prefix>/<tool>/quality`` (fullperc_msgs/TrackingQuality) and,
only when the tool is tracked, ``<topic_prefix>/<tool>/pose`` (PoseStamped, frame ``ots``,
metres, quaternion x y z w). ``header.stamp`` is the frame's acquisition time: the device frame
number mapped to the host clock (see ``FrameClock``), minus ``device_latency_s``. A missing tool
gets ``visible: false`` and no pose — never a stale or NaN one. ``/diagnostics`` carries the link
state, firmware, error counters and the reconnect durations.

Parameters (defaults in brackets): transport [tcp] | serial; host [127.0.0.1]; port [8765];
serial_device [/dev/ttyUSB0]; baud [115200]; tools [tool, base]; tool_roms [tool.rom, base.rom]
(relative paths are looked up in share/fullperc_drivers/config); tool_priorities [] (S/D/B per tool,
default D); mode [BX] | TX; reply_option [1] (0x0001; 0x0801 also reports out-of-volume tools);
rate_hz [60.0]; frame_rate_hz [60.0]; device_latency_s [0.0]; volume [-1: keep]; read_timeout_s
[0.5]; frame_id [ots]; topic_prefix [/ots]; qos_depth [50].
"""

from __future__ import annotations

import os
import sys
import threading
import time
from pathlib import Path

import rclpy
import rclpy.executors
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy

from fullperc_common import ros_conv
from fullperc_common.diagnostics import ERROR, OK, WARN, Diagnostics
from fullperc_common.params import ParameterError, declare
from fullperc_common.subscribers import SubscriberLog
from fullperc_msgs.msg import TrackingQuality

from .ndi.driver import DriverConfig, FrameResult, NdiDriver, ToolConfig


def _level(level) -> int:
    """diagnostics.OK/WARN/ERROR are bytes in Jazzy's msg constants, but Diagnostics.set wants an int."""
    return level[0] if isinstance(level, bytes) else int(level)


def config_dir() -> Path:
    try:
        from ament_index_python.packages import get_package_share_directory

        return Path(get_package_share_directory("fullperc_drivers")) / "config"
    except Exception:  # noqa: BLE001 - not installed: source tree
        return Path(__file__).resolve().parents[1] / "config"


def resolve_rom(path: str) -> Path:
    p = Path(os.path.expanduser(path))
    if p.is_absolute() or p.exists():
        return p
    return config_dir() / p


class NdiNode(Node):
    def __init__(self) -> None:
        super().__init__("ndi_driver")
        transport = declare(self, "transport", "tcp", lambda v: v in ("tcp", "serial"), "tcp or serial")
        host = declare(self, "host", "127.0.0.1")
        port = declare(self, "port", 8765, lambda v: 0 < v < 65536, "TCP port")
        serial_device = declare(self, "serial_device", "/dev/ttyUSB0")
        baud = declare(self, "baud", 115200, lambda v: v in (9600, 14400, 19200, 38400, 57600, 115200,
                                                               230400, 921600, 1228739), "a COMM rate")
        names = list(declare(self, "tools", ["tool", "base"], lambda v: len(v) > 0, "at least one tool"))
        roms = list(declare(self, "tool_roms", ["tool.rom", "base.rom"]))
        prios = list(declare(self, "tool_priorities", [""]))
        mode = declare(self, "mode", "BX", lambda v: v in ("BX", "TX"), "BX or TX")
        option = declare(self, "reply_option", 1, lambda v: v in (0x0001, 0x0801, 0x0009, 0x0809),
                         "0x0001, 0x0801, 0x0009 or 0x0809")
        rate = declare(self, "rate_hz", 60.0, lambda v: v >= 0, ">= 0")
        frame_rate = declare(self, "frame_rate_hz", 60.0, lambda v: v > 0, "> 0")
        latency = declare(self, "device_latency_s", 0.0, lambda v: 0 <= v < 1, "0 <= latency < 1 s")
        volume = declare(self, "volume", -1)
        read_timeout = declare(self, "read_timeout_s", 0.5, lambda v: v > 0, "> 0")
        self.frame_id = declare(self, "frame_id", "ots")
        prefix = declare(self, "topic_prefix", "/ots").rstrip("/")
        depth = declare(self, "qos_depth", 50, lambda v: v > 0, "> 0")
        if len(roms) != len(names):
            raise ParameterError(f"parameter 'tool_roms' needs one ROM per tool ({len(names)}), got {len(roms)}")
        prios = [p for p in prios if p]
        if prios and len(prios) != len(names):
            raise ParameterError("parameter 'tool_priorities' must be empty or have one entry per tool")
        tools = []
        for i, (n, r) in enumerate(zip(names, roms, strict=True)):
            path = resolve_rom(r)
            if not path.is_file():
                raise ParameterError(f"parameter 'tool_roms': ROM file for tool '{n}' not found: {path}")
            tools.append(ToolConfig.from_file(n, path, prios[i] if prios else "D"))
        self.cfg = DriverConfig(transport=transport, host=host, port=port, serial_device=serial_device,
                                baud=baud, tools=tools, mode=mode, reply_option=option, rate_hz=rate,
                                frame_rate_hz=frame_rate, device_latency_s=latency,
                                volume=None if volume < 0 else volume, read_timeout_s=read_timeout)
        try:
            self.cfg.validate()
        except ValueError as e:
            raise ParameterError(str(e)) from e

        qos = QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE)
        self.pose_pubs = {n: self.create_publisher(PoseStamped, f"{prefix}/{n}/pose", qos) for n in names}
        self.qual_pubs = {n: self.create_publisher(TrackingQuality, f"{prefix}/{n}/quality", qos) for n in names}
        where = f"{host}:{port}" if transport == "tcp" else f"{serial_device}@{baud}"
        self.diag = Diagnostics(self, hardware_id=f"ndi {where}")
        self.refused = 0
        self.published = 0
        self._not_tracking_since = time.monotonic()
        self.driver = NdiDriver(self.cfg, on_frame=self._on_frame)
        self.create_timer(0.5, self._update_diag)
        self.subscribers = SubscriberLog(self, lambda: self.pose_pubs)
        self._update_diag()
        self.driver.start()
        self.get_logger().info(f"NDI driver: {transport} {where}, tools {names}, {mode} {option:04X}")

    def _on_frame(self, fr: FrameResult) -> None:
        stamp = ros_conv.ns_to_stamp(fr.stamp_ns)
        latency = max(0.0, (fr.recv_ns - fr.stamp_ns) / 1e9)
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
            if visible:
                try:
                    msg = ros_conv.pose_stamped(fr.stamp_ns, self.frame_id, s.position_m, s.quat_xyzw)
                except ValueError:
                    self.refused += 1
                    visible = False
                else:
                    self.pose_pubs[name].publish(msg)
                    self.published += 1
                    q.fit_error = float(s.fit_error_m)
            q.visible = visible
            self.qual_pubs[name].publish(q)

    def _update_diag(self) -> None:
        d = self.driver
        now = time.monotonic()
        if d.state == "tracking":
            self._not_tracking_since = now
            level, msg = OK, f"tracking ({d.state_detail})"
        elif now - self._not_tracking_since > 5.0:
            level, msg = ERROR, f"{d.state}: {d.last_error or d.state_detail}"
        else:
            level, msg = WARN, f"{d.state}: {d.last_error or d.state_detail}"
        durations = [(b - a) / 1e9 for a, b in d.reconnect_log]
        values = {"state": d.state, "firmware": d.firmware, "last_error": d.last_error,
                  "poses_published": self.published, "poses_refused": self.refused,
                  "frame_clock_resets": d.clock.resets,
                  "reconnect_durations_s": " ".join(f"{x:.3f}" for x in durations),
                  "max_reconnect_s": f"{max(durations):.3f}" if durations else "",
                  "handles": " ".join(f"{n}={h:02X}" for n, h in d.handles.items())}
        values.update(d.counters.as_dict())
        self.diag.set("link", _level(level), msg, values)


def main(args: list[str] | None = None) -> int:
    rclpy.init(args=args)
    node = None
    try:
        node = NdiNode()
        rclpy.spin(node)
    except ParameterError as e:
        print(f"ndi_driver: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        pass
    except rclpy.executors.ExternalShutdownException:
        pass
    finally:
        if node is not None:
            t = threading.Thread(target=node.driver.stop, daemon=True)
            t.start()
            t.join(5.0)
            node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
