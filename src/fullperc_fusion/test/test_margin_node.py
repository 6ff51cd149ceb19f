"""``margin_node`` across processes: the installed executable, a pose publisher in another process (this file run
as a script), and an in-test subscriber for the region labels and the latched margin map.

The layout written by the test is computable by hand: three cameras 2 m from G = (0, 0, 1) at azimuths 0, 90 and
180 deg, all looking at G (pairs 90, 90 and 180 deg apart: margin 2 x 90 = 180 deg, 2 valid pairs, 3 cameras), an
explicit threshold of 150 deg, and an NDI tracker at (5, 5, 1) looking along +y, so B = (5, 6.5, 1) is 1.5 m in
front of it (BVV). P = (0, 0, -5) is beyond every camera's 4 m range (margin 0, PVV).
T_omc_base is a 90 deg turn about z plus (1, 2, 0): p_base = (p_omc.y - 2, 1 - p_omc.x, p_omc.z), so the fused
("base" frame) tool poses are G -> (-2, 1, 1), B -> (4.5, -4, 1), P -> (-2, 1, -5).
"""

from __future__ import annotations

import math
import sys
import time

import pytest
import yaml

CAMS = {"c1": (2.0, 0.0, 1.0), "c2": (0.0, 2.0, 1.0), "c3": (-2.0, 0.0, 1.0)}
POINTS_OMC = {"G": (0.0, 0.0, 1.0), "B": (5.0, 6.5, 1.0), "P": (0.0, 0.0, -5.0)}
POINTS_BASE = {"G": (-2.0, 1.0, 1.0), "B": (4.5, -4.0, 1.0), "P": (-2.0, 1.0, -5.0)}
ORDER = ("G", "B", "P")  # header.stamp.sec = 100 + index identifies the point
BASE_POSE = ((1.0, 2.0, 0.0), (0.0, 0.0, math.sin(math.pi / 4), math.cos(math.pi / 4)))
FLICKER_T0_NS, FLICKER_DT_NS = 1_000 * 10**9, 10_000_000   # target 'flicker': G, P, G, P, ... every 10 ms of stamps
BAND, DWELL = 1.0, 0.2   # margin_node's default hysteresis [deg], [s]


def _quat_from_matrix(cols):
    import numpy as np
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(np.column_stack(cols)).as_quat().tolist()


def write_layout(path):
    # OpenCV camera looking horizontally along f with z up: x = f x up, y = down
    def cam(name, pos, f):
        x = (f[1], -f[0], 0.0)  # f x (0, 0, 1)
        return {"name": name, "position": list(pos), "orientation": _quat_from_matrix([x, (0.0, 0.0, -1.0), f])}

    data = {
        "frame_id": "omc",
        "room": {"min": [-3.0, -3.0, 0.0], "max": [6.0, 8.0, 2.0]},
        "cameras": [cam("c1", CAMS["c1"], (-1.0, 0.0, 0.0)), cam("c2", CAMS["c2"], (0.0, -1.0, 0.0)),
                    cam("c3", CAMS["c3"], (1.0, 0.0, 0.0))],
        # NDI frame looking along +y: z = (0, -1, 0) (volume along -z), y = up, x = y x z = (1, 0, 0)
        "ots": {"position": [5.0, 5.0, 1.0],
                "orientation": _quat_from_matrix([(1.0, 0.0, 0.0), (0.0, 0.0, 1.0), (0.0, -1.0, 0.0)])},
        "threshold": {"mode": "explicit", "deg": 150.0},
    }
    path.write_text(yaml.safe_dump(data))
    return path


# ------------------------------------------------------------------------------------------ publisher process
def run_publisher(rate: float) -> None:
    import rclpy
    from geometry_msgs.msg import PoseStamped

    rclpy.init()
    node = rclpy.create_node("margin_test_publisher")
    pubs = {name: node.create_publisher(PoseStamped, topic, 10) for name, topic in (
        ("base", "/omc/base/pose"), ("tool", "/fullperc/tool/pose"), ("probe", "/fullperc/probe/pose"),
        ("stray", "/fullperc/stray/pose"), ("flicker", "/fullperc/flicker/pose"))}
    k = 0

    def pose(frame, sec, p, q=(0.0, 0.0, 0.0, 1.0), nanosec=0):
        m = PoseStamped()
        m.header.frame_id = frame
        m.header.stamp.sec = sec
        m.header.stamp.nanosec = nanosec
        m.pose.position.x, m.pose.position.y, m.pose.position.z = p
        m.pose.orientation.x, m.pose.orientation.y, m.pose.orientation.z, m.pose.orientation.w = q
        return m

    try:
        while rclpy.ok():
            i = k % len(ORDER)
            name = ORDER[i]
            pubs["base"].publish(pose("omc", 1, *BASE_POSE))
            pubs["tool"].publish(pose("base", 100 + i, POINTS_BASE[name]))
            pubs["probe"].publish(pose("omc", 100 + i, POINTS_OMC[name]))
            pubs["stray"].publish(pose("ots", 100 + i, POINTS_OMC[name]))
            # a boundary crossed back and forth at every sample, stamps 10 ms apart: the hysteresis case
            ns = FLICKER_T0_NS + k * FLICKER_DT_NS
            pubs["flicker"].publish(pose("omc", ns // 10**9, POINTS_OMC["GP"[k % 2]], nanosec=ns % 10**9))
            k += 1
            time.sleep(1.0 / rate)
    except KeyboardInterrupt:
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


# ------------------------------------------------------------------------------------------------------ tests
def _spin_until(executor, pred, timeout, what):
    from fullperc_common.testing import wait_for

    def step():
        executor.spin_once(timeout_sec=0.05)
        return pred()

    return wait_for(step, timeout=timeout, interval=0.0, what=what)


@pytest.mark.system
def test_labels_latched_map_and_parameter_change(procs, rclpy_context, tmp_path, python_exe):
    import rclpy
    from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
    from rcl_interfaces.srv import SetParameters
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from visualization_msgs.msg import Marker, MarkerArray

    from fullperc_common.testing import installed_exe
    from fullperc_msgs.msg import Region

    layout_path = write_layout(tmp_path / "layout.yaml")
    node_proc = procs.start([installed_exe("fullperc_fusion", "margin_node"), "--ros-args",
                             "-p", f"layout_file:={layout_path}", "-p", "targets:=[tool, probe, stray, flicker]",
                             "-p", "map_resolution:=0.5"])
    # tool: fused pose in 'base'; probe: a pose already in the layout frame 'omc'; stray: in 'ots' (unplaceable)
    pub_proc = procs.start([python_exe, __file__, "--publish", "20"], name="publisher")

    node = rclpy.create_node("margin_test_listener", context=rclpy_context)
    ex = SingleThreadedExecutor(context=rclpy_context)
    ex.add_node(node)
    got: dict[str, list] = {"tool": [], "probe": [], "stray": [], "flicker": []}
    for t in got:
        node.create_subscription(Region, f"/fullperc/{t}/region", lambda m, t=t: got[t].append(m), 50)
    markers: list = []
    node.create_subscription(Marker, "/fullperc/tool/region_marker", markers.append, 50)

    def labels(target, threshold=None):
        out = {}
        for m in got[target]:
            # the threshold in force is the layout's -/+ the hysteresis band
            if 100 <= m.header.stamp.sec < 103 and m.label != Region.UNKNOWN and (
                    threshold is None or abs(m.threshold_deg - threshold) <= BAND):
                out[ORDER[m.header.stamp.sec - 100]] = m
        return out

    _spin_until(ex, lambda: len(labels("tool")) == 3 and len(labels("probe")) == 3 and got["stray"], 30,
                "region labels for every point of tool and probe")
    assert node_proc.poll() is None and pub_proc.poll() is None
    for target, frame, pts in (("tool", "base", POINTS_BASE), ("probe", "omc", POINTS_OMC)):
        lab = labels(target)
        assert lab["G"].label == Region.GVV and lab["B"].label == Region.BVV and lab["P"].label == Region.PVV
        g = lab["G"]
        assert g.margin_deg == pytest.approx(180.0, abs=1e-6) and g.valid_pairs == 2 and g.cameras_seeing == 3
        assert abs(g.threshold_deg - 150.0) <= BAND and not g.in_local_volume and lab["B"].in_local_volume
        assert lab["P"].margin_deg == 0.0 and lab["P"].cameras_seeing == 0
        for name, m in lab.items():
            assert m.target == target and m.header.frame_id == frame
            assert (m.position.x, m.position.y, m.position.z) == pytest.approx(pts[name])
    # the region marker of every label (issue 17 item 2): at the labelled position, coloured by the label
    from fullperc_fusion.margin_node import UNKNOWN_COLOR
    colors = {Region.BVV: (0.10, 0.65, 0.20), Region.GVV: (0.20, 0.45, 0.85), Region.PVV: (0.85, 0.20, 0.15),
              Region.UNKNOWN: UNKNOWN_COLOR}
    _spin_until(ex, lambda: len({m.header.stamp.sec for m in markers if 100 <= m.header.stamp.sec < 103}) == 3, 30,
                "region markers of tool")
    by_key = {(m.header.stamp.sec, m.label) for m in got["tool"]}
    for mk in markers:
        if not 100 <= mk.header.stamp.sec < 103:
            continue
        assert mk.type == Marker.SPHERE and mk.header.frame_id == "base" and mk.ns == "region/tool"
        assert (mk.pose.position.x, mk.pose.position.y, mk.pose.position.z) == pytest.approx(
            POINTS_BASE[ORDER[mk.header.stamp.sec - 100]])
        color = next(lbl for lbl, c in colors.items()
                     if (mk.color.r, mk.color.g, mk.color.b) == pytest.approx(c, abs=1e-6))
        assert (mk.header.stamp.sec, color) in by_key
    # a pose in a frame the node cannot place is answered with UNKNOWN, never a guessed label
    assert all(m.label == Region.UNKNOWN for m in got["stray"])

    # hysteresis: the model's label of 'flicker' changes at every sample (G/P every 10 ms); the published one at
    # most once per min_dwell of stamps, and every message is consistent (label vs margin vs threshold in force)
    _spin_until(ex, lambda: len(got["flicker"]) >= 60, 30, "60 region labels of the flickering target")
    fl = sorted(got["flicker"], key=lambda m: (m.header.stamp.sec, m.header.stamp.nanosec))
    stamps = [m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for m in fl]
    change_t = [stamps[i] for i in range(1, len(fl)) if fl[i].label != fl[i - 1].label]
    assert change_t, "the flickering target never changed label"
    assert all(b - a >= DWELL - 1e-6 for a, b in zip(change_t, change_t[1:], strict=False)), change_t
    assert len(change_t) <= (stamps[-1] - stamps[0]) / DWELL + 1
    for m in fl:
        assert m.label in (Region.GVV, Region.PVV)
        assert (m.margin_deg >= m.threshold_deg) == (m.label == Region.GVV), (m.label, m.margin_deg, m.threshold_deg)

    # late subscriber: the map published at start must still arrive (transient local)
    maps: list = []
    qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    node.create_subscription(MarkerArray, "/fullperc/margin_map", maps.append, qos)
    _spin_until(ex, lambda: maps, 20, "the latched margin map")
    ma = maps[0]
    assert ma.markers[0].action == Marker.DELETEALL
    by_ns = {m.ns: m for m in ma.markers[1:]}
    assert {"BVV", "GVV", "PVV", "cameras", "ots_volume"} <= set(by_ns)
    assert all(m.header.frame_id == "omc" for m in ma.markers[1:])
    assert sorted((p.x, p.y, p.z) for p in by_ns["cameras"].points) == sorted(CAMS.values())
    assert len(by_ns["ots_volume"].points) == 2 * (3 * 4 + 2 * 4)  # 3 cross-sections + 2 x 4 side edges
    assert by_ns["BVV"].points and by_ns["GVV"].points  # B and G are grid points of the 0.5 m map
    bvv = {(round(p.x, 3), round(p.y, 3), round(p.z, 3)) for p in by_ns["BVV"].points}
    gvv = {(round(p.x, 3), round(p.y, 3), round(p.z, 3)) for p in by_ns["GVV"].points}
    assert POINTS_OMC["B"] in bvv and POINTS_OMC["G"] in gvv

    # parameter change: threshold 500 deg -> G (margin 180) becomes PVV, and the map is published again
    client = node.create_client(SetParameters, "/margin_node/set_parameters")
    _spin_until(ex, lambda: client.service_is_ready(), 20, "the parameter service")

    def set_param(name, value):
        req = SetParameters.Request()
        pv = ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=value) if isinstance(value, float) \
            else ParameterValue(type=ParameterType.PARAMETER_STRING, string_value=value)
        req.parameters = [Parameter(name=name, value=pv)]
        fut = client.call_async(req)
        _spin_until(ex, fut.done, 20, f"set_parameters {name}")
        return fut.result().results[0]

    res = set_param("hysteresis.min_dwell", -1.0)
    assert not res.successful and "hysteresis.min_dwell" in res.reason
    assert set_param("hysteresis.min_dwell", 0.1).successful

    n_maps = len(maps)
    assert set_param("threshold_deg", 500.0).successful
    _spin_until(ex, lambda: len(maps) > n_maps, 20, "a new map after the parameter change")
    _spin_until(ex, lambda: "G" in labels("tool", 500.0), 20, "labels with the new threshold")
    assert labels("tool", 500.0)["G"].label == Region.PVV

    # an invalid layout file is rejected with the file and field named; the old layout stays in force
    bad = tmp_path / "bad.yaml"
    data = yaml.safe_load(layout_path.read_text())
    data["cameras"][2]["range_m"] = -1.0
    bad.write_text(yaml.safe_dump(data))
    res = set_param("layout_file", str(bad))
    assert not res.successful and str(bad) in res.reason and "cameras[2].range_m" in res.reason
    got["tool"].clear()
    _spin_until(ex, lambda: len(labels("tool")) == 3, 20, "labels after the rejected change")
    assert all(abs(m.threshold_deg - 500.0) <= BAND for m in labels("tool").values())
    assert node_proc.poll() is None
    # all of the above on the EventsExecutor, margin_node's default: the layout change is polled by a timer, as
    # rclpy 7.1's EventsExecutor runs no guard condition (a node with one says so and spins on 'single')
    assert "not usable" not in procs.log(node_proc), procs.log(node_proc)
    node.destroy_node()


@pytest.mark.system
def test_bad_layout_fails_at_start_naming_file_and_field(procs, tmp_path):
    from fullperc_common.testing import installed_exe, wait_for

    path = write_layout(tmp_path / "layout.yaml")
    data = yaml.safe_load(path.read_text())
    del data["cameras"][1]["orientation"]
    path.write_text(yaml.safe_dump(data))
    p = procs.start([installed_exe("fullperc_fusion", "margin_node"), "--ros-args", "-p", f"layout_file:={path}"])
    wait_for(lambda: p.poll() is not None, 20, what="margin_node to exit")
    log = procs.log(p)
    assert p.returncode == 2
    assert str(path) in log and "cameras[1].orientation" in log and "missing" in log


@pytest.mark.system
@pytest.mark.parametrize("arg", ["hysteresis.margin_band_deg:=-1.0", "hysteresis.min_dwell:=-0.2"])
def test_bad_hysteresis_parameter_fails_at_start_naming_it(procs, arg):
    from fullperc_common.testing import installed_exe, wait_for

    p = procs.start([installed_exe("fullperc_fusion", "margin_node"), "--ros-args", "-p", arg,
                     "-p", "publish_map:=false"], name="bad_hysteresis")
    wait_for(lambda: p.poll() is not None, 20, what="margin_node to exit")
    assert p.returncode == 2
    assert f"'{arg.split(':=')[0]}'" in procs.log(p)


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--publish":
        run_publisher(float(sys.argv[2]))
    else:
        sys.exit("usage: test_margin_node.py --publish RATE")
