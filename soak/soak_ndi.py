"""Soak: ``ndi_driver`` on a faulty link to the Vega emulator for 5 minutes (issue 14).

The installed ``vega_emulator`` corrupts 1 % of its replies (CRC) and prefixes 1 % with garbage bytes
(``--corrupt-crc 0.01 --garbage 0.01``); between it and the installed ``ndi_driver`` sits :class:`LinkCutter`, a
TCP relay in this process that cuts the link every ``--disconnect-every`` seconds (30). The cuts cycle through
``--outages`` (default ``0,3,0,4``): ``0`` cuts the connection and lets the driver straight back in (a network
glitch, a device that closed the socket); ``3`` and ``4`` also keep the device unreachable that long (connections
are accepted and closed at once) -- an outage longer than the driver's ``health.stale_after_s`` (2 s), which the
driver must report. A subscriber in this process counts the poses of both tools, looks for non-finite values, and
keeps every ``ndi_driver: link`` status from ``/diagnostics`` with its arrival time. A driver that dies is counted
and started again.

Per cut, *back* is the arrival of the first pose acquired after the cut (its header stamp is later than the cut,
so a pose still in flight does not count). The *reconnect time* of a plain cut is cut -> back; after an outage the
time from the device being reachable again to back is reported on its own: it is set by the driver's back-off
(attempts 0, 0.05, 0.15, 0.35, 0.75, 1.55, 3.15, 5.15 s after the loss, then every 2 s), so it depends on where
the outage ends in that schedule (3 s: the next attempt comes 0.15 s later; 4 s: 1.15 s later). *Reported*: a
non-OK level arrived between the cut and 1.5 s after back (every cut: the driver reports a lost link at once and
holds it as WARN for ``link_hold_s`` = 1 s after it is back, so even a 30 ms reconnect is seen). *Recovered*: an
OK level arrived after back, before the next cut. Figures (bench/benchlib.py lines)::

  ndi_soak_crashes              driver exits other than by the final SIGINT (that exit must be 0, no traceback)
  ndi_reconnect_p99_s           plain cuts: cut -> first new pose (also median, max, each cut)
  ndi_back_after_outage_max_s   outages: device reachable again -> first new pose (each outage)
  ndi_nan_published             poses with a non-finite value
  ndi_outages_reported          of every cut (fields: of the outages, of the plain cuts)
  ndi_recovered_after_outage    of every cut
  ndi_poses_received            both tools, with the rate (fault-free: 2 x 60 Hz) and the emulator's fault counts

Exit status 1 unless: no crash, reconnect p99 <= 1 s, no NaN, every cut reported, OK after every cut.

  source scripts/env.sh && python soak/soak_ndi.py [--duration 300] [--disconnect-every 30] [--outages 0,3,0,4]
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))

from benchlib import emit  # noqa: E402

from fullperc_common.testing import SpunNode  # noqa: E402

STATUS = "ndi_driver: link"
STALE_AFTER_S = 2.0  # ndi_driver's health.stale_after_s default (config/ndi_vega.yaml)


class LinkCutter:
    """A TCP relay driver <-> emulator whose link can be cut, optionally keeping the device away for a while."""

    def __init__(self, upstream_port: int) -> None:
        self.upstream = ("127.0.0.1", upstream_port)
        self.reachable = threading.Event()
        self.reachable.set()
        self._lock = threading.Lock()
        self._pairs: list[tuple[socket.socket, socket.socket]] = []
        self._srv = socket.create_server(("127.0.0.1", 0))
        self._srv.settimeout(0.2)
        self.port = self._srv.getsockname()[1]
        self._stop = threading.Event()
        self.refused = 0
        self._thread = threading.Thread(target=self._accept, daemon=True, name="cutter-accept")
        self._thread.start()

    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._srv.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            if not self.reachable.is_set():
                self.refused += 1
                conn.close()  # the device is away: the connection ends at once
                continue
            try:
                up = socket.create_connection(self.upstream, timeout=5.0)
            except OSError:
                conn.close()
                continue
            for s in (conn, up):
                s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with self._lock:
                self._pairs.append((conn, up))
            for a, b in ((conn, up), (up, conn)):
                threading.Thread(target=self._pump, args=(a, b), daemon=True, name="cutter-pump").start()

    @staticmethod
    def _pump(src: socket.socket, dst: socket.socket) -> None:
        try:
            while True:
                data = src.recv(65536)
                if not data:
                    break
                dst.sendall(data)
        except OSError:
            pass
        for s in (src, dst):
            try:
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass

    def cut(self, keep_away_s: float) -> None:
        """Close every relayed connection now; refuse new ones for ``keep_away_s`` (blocks that long)."""
        if keep_away_s > 0:
            self.reachable.clear()
        with self._lock:
            pairs, self._pairs = self._pairs, []
        for pair in pairs:
            for s in pair:
                try:
                    s.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
                s.close()
        if keep_away_s > 0:
            time.sleep(keep_away_s)
            self.reachable.set()

    def close(self) -> None:
        self._stop.set()
        self._srv.close()
        self.cut(0)
        self._thread.join(2)


class Watcher(SpunNode):
    """This process's view of the driver: every pose (arrival, stamp, finite?) and every link status."""

    def __init__(self, context) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        from fullperc_common.diagnostics import as_level

        self._as_level = as_level
        super().__init__(context, "soak_ndi_watcher")
        self.poses: dict[str, list[tuple[int, int]]] = {"tool": [], "base": []}  # (arrival ns, stamp ns)
        self.nan = 0
        self.diag: list[tuple[int, int, str]] = []  # (arrival ns, level, message)
        qos = QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE)
        for tool in self.poses:
            self.node.create_subscription(PoseStamped, f"/ots/{tool}/pose", lambda m, t=tool: self._pose(t, m), qos)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._diag, 100)
        self.start()

    def _pose(self, tool: str, m) -> None:
        now = time.time_ns()
        p, q = m.pose.position, m.pose.orientation
        finite = all(math.isfinite(v) for v in (p.x, p.y, p.z, q.x, q.y, q.z, q.w))
        with self.lock:
            self.poses[tool].append((now, m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec))
            if not finite:
                self.nan += 1

    def _diag(self, arr) -> None:
        now = time.time_ns()
        for st in arr.status:
            if st.name == STATUS:
                with self.lock:
                    self.diag.append((now, self._as_level(st.level), st.message))

    def n_poses(self) -> int:
        with self.lock:
            return sum(len(v) for v in self.poses.values())

    def last_level(self) -> int | None:
        with self.lock:
            return self.diag[-1][1] if self.diag else None


@dataclass
class Cut:
    t_cut: int  # wall ns
    t_back: int  # wall ns, the device reachable again
    keep_away_s: float
    t_next: int = 0  # the next cut or the end
    first_pose: int | None = None  # arrival of the first pose acquired after the cut
    reported: bool = False
    recovered: bool = False
    levels: str = ""

    @property
    def reconnect_s(self) -> float:
        return (self.first_pose - self.t_back) / 1e9 if self.first_pose is not None else math.inf


REPORT_WINDOW_NS = 1_500_000_000  # link_hold_s 1 s + one 0.25 s evaluation period + delivery


def analyse(cuts: list[Cut], w: Watcher) -> None:
    with w.lock:
        tool = np.array(w.poses["tool"], dtype=np.int64).reshape(-1, 2)
        diag = list(w.diag)
    for c in cuts:
        after = tool[(tool[:, 1] > c.t_cut) & (tool[:, 0] < c.t_next)] if len(tool) else tool
        c.first_pose = int(after[:, 0].min()) if len(after) else None
        # a plain cut is repaired in tens of ms; the driver holds it as WARN for health's link_hold_s (1 s) after,
        # and evaluates its ladder every 0.25 s: look until then
        end = min(c.t_next, (c.first_pose if c.first_pose is not None else c.t_next) + REPORT_WINDOW_NS)
        during = [lvl for t, lvl, _ in diag if c.t_cut <= t <= end]
        c.reported = any(lvl != 0 for lvl in during)
        c.recovered = c.first_pose is not None and any(lvl == 0 for t, lvl, _ in diag if c.first_pose < t < c.t_next)
        c.levels = "".join("OWES"[min(lvl, 3)] for lvl in during)


def start_emulator(tmp: Path, env: dict[str, str], a) -> tuple[subprocess.Popen, int]:
    from fullperc_common.testing import installed_exe, poll_until

    port_file = tmp / "emu_port"
    log = open(tmp / "vega_emulator.log", "wb")  # noqa: SIM115 - lives as long as the process
    p = subprocess.Popen([installed_exe("fullperc_eval", "vega_emulator"), "--port", "0", "--port-file",
                          str(port_file), "--corrupt-crc", str(a.corrupt), "--garbage", str(a.garbage),
                          "--circle", "20", "--seed", str(a.seed)],
                         stdout=log, stderr=subprocess.STDOUT, env=env, start_new_session=True)
    if not poll_until(lambda: port_file.exists() and port_file.read_text().strip(), 60):
        raise RuntimeError("vega_emulator did not start: " + (tmp / "vega_emulator.log").read_text()[-2000:])
    return p, int(port_file.read_text())


def start_driver(tmp: Path, env: dict[str, str], port: int, k: int) -> subprocess.Popen:
    from fullperc_common.testing import installed_exe

    log = open(tmp / f"ndi_driver_{k}.log", "wb")  # noqa: SIM115
    p = subprocess.Popen([installed_exe("fullperc_drivers", "ndi_driver"), "--ros-args", "-p", f"port:={port}"],
                         stdout=log, stderr=subprocess.STDOUT, env=env, start_new_session=True)
    p.log_path = tmp / f"ndi_driver_{k}.log"  # type: ignore[attr-defined]
    return p


def stop(p: subprocess.Popen, sig: int = signal.SIGINT, timeout: float = 20) -> int:
    if p.poll() is None:
        try:
            os.killpg(p.pid, sig)
            p.wait(timeout)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
        except ProcessLookupError:
            pass
    return p.wait()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration", type=float, default=300.0, help="soak time after warm-up [s] (300)")
    ap.add_argument("--disconnect-every", type=float, default=30.0, help="[s] (30)")
    ap.add_argument("--outages", default="0,3,0,4", help="how long each cut keeps the device away, cycled [s]")
    ap.add_argument("--corrupt", type=float, default=0.01, help="reply CRC corruption probability (0.01)")
    ap.add_argument("--garbage", type=float, default=0.01, help="garbage-before-reply probability (0.01)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--domain", type=int, default=None, help="ROS_DOMAIN_ID (default: derived from the pid)")
    a = ap.parse_args()
    outages = [float(x) for x in a.outages.split(",")]

    import rclpy
    from rclpy.context import Context

    from fullperc_common.testing import poll_until

    domain = a.domain if a.domain is not None else 1 + (os.getpid() * 11 + 70) % 100
    os.environ.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONUNBUFFERED="1")
    env = dict(os.environ)
    tmp = Path(tempfile.mkdtemp(prefix="soak_ndi_"))
    ctx = Context()
    rclpy.init(context=ctx)
    emu, emu_port = start_emulator(tmp, env, a)
    cutter = LinkCutter(emu_port)
    watcher = Watcher(ctx)
    drivers = [start_driver(tmp, env, cutter.port, 0)]
    crashes: list[str] = []
    cuts: list[Cut] = []
    final_rc = None
    try:
        if not poll_until(lambda: watcher.n_poses() > 100 and watcher.last_level() == 0, 120):
            raise RuntimeError("no poses / no OK within 120 s of the start:\n"
                               + drivers[-1].log_path.read_text()[-3000:])  # type: ignore[attr-defined]
        t0 = time.monotonic()
        n0 = watcher.n_poses()
        k = 0
        while True:
            t_next = t0 + (k + 1) * a.disconnect_every
            keep = outages[k % len(outages)]
            if t_next + keep > t0 + a.duration - 5.0:  # leave time to come back before the end
                break
            while time.monotonic() < t_next:
                if drivers[-1].poll() is not None:  # a crash: count it, start the driver again
                    d = drivers[-1]
                    crashes.append(f"exit {d.returncode}: {d.log_path.read_text()[-2000:]}")  # type: ignore
                    drivers.append(start_driver(tmp, env, cutter.port, len(drivers)))
                time.sleep(0.05)
            print(f"# cut {k + 1} at {time.monotonic() - t0:.0f} s (device away {keep:g} s)", file=sys.stderr,
                  flush=True)
            t_cut = time.time_ns()
            cutter.cut(keep)
            cuts.append(Cut(t_cut, time.time_ns(), keep))
            k += 1
        while time.monotonic() < t0 + a.duration:
            time.sleep(0.05)
        t_end = time.time_ns()
        poses = watcher.n_poses() - n0
        rate = poses / (time.monotonic() - t0)
        if drivers[-1].poll() is not None:
            d = drivers[-1]
            crashes.append(f"exit {d.returncode}: {d.log_path.read_text()[-2000:]}")  # type: ignore
        final_rc = stop(drivers[-1])
        final_log = drivers[-1].log_path.read_text()  # type: ignore[attr-defined]
        if final_rc != 0 or "Traceback" in final_log:
            crashes.append(f"final SIGINT: exit {final_rc}: {final_log[-2000:]}")
    finally:
        for d in drivers:
            stop(d, signal.SIGKILL)
        watcher.close()
        cutter.close()
        stop(emu)
        rclpy.try_shutdown(context=ctx)
    for i, c in enumerate(cuts):
        c.t_next = cuts[i + 1].t_cut if i + 1 < len(cuts) else t_end
    analyse(cuts, watcher)
    emu_log = (tmp / "vega_emulator.log").read_text(errors="replace")
    stats = next((ln.split(": ", 1)[1] for ln in emu_log.splitlines() if ln.startswith("vega_emulator stopped")), "")

    plain = [c for c in cuts if c.keep_away_s == 0]
    long_cuts = [c for c in cuts if c.keep_away_s > STALE_AFTER_S]
    rec = np.array([c.reconnect_s for c in plain]) if plain else np.array([math.nan])
    back = [c.reconnect_s for c in cuts if c.keep_away_s > 0]
    emit("ndi_soak_crashes", len(crashes), "count", final_exit=final_rc, duration_s=a.duration)
    emit("ndi_reconnect_p99_s", float(np.percentile(rec, 99)), "s", of=len(plain),
         median=round(float(np.median(rec)), 3), max=round(float(np.max(rec)), 3),
         each=[round(float(x), 3) for x in rec])
    emit("ndi_back_after_outage_max_s", max(back) if back else math.nan, "s", of=len(back),
         each=[f"{c.keep_away_s:g} s away: {c.reconnect_s:.3f}" for c in cuts if c.keep_away_s > 0])
    emit("ndi_nan_published", watcher.nan, "count")
    short = [c for c in cuts if c not in long_cuts]
    emit("ndi_outages_reported", sum(c.reported for c in cuts), "count", of=len(cuts),
         outages_reported=f"{sum(c.reported for c in long_cuts)}/{len(long_cuts)}",
         plain_cuts_reported=f"{sum(c.reported for c in short)}/{len(short)}")
    emit("ndi_recovered_after_outage", sum(c.recovered for c in cuts), "count", of=len(cuts))
    emit("ndi_poses_received", poses, "count", rate_hz=round(rate, 1), fault_free_rate_hz=2 * 60.0, emulator=stats)
    for i, c in enumerate(cuts):
        print(f"cut {i + 1}: away {c.keep_away_s:g} s, reconnect {c.reconnect_s:.3f} s, reported {c.reported}, "
              f"recovered {c.recovered}, levels during the cut: {c.levels or '-'}", file=sys.stderr)
    for c in crashes:
        print(f"crash: {c}", file=sys.stderr)
    ok = (not crashes and watcher.nan == 0 and all(c.reported for c in cuts) and all(c.recovered for c in cuts)
          and float(np.percentile(rec, 99)) <= 1.0)
    if ok:
        shutil.rmtree(tmp, ignore_errors=True)
    else:
        print(f"logs kept in {tmp}", file=sys.stderr)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
