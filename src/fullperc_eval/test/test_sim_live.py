"""The installed ``sim`` executable serves what the offline run computes: OMC and Diana UDP streams and the
Vega emulator on TCP, then exits at the end of the task (multi-process, real sockets)."""

from __future__ import annotations

import json
import socket
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from fullperc_common.testing import installed_exe, udp_socket_off_dds_ports, wait_for
from fullperc_drivers.ndi.protocol import encode_command
from fullperc_drivers.streams import decode_diana, decode_omc
from fullperc_eval.sim.live import LiveServer
from fullperc_eval.sim.runner import run_task
from fullperc_eval.sim.scene import DEFAULT_PROFILE

TASK, SEED = "P-G-B", 2


@pytest.fixture(scope="module")
def offline_future():
    """The task as the ``sim`` executable runs it by default (its default twin profile), offline, computed in a
    thread of its own: the first test starts the ``sim`` process (which simulates the same task before it serves)
    while this runs, and drains its sockets meanwhile. The run is deterministic and only read (by the tests and by
    LiveServer): one simulation serves every test of the module."""
    with ThreadPoolExecutor(1) as ex:
        yield ex.submit(run_task, TASK, seed=SEED, profile=DEFAULT_PROFILE)


@pytest.fixture(scope="module")
def offline(offline_future):
    return offline_future.result()


def _udp() -> socket.socket:
    s = udp_socket_off_dds_ports()   # not a port another test's DDS discovery sends to
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
    s.settimeout(0.2)
    return s


@pytest.mark.slow
def test_sim_serves_the_offline_measurements(procs, tmp_path, offline_future):
    so, sd = _udp(), _udp()
    port_file = tmp_path / "vega.port"
    offset = 7_000_000_000  # device clocks 7 s ahead of the host clock
    p = procs.start([installed_exe("fullperc_eval", "sim"), "--task", TASK, "--seed", str(SEED), "--speed", "8",
                     "--omc-addr", f"127.0.0.1:{so.getsockname()[1]}",
                     "--diana-addr", f"127.0.0.1:{sd.getsockname()[1]}", "--vega-port", "0",
                     "--vega-port-file", str(port_file), "--device-clock-offset-ns", str(offset)], name="sim")

    omc, dia = [], []

    def drain() -> bool:
        for s, out, dec in ((so, omc, decode_omc), (sd, dia, decode_diana)):
            try:
                while True:
                    out.append((dec(s.recv(65536)), time.time_ns()))
            except (TimeoutError, BlockingIOError):
                pass
        return p.poll() is not None

    # the Vega emulator answers the Combined API while the task plays
    port = int(wait_for(lambda: port_file.exists() and port_file.read_text().strip(), 120, what="Vega port"))
    with socket.create_connection(("127.0.0.1", port), timeout=5) as c:
        c.sendall(b"INIT \r")
        assert c.recv(64).startswith(b"OKAY")
    wait_for(drain, timeout=120, interval=0.01, what="sim to finish the task")
    drain()
    assert p.returncode == 0, procs.log(p)
    offline = offline_future.result()

    # every OMC frame arrived, in order, with the offline values (mm on the wire)
    fn = np.array([f.frame_number for f, _ in omc])
    np.testing.assert_array_equal(fn, offline.omc.frame_number)
    tool = offline.omc.bodies["tool"]
    for i in range(0, len(omc), 97):
        f = omc[i][0]
        b = {x.name: x for x in f.bodies}
        # the twin's extra targets too (sim.targets): the hand-held instrument and the patient reference
        assert set(b) == {"base", "ots_rig", "tool", "instrument", "reference"}
        assert b["tool"].tracked == bool(tool.tracked[i])
        for name, body_id in (("instrument", 4), ("reference", 5)):
            extra = offline.omc.bodies[name]
            assert b[name].tracked == bool(extra.tracked[i]) and b[name].id == body_id
            if extra.tracked[i]:
                np.testing.assert_allclose(b[name].position_mm, extra.position[i] * 1000.0, rtol=0, atol=1e-9)
        if tool.tracked[i]:
            np.testing.assert_allclose(b["tool"].position_mm, tool.position[i] * 1000.0, rtol=0, atol=1e-9)
            np.testing.assert_allclose(b["tool"].quat_xyzw, tool.quat_xyzw[i], atol=1e-12)
        assert f.latency_s == pytest.approx(offline.omc.latency_s / 8, rel=1e-6)
    # device time stamps: capture times on the offset device clock, spaced like the simulation (scaled by speed)
    ts = np.array([f.timestamp_ns for f, _ in omc], dtype=np.int64)
    np.testing.assert_allclose(np.diff(ts), np.diff(offline.omc.t_ns) / 8, atol=2)
    recv = np.array([r for _, r in omc], dtype=np.int64)
    assert np.median(ts - offset - recv) < 0  # stamped before it was received: capture, not send time
    # the joint stream carries the offline joint angles
    assert len(dia) == len(offline.diana.t_ns)
    k = len(dia) // 2
    np.testing.assert_array_equal(dia[k][0].q, offline.diana.q[k])

    log = [json.loads(line) for line in procs.log(p).splitlines() if line.startswith("{")]
    events = [r["event"] for r in log]
    assert events[0] == "plan" and "start" in events and events[-1] == "end"
    regions = [r["region"] for r in log if r["event"] == "region"]
    assert regions == ["PVV", "GVV", "BVV"]



def test_task_waits_until_a_driver_tracks(offline):
    """``serve(wait_for_tracking_s=…)``: no device data and no task clock before a driver sent TSTART to the
    Vega emulator, so a recorder that starts with the drivers sees the task from its first sample."""
    run = offline
    so = _udp()
    events: list[dict] = []
    server = LiveServer(run, speed=8.0, omc_addr=("127.0.0.1", so.getsockname()[1]),
                        diana_addr=("127.0.0.1", so.getsockname()[1]), vega_port=0, log=events.append)
    th = threading.Thread(target=server.serve, kwargs={"start_delay_s": 0.0, "wait_for_tracking_s": 60.0},
                          daemon=True)
    th.start()
    try:
        wait_for(lambda: server.vega is not None, 10, what="Vega emulator")
        time.sleep(1.0)
        assert [e["event"] for e in events] == [] and server.t0_host_ns == 0
        with pytest.raises(TimeoutError):
            so.recv(65536)  # nothing streamed while waiting
        with socket.create_connection(("127.0.0.1", server.vega.port), timeout=5) as c:
            for cmd in ("INIT", "TSTART"):
                c.sendall(encode_command(cmd))
                assert c.recv(64).startswith(b"OKAY"), cmd
            t_tstart = time.time_ns()
            wait_for(lambda: any(e["event"] == "start" for e in events), 10, what="task start")
        assert [e["event"] for e in events][:2] == ["tracking", "start"]
        assert server.t0_host_ns >= t_tstart - 50_000_000
        # the emulator ran before the task clock was set; from then on its frames are the simulated Vega's
        _assert_frames_carry_their_own_sample(server)
        assert len(so.recv(65536)) > 0  # and now the streams play
    finally:
        server.stop()
        th.join(10)
    assert not th.is_alive()


def _assert_frames_carry_their_own_sample(server: LiveServer, n: int = 120) -> None:
    """Each emulator frame from the task start on is captured at one of the simulated Vega's sample times and
    carries that sample (not the one before it: stamped by its frame time, such a pose was up to a period old)."""
    run, dev = server.run, server.vega.device
    first = dev.frame_number(server.host_ns(run.ots.t_ns[0]))
    served = 0
    for f in range(first, first + n):
        s = server.sim_ns(dev.frame_time_ns(f))
        if s < run.ots.t_ns[0]:
            continue
        k = int(np.argmin(np.abs(run.ots.t_ns - s)))
        assert abs(int(run.ots.t_ns[k]) - s) <= 2 * server.speed + 2, (f, s, run.ots.t_ns[k])   # ns of rounding
        poses = dev.poses_for_frame(f)
        for name, tool in run.ots.tools.items():
            if tool.visible[k]:
                np.testing.assert_array_equal(poses[name].position_mm, tool.position[k] * 1000.0)
                served += 1
    assert served > 0


def test_vega_restarted_during_the_task_is_on_the_task_s_frame_grid(offline):
    """A Vega emulator started while the task plays (the demo's ``vega_outage``: a fresh one after a kill)."""
    run = offline
    server = LiveServer(run, speed=1.0, vega_port=0, log=lambda rec: None,
                        omc_addr=("127.0.0.1", 9), diana_addr=("127.0.0.1", 9))
    try:
        server.t0_host_ns = time.time_ns() - 1_234_567   # a task clock off the emulator's own frame grid
        server._start_vega()
        _assert_frames_carry_their_own_sample(server, n=int(run.ots.t_ns.size))
    finally:
        server.close()


def test_task_starts_anyway_when_nobody_tracks(offline):
    """A demo without a Vega driver is not stuck: after the timeout the task starts and says why."""
    run = offline
    events: list[dict] = []
    server = LiveServer(run, speed=50.0, vega_port=0, log=events.append,
                        omc_addr=("127.0.0.1", 9), diana_addr=("127.0.0.1", 9))
    t = time.monotonic()
    server.serve(start_delay_s=0.0, wait_for_tracking_s=0.5)
    assert time.monotonic() - t >= 0.5
    names = [e["event"] for e in events]
    assert names[0] == "tracking_timeout" and "start" in names and names[-1] == "end"
