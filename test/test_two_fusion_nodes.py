"""System test: the example graph config/two_fusion_nodes.yaml -- targets partitioned over two fusion_node processes.

The supervisor loads the graph and starts both processes on a private domain; stand-in drivers in this process
publish OMC and OTS poses of the base marker and of every target; each target's fused pose must arrive, published
by the process whose params file lists that target and by no other. Tolerant of a busy machine: generous waits,
no rate or latency bound.
"""

from __future__ import annotations

import io
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from fullperc_common.testing import poll_until, workspace_root
from fullperc_eval.graph.supervisor import Supervisor, load_graph

pytestmark = pytest.mark.system

ROOT = workspace_root()
CONFIG = ROOT / "src" / "fullperc_eval" / "config"
GRAPH = CONFIG / "two_fusion_nodes.yaml"
FUSED_WANTED = 20          # fused poses per target


def _partition(graph) -> dict[str, list[str]]:
    """process name -> targets, read from the params file each process's command line names."""
    out = {}
    for p in graph.processes:
        params = Path(p.cmd[p.cmd.index("--params-file") + 1])
        node = p.cmd[p.cmd.index("-r") + 1].split(":=")[1]
        doc = yaml.safe_load(params.read_text())
        out[node] = list(doc[node]["ros__parameters"]["targets"])
    return out


def test_graph_loads_and_partitions_the_targets() -> None:
    graph = load_graph(GRAPH, {"params_dir": str(CONFIG)})
    assert [p.cmd[0] for p in graph.processes] == ["fullperc_fusion/fusion_node"] * 2
    parts = _partition(graph)
    assert len(parts) == 2
    a, b = parts.values()
    assert a and b and not set(a) & set(b), parts


def test_two_processes_publish_their_targets(tmp_path: Path, ros_env: dict[str, str]) -> None:
    # ros_env: a domain id of this test's own, set in this process's environment, which the supervisor
    # passes on to both nodes
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from rclpy.context import Context
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    from fullperc_common.ros_conv import pose_stamped
    from fullperc_common.testing import SpunNode
    from fullperc_common.transforms import T_to_pq, inv_T, make_T

    graph = load_graph(GRAPH, {"params_dir": str(CONFIG)})
    parts = _partition(graph)
    targets = [t for ts in parts.values() for t in ts]
    out = io.StringIO()
    sup = Supervisor(graph, tmp_path / "logs", ROOT, out=out)
    ctx = Context()
    rclpy.init(context=ctx)
    listener = SpunNode(ctx, "two_nodes_listener")
    got: dict[str, int] = dict.fromkeys(targets, 0)
    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)

    def count(t: str) -> None:
        with listener.lock:
            got[t] += 1

    for t in targets:
        listener.node.create_subscription(PoseStamped, f"/fullperc/{t}/pose", lambda _m, t=t: count(t), qos)
    listener.start()
    pub_node = rclpy.create_node("two_nodes_drivers", context=ctx)
    pubs = {f"/{d}/{b}/pose": pub_node.create_publisher(PoseStamped, f"/{d}/{b}/pose", qos)
            for d in ("omc", "ots") for b in ("base", *targets)}
    try:
        assert sup.start(), out.getvalue()
        T_omc_base = make_T([1.0, 0.5, 0.8], [0, 0, 0.2588190451, 0.9659258263])
        T_ots_omc = inv_T(make_T([3.0, 1.0, 1.5], [0, 0, 0.9659258263, 0.2588190451]))
        rng = np.random.default_rng(0)
        end = time.monotonic() + 180
        k = 0
        while time.monotonic() < end:
            with listener.lock:
                if min(got.values()) >= FUSED_WANTED:
                    break
            ns = time.time_ns()
            for dev, T_dev in (("omc", np.eye(4)), ("ots", T_ots_omc)):
                p, q = T_to_pq(T_dev @ T_omc_base)
                pubs[f"/{dev}/base/pose"].publish(pose_stamped(ns, dev, p, q))
                for i, t in enumerate(targets):
                    T = T_omc_base @ make_T([0.3 + 0.05 * i, 0.01 * np.sin(k / 50), 0.2])
                    T[:3, 3] += rng.normal(0, 1e-4, 3)
                    p, q = T_to_pq(T_dev @ T)
                    pubs[f"/{dev}/{t}/pose"].publish(pose_stamped(ns, dev, p, q))
            k += 1
            time.sleep(0.01)
        with listener.lock:
            final = dict(got)
        assert min(final.values()) >= FUSED_WANTED, (final, out.getvalue()[-2000:])
        for node, ts in parts.items():
            for t in ts:
                owners = poll_until(lambda t=t: {i.node_name for i in
                                                 pub_node.get_publishers_info_by_topic(f"/fullperc/{t}/pose")},
                                    timeout=20)
                assert owners == {node}, (t, owners)
        assert all(r.popen.poll() is None for r in sup.running), out.getvalue()[-2000:]
    finally:
        pub_node.destroy_node()
        listener.close()
        rclpy.shutdown(context=ctx)
        codes = sup.shutdown()
    assert set(codes) == set(parts) and all(c == 0 for c in codes.values()), (codes, out.getvalue()[-2000:])
