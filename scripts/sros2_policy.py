"""Write the SROS2 policy of the demo graph from the nodes' own topic lists (docs/security.md).

Starts every ROS node of ``config/demo_graph.yaml`` (not the simulator: it talks UDP/TCP, not DDS) with the graph's
own command lines and parameters, through the supervisor, so each node is ready exactly as in ``make demo`` (the
drivers create their publishers for the configured bodies and tools without a device; the NDI driver retries its
connection meanwhile). Then reads, from the ROS graph, what each node publishes, subscribes to, serves and calls
(``get_publisher_names_and_types_by_node`` and friends -- what ``ros2 security generate_policy`` reads, which the
wheel path does not have), waits until that stayed the same for ``--settle`` seconds (discovery delivers a
participant's endpoints over seconds), stops the graph and writes one enclave per node
(:mod:`fullperc_eval.graph.sros2_policy`).

Why introspection and not a list kept by hand: the topics follow from parameters (targets, bodies, tools, side-by-
side filters) and from code; a hand-kept list drifts, and a permission missing under ``ROS_SECURITY_STRATEGY=Enforce``
is a node that silently gets no data. A node that is not running when this runs gets no enclave (the script fails).

Run (any machine; the policy is then used on a system ROS 2 install, docs/security.md):
    source scripts/env.sh && python scripts/sros2_policy.py --out policy.xml
Exit 0 with the file written, 1 when a node did not start or the graph did not settle within ``--timeout``.
"""

from __future__ import annotations

import argparse
import os
import signal
import socket
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

from fullperc_eval.graph.demo import free_port, graph_path
from fullperc_eval.graph.sros2_policy import DEFAULT_PREFIX, NodeAccess, enclave_path, policy_xml
from fullperc_eval.graph.supervisor import Graph, GraphError, Supervisor, load_graph

NOT_ROS = ("sim",)   # processes of the demo graph that create no ROS node
INTROSPECTOR = "_fullperc_sros2_policy"   # hidden (leading _): left out of the policy, as generate_policy does


def demo_values(out: Path) -> dict[str, str]:
    """Values for the demo graph's placeholders: free ports (nothing listens on the Vega's: the NDI driver retries),
    a scratch output folder, and an identity arm base (it changes a /tf_static transform, not a topic)."""
    return {"task": "P-B-G-P", "seed": "0", "out": str(out), "speed": "1.0",
            "omc_port": str(free_port(socket.SOCK_DGRAM)), "diana_port": str(free_port(socket.SOCK_DGRAM)),
            "vega_port": str(free_port(socket.SOCK_STREAM)), "diana_base": "[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]"}


def ros_nodes_only(graph: Graph, skip: tuple[str, ...]) -> Graph:
    """The graph without the processes named in ``skip`` (also dropped from its stop stages)."""
    stages = None
    if graph.stop_stages is not None:
        stages = [s for s in ([n for n in st if n not in skip] for st in graph.stop_stages) if s]
    return replace(graph, processes=[p for p in graph.processes if p.name not in skip], stop_stages=stages)


def snapshot(node) -> dict[tuple[str, str], NodeAccess]:
    """(namespace, name) -> what that node uses, for every visible node of the graph but hidden ones (``_*``)."""
    from rclpy.node import NodeNameNonExistentError

    out = {}
    for name, ns in node.get_node_names_and_namespaces():
        if not name or name.startswith("_"):
            continue
        try:
            def names(fn, name=name, ns=ns) -> frozenset[str]:
                return frozenset(t for t, _types in fn(name, ns))

            out[(ns, name)] = NodeAccess(
                name, ns, publish=names(node.get_publisher_names_and_types_by_node),
                subscribe=names(node.get_subscriber_names_and_types_by_node),
                reply=names(node.get_service_names_and_types_by_node),
                request=names(node.get_client_names_and_types_by_node))
        except NodeNameNonExistentError:   # it left the graph between the two calls: the next snapshot differs
            continue
    return out


def settle(node, sup: Supervisor, expect: int, settle_s: float, timeout: float) -> list[NodeAccess]:
    """The graph's nodes once ``expect`` of them (one per process) are seen and nothing changed for ``settle_s`` s.

    A liveness bound (``timeout``), not a speed requirement: on a busy machine discovery takes longer and the
    result is the same. Raises RuntimeError (naming the process) when a node exits meanwhile."""
    end = time.monotonic() + timeout
    prev: dict | None = None
    since = time.monotonic()
    while True:
        for r in sup.running:
            if r.popen.poll() is not None:
                raise RuntimeError(f"{r.spec.name} exited (code {r.popen.returncode}); see {r.log_path}")
        snap = snapshot(node)
        now = time.monotonic()
        if snap != prev:
            prev, since = snap, now
        elif now - since >= settle_s and len(snap) == expect:
            return list(snap.values())
        elif now - since >= settle_s and len(snap) > expect:   # another graph on this domain: its nodes would
            raise RuntimeError(                                 # get enclaves too
                f"{len(snap)} nodes on ROS_DOMAIN_ID {os.environ.get('ROS_DOMAIN_ID', '0')} for {expect} processes "
                f"({', '.join(sorted(n for _, n in snap))}): run on a domain of its own")
        if now > end:
            raise RuntimeError(f"the graph did not settle within {timeout:.0f} s: {len(snap)} of {expect} nodes seen "
                               f"({', '.join(sorted(n for _, n in snap)) or 'none'})")
        time.sleep(0.25)


def introspect(graph_file: Path, root: Path, logs: Path, skip: tuple[str, ...], settle_s: float,
               timeout: float) -> list[NodeAccess]:
    """Run the graph's ROS nodes, read what each uses, stop them; raises RuntimeError when that fails."""
    import rclpy
    from rclpy.context import Context

    with tempfile.TemporaryDirectory(prefix="sros2_policy_") as scratch:
        graph = ros_nodes_only(load_graph(graph_file, demo_values(Path(scratch))), skip)
        sup = Supervisor(graph, logs, root, out=sys.stderr)
        old = signal.signal(signal.SIGTERM, signal.default_int_handler)   # SIGTERM too stops the graph below
        context = None
        try:
            if not sup.start():
                raise RuntimeError(f"the graph did not start: {sup.reason}")
            # the introspecting participant is made after the nodes: a new participant is matched with the existing
            # ones' endpoints at once, instead of at their next periodic announcement
            context = Context()
            rclpy.init(context=context)
            node = rclpy.create_node(INTROSPECTOR, context=context)
            try:
                return settle(node, sup, len(graph.processes), settle_s, timeout)
            finally:
                node.destroy_node()
        finally:
            if context is not None:
                rclpy.shutdown(context=context)
            codes = sup.shutdown()
            signal.signal(signal.SIGTERM, old)
            if bad := {k: v for k, v in codes.items() if v != 0}:
                print(f"sros2_policy: exit codes at shutdown: {bad} (logs in {logs})", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=Path("policy.xml"), help="policy file to write (policy.xml)")
    ap.add_argument("--graph", type=Path, default=None, help="graph file (default: the demo graph)")
    ap.add_argument("--skip", nargs="*", default=list(NOT_ROS), help="processes that are not ROS nodes (sim)")
    ap.add_argument("--prefix", default=DEFAULT_PREFIX, help="enclave prefix (/fullperc: /fullperc/<node>)")
    ap.add_argument("--settle", type=float, default=4.0,
                    help="seconds the graph must stay unchanged (> Fast DDS's 3 s announcement period)")
    ap.add_argument("--timeout", type=float, default=300.0, help="liveness bound for the nodes to appear [s]")
    ap.add_argument("--logs", type=Path, default=Path("log/sros2_policy"), help="the nodes' logs")
    args = ap.parse_args(argv)
    root = Path(os.environ.get("FULLPERC_ROOT", os.getcwd()))
    try:
        nodes = introspect(args.graph or graph_path(root), root, args.logs, tuple(args.skip), args.settle,
                           args.timeout)
    except (GraphError, RuntimeError, KeyboardInterrupt) as e:
        print(f"sros2_policy: {e or 'interrupted'}", file=sys.stderr)
        return 1
    args.out.write_text(policy_xml(nodes, args.prefix))
    print(f"wrote {args.out}: {len(nodes)} enclaves (ROS_DOMAIN_ID={os.environ.get('ROS_DOMAIN_ID', '0')})")
    for n in sorted(nodes, key=lambda n: (n.ns, n.node)):
        print(f"  {enclave_path(n.node, n.ns, args.prefix)}: publishes {len(n.publish)}, subscribes "
              f"{len(n.subscribe)}, serves {len(n.reply)}, calls {len(n.request)} "
              f"(run it with --ros-args --enclave {enclave_path(n.node, n.ns, args.prefix)})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
