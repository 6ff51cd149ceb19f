"""Soak: each of the five installed nodes is stopped with SIGINT while data flows, 20 times (issue 14 item 3).

One run = start the node, wait until new messages of its output topic arrive in this process, send SIGINT,
collect the exit. Clean = exit status 0 and no "Traceback" in the node's output. Prints one JSON line per node
(the bench/benchlib.py line format, with ``of`` = runs):

  {"name": "sigint_clean_exits[fusion_node]", "value": 20, "unit": "count", "of": 20}

and, on stderr, why each unclean run was unclean with the tail of its log. Exit status 1 if any run was
unclean. ``make test`` runs the same cycle 3x SIGINT + 1x SIGTERM per node (test/test_node_lifecycle.py).

  source scripts/env.sh && python soak/soak_signals.py [--runs 20] [--nodes fusion_node margin_node]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "test"))

from lifecycle_nodes import NODES, msg_type, signal_cycle, start_feed  # noqa: E402

from fullperc_common.testing import Procs, TopicCounter  # noqa: E402


def soak_node(name: str, runs: int, tmp: Path, env: dict[str, str]) -> tuple[int, list[str]]:
    import rclpy
    from rclpy.context import Context

    spec = NODES[name]
    procs = Procs(env, tmp)
    ctx = Context()
    rclpy.init(context=ctx)
    counter = None
    problems: list[str] = []
    clean = 0
    try:
        ros_args = start_feed(procs, spec, tmp)
        counter = TopicCounter(ctx, {spec.output: msg_type(spec.output_type)}, node_name="soak_signals_counter")
        for k in range(runs):
            r = signal_cycle(procs, spec, ros_args, counter, signal.SIGINT, k)
            if r.clean:
                clean += 1
            else:
                problems.append(f"{name} run {k + 1}: {r.problem} ({r.flowed} messages flowed)\n{r.log[-2000:]}")
    finally:
        if counter is not None:
            counter.close()
        procs.stop_all()
        rclpy.try_shutdown(context=ctx)
    return clean, problems


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--nodes", nargs="+", default=list(NODES), choices=list(NODES))
    ap.add_argument("--domain", type=int, default=None, help="ROS_DOMAIN_ID (default: derived from the pid)")
    a = ap.parse_args()

    domain = a.domain if a.domain is not None else 1 + (os.getpid() * 13 + 50) % 100
    os.environ.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONUNBUFFERED="1")
    env = dict(os.environ)
    tmp = Path(tempfile.mkdtemp(prefix="soak_signals_"))
    all_clean = True
    for name in a.nodes:
        node_tmp = tmp / name
        node_tmp.mkdir()
        clean, problems = soak_node(name, a.runs, node_tmp, env)
        print(json.dumps({"name": f"sigint_clean_exits[{name}]", "value": clean, "unit": "count", "of": a.runs}),
              flush=True)
        for p in problems:
            print(p, file=sys.stderr, flush=True)
        all_clean &= clean == a.runs
    if all_clean:
        shutil.rmtree(tmp, ignore_errors=True)
    else:
        print(f"logs kept in {tmp}", file=sys.stderr)
    return 0 if all_clean else 1


if __name__ == "__main__":
    sys.exit(main())
