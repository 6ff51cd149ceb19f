"""System test: the hardware bring-up (config/bringup_graph.yaml) against the emulators, run as docs/hardware.md says.

The graph runs exactly as on real hardware -- ``supervisor run`` with the page's own command, ndi_driver on TCP,
omc_driver on the ``nokov_sdk`` backend, diana_state on ``diana_api``, fusion_node from a parameter file, margin_node
-- with only the devices replaced: ``vega_emulator`` (the Combined API on a free TCP port, fullperc's emulator ROMs),
the C double of NOKOV's SDK (``fake_nokov_sdk.c``, a steady scene at 200 Hz) and the C double of DianaApi. The
emulated Vega sees the OMC's two bodies where the OMC does, so the fused tool sits where both put it.

Every command of docs/hardware.md is either run here (``RUN``: the bring-up, the two ``echo`` checks, the two service
calls) or named as one that needs the real devices or changes the machine (``NOT_HERE``, with the reason);
``test_every_command_of_the_page_is_run_here_or_needs_hardware`` fails when the page and these lists drift apart.
"""

from __future__ import annotations

import json
import re
import shlex
import shutil
import signal
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

from fullperc_common.diagnostics import as_level
from fullperc_common.testing import installed_exe, wait_for

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "hardware.md"
ROMS = ROOT / "src" / "fullperc_drivers" / "config" / "emulator_roms"   # synthetic: for the emulator only
C_DIR = ROOT / "src" / "fullperc_drivers" / "test" / "c"

BRINGUP = ("supervisor run install/fullperc_eval/share/fullperc_eval/config/bringup_graph.yaml "
           "--set ndi_address=P9-01234.local --set \"tools=[tool, base]\" "
           "--set \"tool_roms=[$HOME/or1/roms/tool.rom, $HOME/or1/roms/base.rom]\" "
           "--set nokov_server=10.1.1.198 --set nokov_sdk=$HOME/nokov/lib/libnokov_sdk.so "
           "--set \"bodies=[base, tool]\" --set \"targets=[tool]\" --set fusion_params=$HOME/or1/fusion.yaml")
ECHO_DIAGNOSTICS = "python -m fullperc_eval.bag echo /diagnostics --count 5"
ECHO_POSE = "python -m fullperc_eval.bag echo /fullperc/tool/pose --count 3"
INITIALIZE = "call /fusion_node/initialize std_srvs/srv/Trigger"
CALIBRATE = "call /fusion_node/calibrate std_srvs/srv/Trigger"
RUN = [BRINGUP, ECHO_DIAGNOSTICS, ECHO_POSE, INITIALIZE, CALIBRATE]
# commands of the page that cannot run against the emulators, and why
NOT_HERE = {
    "getent hosts P9-01234.local": "resolves the real Vega's Bonjour name on the OR network",
    "ping -c 3 10.1.1.198": "reaches the real XINGYING computer",
    "sudo ufw allow from 10.1.1.0/24": "changes the machine's firewall",
    "ros2 launch fullperc_eval bringup.launch.py ndi_address:=P9-01234.local \"tools:=[tool, base]\" "
    "\"tool_roms:=[$HOME/or1/roms/tool.rom, $HOME/or1/roms/base.rom]\" nokov_server:=10.1.1.198 "
    "nokov_sdk:=$HOME/nokov/lib/libnokov_sdk.so \"bodies:=[base, tool]\" \"targets:=[tool]\" "
    "fusion_params:=$HOME/or1/fusion.yaml":
        "needs `launch`, which the wheel install has not (test_launch_matches_graph checks the file against the graph)",
    "export ROS_DOMAIN_ID=42": "environment of the user's shell (the test has its own domain: ros_env)",
    "export ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET": "environment: discovery beyond this machine",
    "export ROS_STATIC_PEERS=10.1.1.20": "environment: discovery of another computer",
    "source scripts/env.sh": "the shell set-up every test already runs under",
    "make build": "the build the test suite runs first",
    "sudo usermod -aG dialout $USER": "changes the user's groups (a serial tracker)",
}
# the SDK double's tool (500, 600, -700.5) mm minus its base (100, -200, 300.25) mm, both at the identity orientation
TOOL_IN_BASE_MM = np.array([400.0, 800.0, -1000.75])

pytestmark = pytest.mark.system


def _page_commands() -> list[str]:
    """Every command in the page's ``bash`` blocks, continuation lines joined, comments dropped."""
    cmds = []
    for block in re.findall(r"```bash\n(.*?)```", PAGE.read_text(), re.S):
        for cmd in re.sub(r"\\\n\s*", "", block).splitlines():
            cmd = re.sub(r"\s+#.*$", "", cmd).strip()
            if cmd and not cmd.startswith("#"):
                cmds.append(" ".join(cmd.split()))
    return cmds


def test_every_command_of_the_page_is_run_here_or_needs_hardware():
    page = _page_commands()
    assert not (unknown := [c for c in page if c not in RUN and c not in NOT_HERE]), \
        f"docs/hardware.md commands neither run by this test nor named as hardware-only: {unknown}"
    assert not (stale := [c for c in [*RUN, *NOT_HERE] if c not in page]), f"no longer in docs/hardware.md: {stale}"


def _compile(src: Path, out: Path) -> Path:
    gcc = shutil.which("gcc")
    if gcc is None:
        pytest.skip("gcc not installed: cannot build the C doubles of the vendor libraries")
    subprocess.run([gcc, "-shared", "-fPIC", "-O1", "-pthread", "-o", str(out), str(src), "-lm"], check=True,
                   capture_output=True)
    return out


def _vega_poses() -> list[str]:
    """``--pose`` options of the emulator: base and tool in the Vega's volume, the tool where the OMC puts it in
    ``base`` (the SDK double's bodies have the identity orientation), both turned by the same rotation."""
    from scipy.spatial.transform import Rotation

    aim = np.array([0.35, 0.0, -0.94])          # the base-to-tool offset pointed into the depth of the pyramid
    rot, _ = Rotation.align_vectors([aim / np.linalg.norm(aim)], [TOOL_IN_BASE_MM / np.linalg.norm(TOOL_IN_BASE_MM)])
    base = np.array([-200.0, 0.0, -1050.0])
    q = ",".join(f"{v:.9f}" for v in rot.as_quat())
    return ["--pose", "base=" + ",".join(f"{v:.6f}" for v in base) + "," + q,
            "--pose", "tool=" + ",".join(f"{v:.6f}" for v in base + rot.apply(TOOL_IN_BASE_MM)) + "," + q]


def _bringup_argv(port: int, sdk: Path, diana: Path, params: Path) -> list[str]:
    """The page's bring-up command with the devices' addresses and files replaced by the emulators'."""
    words = shlex.split(BRINGUP)
    sets = dict(words[i + 1].split("=", 1) for i, w in enumerate(words) if w == "--set")
    assert sets.keys() == {"ndi_address", "tools", "tool_roms", "nokov_server", "nokov_sdk", "bodies", "targets",
                           "fusion_params"}
    sets |= {"ndi_address": "127.0.0.1", "tool_roms": f"[{ROMS / 'tool.rom'}, {ROMS / 'base.rom'}]",
             "nokov_sdk": str(sdk), "fusion_params": str(params),
             # the emulator's port; the SDK double's time stamps are in microseconds (NOKOV's unit is a parameter)
             "ndi_port": str(port), "sdk_timestamp_unit_ns": "1000",
             # the page's "with the arm" variant
             "with_diana": "true", "diana_library": str(diana)}
    assert sets["nokov_server"] == "10.1.1.198"       # the SDK double's server
    head = words[:words.index("--set")]
    return [installed_exe("fullperc_eval", head[0]), *head[1:], *(a for k, v in sets.items()
                                                                  for a in ("--set", f"{k}={v}"))]


class _Listener:
    """Fused poses and the latest /diagnostics status of each name, from a node in this process."""

    def __init__(self, context) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        from fullperc_common.testing import SpunNode

        self.spun = SpunNode(context, "bringup_test_listener")
        self.poses: list = []
        self.status: dict[str, tuple[int, str]] = {}
        qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        self.spun.node.create_subscription(PoseStamped, "/fullperc/tool/pose", self._pose, qos)
        self.spun.node.create_subscription(DiagnosticArray, "/diagnostics", self._diag, 100)
        self.spun.start()

    def _pose(self, m) -> None:
        with self.spun.lock:
            self.poses.append(m)

    def _diag(self, m) -> None:
        with self.spun.lock:
            for st in m.status:
                self.status[st.name] = (as_level(st.level), st.message)

    def n_poses(self) -> int:
        with self.spun.lock:
            return len(self.poses)

    def levels(self, names: tuple[str, ...]) -> dict[str, tuple[int, str] | None]:
        with self.spun.lock:
            return {n: self.status.get(n) for n in names}


def _tail(path: Path, n: int = 3000) -> str:
    return path.read_text(errors="replace")[-n:] if path.exists() else "(no log)"


DRIVERS = ("omc_driver: omc", "ndi_driver: link", "diana_state: diana")


def _run(cmd: str, env: dict[str, str], graph_log, timeout: float = 120.0) -> subprocess.CompletedProcess:
    """One of the page's commands, as a user types it (``call`` is the installed executable); a command that does not
    end within ``timeout`` fails the test with the graph's log (a liveness bound, not a performance figure)."""
    words = shlex.split(cmd)
    words[0] = sys.executable if words[0] == "python" else installed_exe("fullperc_eval", words[0])
    try:
        return subprocess.run(words, env=env, cwd=ROOT, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        pytest.fail(f"{cmd!r} did not end within {timeout:.0f} s; the graph's log:\n{graph_log()}")


def test_bringup_against_the_emulators_fuses_and_reports_ok(procs, ros_env, rclpy_context, tmp_path,
                                                            record_property):
    sdk = _compile(C_DIR / "fake_nokov_sdk.c", tmp_path / "libnokov_sdk.so")
    diana = _compile(C_DIR / "fake_diana_api.c", tmp_path / "libDianaApi.so")
    # the user's copy of fusion.yaml; here a 1 s collection for ~/calibrate (10 s by default) keeps the test short
    params = tmp_path / "fusion.yaml"
    params.write_text("/**/fusion_node:\n  ros__parameters:\n    calibration:\n      duration: 1.0\n")
    port_file = tmp_path / "vega_port"
    emu = procs.start([installed_exe("fullperc_eval", "vega_emulator"), "--port", "0", "--port-file", str(port_file),
                       "--tool", f"tool={ROMS / 'tool.rom'}", "--tool", f"base={ROMS / 'base.rom'}", *_vega_poses()])
    wait_for(lambda: port_file.exists() and port_file.read_text().strip() or emu.poll() is not None, timeout=60,
             what="the Vega emulator's port", detail=lambda: procs.log(emu))
    assert emu.poll() is None, procs.log(emu)
    # a scene at rest for 1000 s, at 100 Hz (XINGYING's default rate is higher: here the whole graph, the emulators
    # and the test share a machine that may be busy)
    env = dict(ros_env, FAKE_NOKOV_FRAMES="100000", FAKE_NOKOV_RATE_HZ="100", FAKE_NOKOV_STEADY="1")
    lis = _Listener(rclpy_context)
    sup = procs.start([*_bringup_argv(int(port_file.read_text()), sdk, diana, params), "--logs",
                       str(tmp_path / "logs")], name="supervisor", env=env, cwd=ROOT)
    try:
        def log() -> str:
            return procs.log(sup)[-3000:] + "\n--- fusion_node:\n" + _tail(tmp_path / "logs" / "fusion.log")

        wait_for(lambda: sup.poll() is not None or "started ndi" in procs.log(sup), timeout=240,
                 what="the supervisor to start every process", detail=log)
        assert sup.poll() is None, log()
        wait_for(lambda: lis.n_poses() >= 50, timeout=120, what="fused poses on /fullperc/tool/pose", detail=log)
        wait_for(lambda: all(v is not None and v[0] == 0 for v in lis.levels(DRIVERS).values()), timeout=120,
                 what="every driver OK on /diagnostics", detail=lambda: (lis.levels(DRIVERS), log()))
        with lis.spun.lock:
            poses = list(lis.poses)
        assert all(m.header.frame_id == "base" for m in poses)
        xyz = np.array([[m.pose.position.x, m.pose.position.y, m.pose.position.z] for m in poses])
        err_mm = np.linalg.norm(xyz - TOOL_IN_BASE_MM / 1000.0, axis=1) * 1000.0
        record_property("bringup_fused_error_mm", f"median {np.median(err_mm):.3f}, max {err_mm.max():.3f}")
        assert np.median(err_mm[-20:]) < 1.0, f"fused tool off the emulated one by {err_mm[-20:]} mm"

        # the page's checks (side by side: each is seconds of interpreter start and discovery) and service calls
        with ThreadPoolExecutor(2) as pool:
            diag, pose = pool.map(lambda c: _run(c, ros_env, log), (ECHO_DIAGNOSTICS, ECHO_POSE))
        assert diag.returncode == 0 and len(diag.stdout.splitlines()) == 5, diag.stderr
        assert pose.returncode == 0, pose.stderr
        lines = [json.loads(ln) for ln in pose.stdout.splitlines()]
        assert len(lines) == 3 and all(m["header"]["frame_id"] == "base" for m in lines)
        for cmd in (INITIALIZE, CALIBRATE):
            r = _run(cmd, ros_env, log)
            assert r.returncode == 0, (cmd, r.stderr)
            assert json.loads(r.stdout)["success"] is True, (cmd, r.stdout)
        n = lis.n_poses()
        wait_for(lambda: lis.n_poses() > n + 50, timeout=60, what="fused poses after ~/calibrate", detail=log)
        assert re.search(r"calibrated over [0-9.]+ s: T_omc_base", procs.log(sup)), log()
    finally:
        lis.spun.close()
        rc = procs.stop(sup, signal.SIGINT, timeout=120)
    out = procs.log(sup)
    assert rc == 0, out[-3000:]
    stopped = re.search(r"all processes stopped: (.*)", out)
    assert stopped and set(re.findall(r"=(\S+?)(?:,|$)", stopped.group(1))) == {"0"}, out[-3000:]
    assert set(re.findall(r"(\w+)=", stopped.group(1))) == {"fusion", "margin", "omc", "diana", "ndi"}
    record_property("bringup_fused_poses", len(poses))


def test_a_missing_argument_stops_the_bringup_before_anything_starts(ros_env):
    """The page's command without ``tool_roms`` (the user's ROMs): exit 2, one line naming it, nothing started."""
    words = shlex.split(BRINGUP)
    i = next(i for i, w in enumerate(words) if w.startswith("tool_roms="))
    del words[i - 1:i + 1]
    r = subprocess.run([installed_exe("fullperc_eval", "supervisor"), *words[1:]], env=ros_env, cwd=ROOT,
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "{tool_roms}" in r.stderr and "--set tool_roms=" in r.stderr, r.stderr
    assert "started" not in r.stdout

