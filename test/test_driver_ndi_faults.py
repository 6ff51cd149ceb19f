"""``ndi_driver`` under injected faults: the installed executable against the installed ``vega_emulator``.

Between the two sits :class:`FaultProxy`, a small TCP proxy in this process that forwards the Combined API
command by command and can: freeze BX replies (the same reply, same frame number, over and over), make every BX
body garbage behind a valid CRC, put NaN into every transform, slow every reply down, and answer ``ERROR0D`` to
the PINIT of one tool's ROM (what a Vega says to a ROM it refuses). The tests check what an operator sees: the
``/diagnostics`` level and message (leaving OK, saying why, coming back to OK only when poses flow), the console
lines, the exit status -- with liveness bounds only (``wait_for``), never a wall-clock assertion. Without faults,
``/ots/bodies`` is checked against the per-tool topics frame by frame (a tool the emulator hides included).
"""

from __future__ import annotations

import re
import signal
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from fullperc_common.diagnostics import as_level
from fullperc_common.ports import free_port
from fullperc_common.testing import SpunNode, installed_exe, side_by_side_fixture, wait_for, wait_for_first_line
from fullperc_drivers.ndi import replies as R
from fullperc_drivers.ndi.protocol import FrameReader, decode_command, encode_ascii_reply, encode_binary_reply

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "src" / "fullperc_drivers" / "config" / "emulator_roms"   # synthetic
OK, WARN, ERROR = 0, 1, 2
GARBAGE_STATUSES = 3  # link statuses (1 s period, and at level changes) watched during garbage: none may be OK


class FaultProxy:
    """driver <-> proxy <-> emulator, one command and one reply at a time; ``mode`` applies to BX replies."""

    def __init__(self, upstream_port: int, refuse_rom: bytes | None = None, delay_s: float = 0.0) -> None:
        self.upstream = ("127.0.0.1", upstream_port)
        self.refuse_rom = refuse_rom
        self.delay_s = delay_s
        self.mode = "pass"  # pass | freeze | garbage | nan
        self.refused_pinit = 0
        self.commands: list[str] = []  # every command forwarded or answered, by name, in order
        self._last_bx: bytes | None = None
        self._srv = socket.create_server(("127.0.0.1", 0))
        self._srv.settimeout(0.2)
        self.port = self._srv.getsockname()[1]
        self._stop = threading.Event()
        self._threads = [threading.Thread(target=self._accept, daemon=True)]
        self._threads[0].start()

    def close(self) -> None:
        self._stop.set()
        self._srv.close()
        for t in self._threads:
            t.join(2.0)

    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._srv.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            t = threading.Thread(target=self._serve, args=(conn,), daemon=True)
            t.start()
            self._threads.append(t)

    def _serve(self, conn: socket.socket) -> None:
        up = socket.create_connection(self.upstream, timeout=5.0)
        conn.settimeout(0.2)
        reader = FrameReader()
        roms: dict[str, bytearray] = {}
        buf = bytearray()
        try:
            while not self._stop.is_set():
                try:
                    data = conn.recv(65536)
                except TimeoutError:
                    continue
                if not data:
                    return
                buf += data
                while b"\r" in buf:
                    i = buf.index(b"\r")
                    line, buf = bytes(buf[:i + 1]), buf[i + 1:]
                    reply = self._handle(line, up, reader, roms)
                    if self.delay_s:
                        time.sleep(self.delay_s)
                    conn.sendall(reply)
        except OSError:
            return
        finally:
            conn.close()
            up.close()

    def _forward(self, line: bytes, up: socket.socket, reader: FrameReader):
        up.sendall(line)
        while True:
            rep = reader.pop()
            if rep is not None:
                return rep
            chunk = up.recv(65536)
            if not chunk:
                raise OSError("emulator closed the connection")
            reader.feed(chunk)

    def _handle(self, line: bytes, up: socket.socket, reader: FrameReader, roms: dict[str, bytearray]) -> bytes:
        cmd = decode_command(line)
        self.commands.append(cmd.name)
        if cmd.name == "PVWR":  # remember what each handle was given
            h, addr = cmd.params[:2].upper(), int(cmd.params[2:6], 16)
            rom = roms.setdefault(h, bytearray(1024))
            rom[addr:addr + 64] = bytes.fromhex(cmd.params[6:])
        if cmd.name == "PINIT" and self.refuse_rom is not None:
            rom = roms.get(cmd.params[:2].upper())
            if rom is not None and bytes(rom[:len(self.refuse_rom)]) == self.refuse_rom:
                self.refused_pinit += 1
                return encode_ascii_reply("ERROR0D")
        rep = self._forward(line, up, reader)
        if not rep.binary:
            return encode_ascii_reply(rep.data)
        if cmd.name != "BX":
            return encode_binary_reply(rep.data)
        if self.mode == "freeze" and self._last_bx is not None:
            return encode_binary_reply(self._last_bx)
        if self.mode == "garbage":
            return encode_binary_reply(b"\xff" * len(rep.data))
        if self.mode == "nan":
            opt = int(cmd.params or "1", 16)
            data = R.parse_bx(rep.data, opt)
            for t in data.tools:
                if t.q_wxyz is not None:
                    t.q_wxyz = np.full(4, np.nan)
            return encode_binary_reply(R.format_bx(data, opt))
        self._last_bx = rep.data
        return encode_binary_reply(rep.data)


class Listener(SpunNode):
    """This process's view of the driver: poses per tool and the latest ``ndi_driver: link`` status."""

    def __init__(self, context, tools=("tool", "base")) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        super().__init__(context, "ndi_fault_listener")
        self.poses = {t: 0 for t in tools}
        self.history: list[tuple[int, str, dict]] = []
        qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        for t in tools:
            self.node.create_subscription(PoseStamped, f"/ots/{t}/pose", lambda m, t=t: self._pose(t), qos)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._diag, 50)
        self.start()

    def _pose(self, t: str) -> None:
        with self.lock:
            self.poses[t] += 1

    def _diag(self, arr) -> None:
        for st in arr.status:
            if st.name == "ndi_driver: link":
                lvl = as_level(st.level)
                with self.lock:
                    self.history.append((lvl, st.message, {kv.key: kv.value for kv in st.values}))

    def n_poses(self, tool: str) -> int:
        with self.lock:
            return self.poses[tool]

    def n_statuses(self) -> int:
        with self.lock:
            return len(self.history)

    def statuses(self) -> list[tuple[int, str, dict]]:
        with self.lock:
            return list(self.history)

    def status(self) -> tuple[int | None, str, dict]:
        with self.lock:
            return self.history[-1] if self.history else (None, "", {})

    def wait_level(self, level: int, *needles: str, timeout: float = 30.0, what: str = "") -> str:
        def ok():
            lvl, msg, _ = self.status()
            return lvl == level and all(n in msg for n in needles)
        wait_for(ok, timeout=timeout, what=what or f"level {level} with {needles} (last: {self.status()[:2]})")
        return self.status()[1]


def start_emulator(procs, tmp_path, *extra) -> int:
    port_file = tmp_path / "emu_port"
    procs.start([installed_exe("fullperc_eval", "vega_emulator"), "--port", "0", "--port-file", str(port_file),
                 "--tool", f"tool={CONFIG / 'tool.rom'}", "--tool", f"base={CONFIG / 'base.rom'}",
                 "--pose", "tool=25,-40,-1500,0,0,0.6,0.8", "--pose", "base=150,80,-1700", *extra],
                name="vega_emulator")
    wait_for(lambda: port_file.exists() and port_file.read_text().strip(), timeout=30, what="emulator port")
    return int(port_file.read_text())


def start_driver(procs, port: int, *params: str, name: str = "ndi_driver", params_file: Path | None = None):
    args = [installed_exe("fullperc_drivers", "ndi_driver"), "--ros-args"]
    if params_file is not None:
        args += ["--params-file", str(params_file)]
    args += ["-p", f"port:={port}"]
    for p in params:
        args += ["-p", p]
    return procs.start(args, name=name)


def free_tcp_port() -> int:
    return free_port(socket.SOCK_STREAM)


def _health_leaves_ok_on_frozen_nan_and_garbage_replies_and_recovers(procs, tmp_path, rclpy_context):
    proxy = FaultProxy(start_emulator(procs, tmp_path))
    # stale_after_s 1 s (default 2 s): each fault phase lasts until the level left OK, which takes that long
    drv = start_driver(procs, proxy.port, "health.reconnect_window_s:=3.0", "health.stale_after_s:=1.0")
    wait_for_first_line(procs, drv)   # the listener once the driver is up: matched at once (wait_for_first_line)
    lis = Listener(rclpy_context)
    try:
        wait_for(lambda: lis.n_poses("tool") > 30 and lis.n_poses("base") > 30, timeout=40, what="poses")
        assert "tracking 2 tools at" in lis.wait_level(OK, what="OK while poses flow")

        proxy.mode = "freeze"  # same BX reply, same frame number, over and over
        msg = lis.wait_level(ERROR, "frame number frozen", what="ERROR for frozen replies")
        assert "no new frames for" in msg
        n = lis.n_poses("tool")
        proxy.mode = "pass"
        lis.wait_level(OK, what="OK again once poses flow")
        assert lis.n_poses("tool") > n

        proxy.mode = "nan"  # every transform NaN: refused, and the level says so
        msg = lis.wait_level(ERROR, "every pose refused", what="ERROR for refused poses")
        assert "non-finite" in msg or "not a" in msg or "NaN" in msg.lower(), msg
        proxy.mode = "pass"
        lis.wait_level(OK, what="OK after the NaN phase")

        proxy.mode = "garbage"  # every BX body garbage behind a valid CRC: reconnects, never OK
        msg = lis.wait_level(ERROR, "no new frames for", what="ERROR for garbage replies")
        since = lis.n_statuses() - 1  # from that ERROR on
        # it reconnects (or says it is not connected) ...
        wait_for(lambda: int(lis.status()[2].get("reconnects_recent", 0)) >= 1 or "not connected" in lis.status()[1],
                 timeout=40, what=f"a reconnect on garbage replies (last: {lis.status()[:2]})")
        # ... and stays out of OK while the garbage lasts: through GARBAGE_STATUSES more evaluations (a count of the
        # driver's own health periods, not a length of time a busy machine would fill with fewer of them)
        n = lis.n_statuses()
        wait_for(lambda: lis.n_statuses() >= n + GARBAGE_STATUSES, timeout=40,
                 what=f"{GARBAGE_STATUSES} more link statuses during the garbage")
        levels = [(lvl, m) for lvl, m, _ in lis.statuses()[since:]]
        assert all(lvl != OK for lvl, _ in levels), [m for lvl, m in levels if lvl == OK]
        proxy.mode = "pass"
        lis.wait_level(OK, timeout=40, what="OK after the garbage phase")
        assert drv.poll() is None
    finally:
        lis.close()
        proxy.close()
    assert procs.stop(drv) == 0
    log = procs.log(drv)
    assert "Traceback" not in log
    assert "frame number frozen" in log  # the level changes reached the console too


def _a_rom_the_device_refuses_is_named_and_the_other_tool_keeps_tracking(procs, tmp_path, rclpy_context):
    base_rom = CONFIG / "base.rom"
    proxy = FaultProxy(start_emulator(procs, tmp_path), refuse_rom=base_rom.read_bytes())
    drv = start_driver(procs, proxy.port, f"tool_roms:=[{CONFIG / 'tool.rom'}, {base_rom}]")
    wait_for_first_line(procs, drv)
    lis = Listener(rclpy_context)
    try:
        wait_for(lambda: lis.n_poses("tool") > 60, timeout=40, what="poses of the accepted tool")
        msg = lis.wait_level(WARN, "tool 'base'", "refused by the device", what="WARN naming the refused tool")
        assert "ERROR0D" in msg and str(base_rom) in msg
        values = lis.status()[2]
        assert values["link_losses"] == "0" and values["refused_tools"] == "base"  # no reconnect loop
        assert lis.n_poses("base") == 0 and proxy.refused_pinit == 1
    finally:
        lis.close()
        proxy.close()
    log = procs.log(drv)
    line = next((ln for ln in log.splitlines() if "tool 'base'" in ln and "refused" in ln), "")
    assert str(base_rom) in line and "PINIT" in line, log[-2000:]


def _a_garbage_rom_file_stops_the_driver_naming_the_file(procs, tmp_path, content):
    bad = tmp_path / "broken.rom"
    bad.write_bytes(content)
    p = start_driver(procs, free_tcp_port(), f"tool_roms:=[{bad}, emulator_roms/base.rom]")
    wait_for(lambda: p.poll() is not None, timeout=40, what="ndi_driver to exit")
    log = procs.log(p)
    assert p.returncode == 2, log
    lines = [ln for ln in log.splitlines() if str(bad) in ln]
    assert len(lines) == 1 and "rejected" in lines[0] and "tool definition" in lines[0], log
    assert "tool 'tool'" in lines[0]
    assert "Traceback" not in log


LOG_TIME = re.compile(r"^\[(?:WARN|INFO|ERROR)\] \[(\d+\.\d+)\]")


def _refused_lines(log: str) -> list[tuple[float, str]]:
    """(log time [s], line) of the console lines with the TCP reason the driver gives for each failed attempt (not
    the health ladder's level changes), in order."""
    out = []
    for ln in log.splitlines():
        m = LOG_TIME.match(ln)
        if m and "cannot bring up the NDI device at" in ln and "Connection refused" in ln:
            out.append((float(m[1]), ln))
    return out


def _an_unreachable_device_is_explained_on_the_console(procs, tmp_path):
    port = free_tcp_port()  # nothing listens there
    shipped = ROOT / "install/fullperc_drivers/share/fullperc_drivers/config/ndi_vega.yaml"  # also: it parses
    tcp = start_driver(procs, port, name="ndi_tcp", params_file=shipped)
    missing = tmp_path / "no_such_serial_device"
    ser = start_driver(procs, port, "transport:=serial", f"serial_device:={missing}", name="ndi_serial")
    wait_for(lambda: "Connection refused" in procs.log(tcp), timeout=40, what="the TCP reason on the console")
    wait_for(lambda: str(missing) in procs.log(ser) and "cannot open serial port" in procs.log(ser), timeout=40,
             what="the serial reason on the console")
    line = next(ln for ln in procs.log(tcp).splitlines() if "Connection refused" in ln)
    assert f"127.0.0.1:{port}" in line and "ndi_driver" in line
    # Throttled, not flooding: the driver retries with back-off (0, then 0.05 s doubling up to backoff_max_s), and
    # the console repeats the reason at most every THROTTLE_S with the count of the retries it held back. Wait for
    # the second line (a condition, not a length of time) and check both from the log's own stamps: the lines are
    # THROTTLE_S or more apart, and the count is at least one retry (it does retry) and at most what the back-off
    # allows in that time -- a driver retrying without back-off would make thousands.
    wait_for(lambda: len(_refused_lines(procs.log(tcp))) >= 2, timeout=60, what="the repeated TCP reason",
             detail=lambda: procs.log(tcp)[-2000:])
    (t1, _), (t2, second) = _refused_lines(procs.log(tcp))[:2]
    assert t2 - t1 >= THROTTLE_S - 0.05, (t1, t2, second)
    m = re.search(r"\((\d+) more times? in the last (\d+) s\)", second)
    assert m, second
    held_back = int(m[1])
    # (the executor logs an attempt when it gets to it: a late first line shortens t2 - t1 by its delay, the slack)
    assert 1 <= held_back <= _max_attempts(t2 - t1 + THROTTLE_S), (held_back, t2 - t1, second)
    for p in (tcp, ser):
        assert p.poll() is None
        assert procs.stop(p) == 0


THROTTLE_S = 5.0        # ndi_driver's ConsoleThrottle period for the link reason
BACKOFF = (0.05, 0.5)   # DriverConfig backoff_initial_s, backoff_max_s


def _max_attempts(seconds: float) -> int:
    """Most connection attempts the back-off schedule allows within ``seconds`` after a failed one (each attempt
    failing at once: nothing listens)."""
    n, t, wait = 0, 0.0, BACKOFF[0]
    while t + wait <= seconds:
        t += wait
        n += 1
        wait = min(BACKOFF[1], wait * 2)
    return n + 1


class FrameListener(SpunNode):
    """``/ots/bodies`` and every ``/ots/<tool>/{pose,quality}`` message, in arrival order per topic."""

    def __init__(self, context, tools=("tool", "base")) -> None:
        from geometry_msgs.msg import PoseStamped
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        from fullperc_msgs.msg import TrackedBodies, TrackingQuality

        super().__init__(context, "ndi_bodies_listener")
        qos = QoSProfile(depth=2000, reliability=ReliabilityPolicy.RELIABLE)
        self.got: dict[str, list] = {"/ots/bodies": []}
        self.node.create_subscription(TrackedBodies, "/ots/bodies", lambda m: self._add("/ots/bodies", m), qos)
        for t in tools:
            for what, typ in (("pose", PoseStamped), ("quality", TrackingQuality)):
                topic = f"/ots/{t}/{what}"
                self.got[topic] = []
                self.node.create_subscription(typ, topic, lambda m, topic=topic: self._add(topic, m), qos)
        self.start()

    def _add(self, topic: str, msg) -> None:
        with self.lock:
            self.got[topic].append(msg)

    def stamps(self) -> dict[str, list[int]]:
        with self.lock:
            return {k: [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in v] for k, v in self.got.items()}


def _bodies_carries_every_frame_as_the_per_tool_topics_do(procs, tmp_path, rclpy_context):
    """``/ots/bodies``: one TrackedBodies per device frame, whose stamp and frame_id are those of the frame's per-tool
    messages (matched by stamp), one body per tool in the ``tools`` order, each with its quality's fields and its
    pose message's pose; ``base``, which the emulator hides, ``visible: false`` with an all-zero pose and no pose
    message. Compared over the frames every topic has (the listener joins a running stream: its topics match one
    after another)."""
    from geometry_msgs.msg import Pose

    drv = start_driver(procs, start_emulator(procs, tmp_path, "--hidden", "base", "--circle", "30"))
    wait_for_first_line(procs, drv)
    lis = FrameListener(rclpy_context)
    watched = ("/ots/bodies", "/ots/tool/pose", "/ots/tool/quality", "/ots/base/quality")

    def window() -> tuple[int, int, int]:   # (first, last) stamp every watched topic got, frames in between
        st = lis.stamps()
        if not all(st[k] for k in watched):
            return 0, -1, 0
        lo, hi = max(st[k][0] for k in watched), min(st[k][-1] for k in watched)
        return lo, hi, sum(lo <= t <= hi for t in st["/ots/bodies"])

    try:
        wait_for(lambda: window()[2] >= 120, timeout=60, what="120 frames on /ots/bodies and the per-tool topics",
                 detail=lambda: {k: len(v) for k, v in lis.stamps().items()})
    finally:
        lis.close()
    assert drv.poll() is None, procs.log(drv)
    lo, hi, _ = window()
    got = {k: [m for m in v if lo <= m.header.stamp.sec * 10**9 + m.header.stamp.nanosec <= hi]
           for k, v in lis.got.items()}
    by_stamp = {k: {(m.header.stamp.sec, m.header.stamp.nanosec): m for m in v} for k, v in got.items()}
    frames = got["/ots/bodies"]
    assert len(by_stamp["/ots/bodies"]) == len(frames) >= 120   # one message per frame
    assert set(by_stamp["/ots/bodies"]) == set(by_stamp["/ots/tool/quality"]) == set(by_stamp["/ots/base/quality"])
    assert by_stamp["/ots/base/pose"] == {}   # hidden
    for f in frames:
        key = (f.header.stamp.sec, f.header.stamp.nanosec)
        assert [b.name for b in f.bodies] == ["tool", "base"]
        for b in f.bodies:
            q = by_stamp[f"/ots/{b.name}/quality"][key]
            assert f.header == q.header and f.header.frame_id == "ots" and f.latency == q.latency
            assert (b.visible, b.fit_error, b.frame_number, b.markers_used, b.port_status) == \
                (q.visible, q.fit_error, q.frame_number, q.markers_used, q.port_status), b.name
            if b.visible:
                pose = by_stamp[f"/ots/{b.name}/pose"][key]
                assert pose.header == f.header and b.pose == pose.pose
            else:
                assert key not in by_stamp[f"/ots/{b.name}/pose"] and b.pose == Pose()
        assert f.bodies[0].visible and not f.bodies[1].visible   # tool tracked, base hidden
    assert len({f.bodies[0].pose.position.x for f in frames}) > 1   # on its circle: the poses are the frames' own


def _ctrl_c_over_a_slow_link_exits_0_without_a_traceback(procs, tmp_path, rclpy_context):
    proxy = FaultProxy(start_emulator(procs, tmp_path), delay_s=0.02)
    try:
        for i in range(2):
            drv = start_driver(procs, proxy.port, name=f"ndi_driver_{i}")
            wait_for_first_line(procs, drv)   # a listener of each run's own, made once the driver is up
            lis = Listener(rclpy_context)
            try:
                wait_for(lambda lis=lis: lis.n_poses("tool") > 20, timeout=40, what="poses over the slow link")
                assert procs.stop(drv, signal.SIGINT) == 0, procs.log(drv)   # the listener still subscribed
            finally:
                lis.close()
            log = procs.log(drv)
            assert "Traceback" not in log and "callback failed" not in log, log[-3000:]
            # the stop took the clean path over the slow link: TSTOP went to the device before the exit
            assert proxy.commands.count("TSTOP") == i + 1, proxy.commands[-10:]
    finally:
        proxy.close()


GARBAGE_ROMS = {"empty": b"", "text": b"this is not a tool definition\n" * 40}

# the selected tests' scenarios at once, side by side, each with its own emulator, driver and domain: most of a
# scenario is waiting (processes starting, the driver's health periods, its back-off)
scenarios = side_by_side_fixture(
    _health_leaves_ok_on_frozen_nan_and_garbage_replies_and_recovers,
    _a_rom_the_device_refuses_is_named_and_the_other_tool_keeps_tracking,
    _an_unreachable_device_is_explained_on_the_console,
    _ctrl_c_over_a_slow_link_exits_0_without_a_traceback,
    _bodies_carries_every_frame_as_the_per_tool_topics_do,
    **{f"test_a_garbage_rom_file_stops_the_driver_naming_the_file[{k}]":
       (_a_garbage_rom_file_stops_the_driver_naming_the_file, {"content": content})
       for k, content in GARBAGE_ROMS.items()})


def test_health_leaves_ok_on_frozen_nan_and_garbage_replies_and_recovers(scenarios, request):
    scenarios.result(request.node.name)


def test_a_rom_the_device_refuses_is_named_and_the_other_tool_keeps_tracking(scenarios, request):
    scenarios.result(request.node.name)


@pytest.mark.parametrize("content", list(GARBAGE_ROMS))
def test_a_garbage_rom_file_stops_the_driver_naming_the_file(scenarios, request, content):
    scenarios.result(request.node.name)


def test_an_unreachable_device_is_explained_on_the_console(scenarios, request):
    scenarios.result(request.node.name)


def test_ctrl_c_over_a_slow_link_exits_0_without_a_traceback(scenarios, request):
    scenarios.result(request.node.name)


def test_bodies_carries_every_frame_as_the_per_tool_topics_do(scenarios, request):
    scenarios.result(request.node.name)
