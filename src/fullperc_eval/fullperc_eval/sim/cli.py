"""``sim`` executable: the OR digital twin serving the device streams (ROS-free process).

    sim --task P-B-G-P --seed 0 --speed 1.0            # plays one task in real time, then exits
    sim --task G-B-P --speed 4 --vega-port 0 --loop    # 4x faster, any free Vega port, repeat forever
    sim --task P-G-B --save-npz /tmp/run.npz --no-serve   # offline arrays with ground truth only
    sim --task P-B-G-P --vega-bump 12:0.005:0.3        # the Vega stand bumped 12 s into the task

Defaults: OMC UDP frames to 127.0.0.1:3883, Diana UDP joint states to 127.0.0.1:3884, NDI Vega emulator on
TCP 127.0.0.1:8765 (``--vega-port 0``: a free port, printed in the ``start`` record and written to
``--vega-port-file``; ``--vega-port -1``: no Vega). ROS-style parameters are accepted too
(``--ros-args -p task:=P-B-G -p seed:=3 -p speed:=2.0``), so a launcher can treat it like a node.
Stdout: JSON lines (plan, start, region changes, end). Ctrl-C / SIGTERM stop it cleanly.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import time

import numpy as np

from fullperc_eval.bag.calibration import save_calibration
from fullperc_eval.bag.errors import BagError
from fullperc_fusion.margin.layout import load_layout

from .dataset import sim_calibration, write_truth_bag
from .live import LiveServer
from .run import simulate
from .scene import DEFAULT_PROFILE, PROFILES, VegaBump, build_scene
from .targets import add_targets
from .tasks import TASKS, TaskPlanningError, plan_task


def _addr(s: str) -> tuple[str, int]:
    host, _, port = s.rpartition(":")
    try:
        return (host or "127.0.0.1", int(port))
    except ValueError as e:
        raise argparse.ArgumentTypeError(f"expected host:port, got {s!r}") from e


def _ros_params(argv: list[str]) -> list[str]:
    """Turn ``--ros-args -p name:=value ...`` into ``--name value`` (other ROS args are ignored)."""
    if "--ros-args" not in argv:
        return argv
    i = argv.index("--ros-args")
    out, rest = argv[:i], argv[i + 1:]
    k = 0
    while k < len(rest):
        if rest[k] in ("-p", "--param") and k + 1 < len(rest) and ":=" in rest[k + 1]:
            name, val = rest[k + 1].split(":=", 1)
            flag = "--" + name.replace("_", "-")
            if val.lower() in ("true", "false"):
                if val.lower() == "true":
                    out.append(flag)
            else:
                out += [flag, val]
            k += 2
        else:
            k += 1
    return out


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="sim", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--task", default="P-B-G-P", choices=TASKS)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--profile", default=DEFAULT_PROFILE, choices=(*PROFILES, "base"),
                    help=f"twin profile (default {DEFAULT_PROFILE}; base = scene.yaml alone)")
    ap.add_argument("--speed", type=float, default=1.0, help="1.0 = real time, 2.0 = twice as fast")
    ap.add_argument("--omc-addr", type=_addr, default=("127.0.0.1", 3883))
    ap.add_argument("--diana-addr", type=_addr, default=("127.0.0.1", 3884))
    ap.add_argument("--vega-host", default="127.0.0.1")
    ap.add_argument("--vega-port", type=int, default=8765, help="0 = any free port, -1 = no Vega emulator")
    ap.add_argument("--vega-port-file", help="write the bound Vega TCP port here once listening")
    ap.add_argument("--device-clock-offset-ns", type=int, default=0,
                    help="device clocks run this far ahead of the host clock (tests the drivers' clock mapping)")
    ap.add_argument("--start-delay", type=float, default=0.5, help="seconds between start-up and the task start")
    ap.add_argument("--start-when-tracking", type=float, default=0.0, metavar="TIMEOUT_S",
                    help="before --start-delay, wait up to this long until a driver has started tracking on the "
                         "Vega emulator (0 = do not wait)")
    ap.add_argument("--loop", action="store_true", help="repeat the task until stopped")
    ap.add_argument("--scene", help="scene.yaml (default: installed fullperc_eval/config/scene.yaml)")
    ap.add_argument("--layout", help="camera layout (default: installed fullperc_fusion/config/or_layout.yaml)")
    ap.add_argument("--save-npz", help="also write the offline arrays (measurements + ground truth) here")
    ap.add_argument("--no-serve", action="store_true", help="only simulate (and --save-npz), do not serve")
    ap.add_argument("--vega-outage", default="", metavar="A:B",
                    help="switch the Vega emulator off from task second A to B (as if killed), then start a fresh "
                         "one on the same port, as a power-cycled device would come back")
    ap.add_argument("--vega-bump", default="", metavar="AT:DX[:TILT]",
                    help="bump the Vega stand at task second AT: the Vega head and its OMC rig body ots_rig move by DX "
                         "metres along omc x and tilt by TILT degrees about omc y (what fusion_node's link monitor "
                         "must report)")
    ap.add_argument("--truth-out", metavar="DIR",
                    help="after the task, write the extra targets' true poses (host-clock stamps of the served run) "
                         "as a bag with /sim/truth/<target> here (the demo merges it into its recording)")
    ap.add_argument("--calibration-out", help="write the run's calibration.yaml (true T_base_diana_base, "
                    "T_flange_tool) here, for evaluating a recording of this run")
    return ap


def _vega_outage(server, off_s: float, on_s: float) -> None:
    """Kill the Vega emulator ``off_s`` host seconds into the task and start a fresh one at ``on_s``."""
    started = time.time_ns()
    # the task starts when serve() has started the emulator and set t0 (after this thread started)
    while server.vega is None or not (getattr(server, "t0_host_ns", 0) or 0) > started:
        if server._stop.wait(0.01):
            return
    t0 = server.t0_host_ns / 1e9
    for at, what in ((off_s, "off"), (on_s, "on")):
        delay = t0 + at - time.time()
        if delay > 0 and server._stop.wait(delay):
            return
        if what == "off":
            server.vega.stop()
        else:
            server._start_vega()
        print(json.dumps({"event": "vega_" + what, "t_host_ns": time.time_ns()}), flush=True)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(_ros_params(list(sys.argv[1:] if argv is None else argv)))
    if not args.speed > 0:
        print(f"sim: --speed must be > 0, got {args.speed}", file=sys.stderr)
        return 2
    try:
        bump = VegaBump.parse(args.vega_bump) if args.vega_bump else None
    except ValueError as e:
        print(f"sim: --vega-bump: {e}", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    layout = load_layout(args.layout) if args.layout else None
    scene = build_scene(args.seed, config=args.scene, layout=layout, profile=args.profile)
    try:
        plan = plan_task(args.task, scene)
    except TaskPlanningError as e:
        print(f"sim: {e}", file=sys.stderr, flush=True)
        return 3
    scene = scene.with_diana_base(plan.T_omc_diana_base).with_vega_bump(bump)
    run = add_targets(simulate(scene, plan.arc, task=args.task), scene)
    run.info["profile"] = scene.config.get("_profile", "base")
    print(json.dumps({"event": "plan", "task": args.task, "seed": args.seed, "profile": args.profile,
                      "joint": plan.arc.joint,
                      "arc_deg": [round(float(np.degrees(a)), 2) for a in (plan.arc.start, plan.arc.end)],
                      "duration_s": run.duration_s, "ots_fraction_b": round(plan.ots_fraction_b, 3),
                      "compute_s": round(time.perf_counter() - t0, 2)}), flush=True)
    if args.save_npz:
        run.save_npz(args.save_npz)
    if args.calibration_out:
        save_calibration(args.calibration_out, sim_calibration(run))
    if args.no_serve:
        return 0

    server = LiveServer(run, speed=args.speed, omc_addr=args.omc_addr, diana_addr=args.diana_addr,
                        vega_port=None if args.vega_port < 0 else args.vega_port, vega_host=args.vega_host,
                        device_clock_offset_ns=args.device_clock_offset_ns, frustum=scene.layout.frustum)

    def _stop(*_):
        server.stop()

    signal.signal(signal.SIGINT, _stop)
    signal.signal(signal.SIGTERM, _stop)
    if args.vega_port_file and args.vega_port >= 0:
        server._start_vega()
        with open(args.vega_port_file, "w") as f:
            f.write(str(server.vega.port))
    if args.vega_outage and args.vega_port >= 0:
        a, b = (float(x) for x in args.vega_outage.split(":"))
        threading.Thread(target=_vega_outage, args=(server, a / args.speed, b / args.speed), daemon=True).start()
    server.serve(start_delay_s=args.start_delay, loops=0 if args.loop else 1,
                 wait_for_tracking_s=args.start_when_tracking)
    if args.truth_out and run.extra_truth and server.t0_host_ns:
        # stamps as the drivers publish them: capture time on the host clock (the last served loop)
        truth = {n: (np.array([server.host_ns(t) for t in tr.t_ns], dtype=np.int64), tr.T_base_tool)
                 for n, tr in run.extra_truth.items()}
        try:
            write_truth_bag(args.truth_out, truth, {"task": args.task, "seed": str(args.seed)})
        except (OSError, BagError) as e:
            print(f"sim: --truth-out {args.truth_out}: {e}", file=sys.stderr, flush=True)
            return 1
        print(json.dumps({"event": "truth", "targets": sorted(truth), "path": args.truth_out}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
