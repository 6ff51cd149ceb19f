"""``supervisor`` executable: ``run GRAPH`` (any process graph, :mod:`.supervisor`) or ``demo`` (:mod:`.demo`).

The command line sits apart from both so that neither imports the other: the demo runs its graph with the
supervisor, and the supervisor knows nothing of the demo.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from . import supervisor
from .demo import run_demo
from .supervisor import GraphError, run_graph


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="supervisor", description=supervisor.__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run", help="run a graph file")
    r.add_argument("graph")
    r.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    r.add_argument("--logs", default="log/supervisor")
    r.add_argument("--timeout", type=float, default=None, help="shut down after S seconds")
    d = sub.add_parser("demo", help="the simulated-OR demo (see docs/demo.md)")
    d.add_argument("--task", default="P-B-G-P")
    d.add_argument("--seed", default="0")
    d.add_argument("--out", default="demo_out")
    d.add_argument("--speed", default="1.0", help="simulation speed (1.0 = real time)")
    d.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                   help="graph variable, e.g. vega_outage=8:14 (switch the Vega off from task second 8 to 14)")
    d.add_argument("--profile", default="paper", choices=("paper", "spec", "base"),
                   help="twin profile the simulator plays (default paper; base = scene.yaml alone)")
    d.add_argument("--calibration", type=Path, default=None, metavar="FILE",
                   help="static-link calibration YAML for fusion_node (calibration_file) and the offline evaluation "
                        "(default: fusion_node calibrates itself)")
    d.add_argument("--graph", type=Path, default=None,
                   help="graph file (default: the installed config/demo_graph.yaml)")
    args = ap.parse_args(argv)
    root = Path(os.environ.get("FULLPERC_ROOT", os.getcwd()))
    try:
        if args.cmd == "run":
            values = dict(kv.split("=", 1) for kv in args.set)
            return run_graph(args.graph, values, Path(args.logs), root, args.timeout)
        return run_demo(task=args.task, seed=args.seed, out=Path(args.out), root=root, speed=args.speed,
                        extra=dict(kv.split("=", 1) for kv in args.set), graph=args.graph, profile=args.profile,
                        calibration=args.calibration)
    except GraphError as e:
        print(f"supervisor: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # Ctrl-C after the graph stopped (e.g. during the evaluation): no traceback
        print(f"{args.cmd}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
