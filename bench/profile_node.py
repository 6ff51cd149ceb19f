"""Where fusion_node's CPU goes under the live bench load: py-spy samples of the node, split by what runs.

Runs the ``live_fusion`` harness (publisher at OMC 240 Hz + OTS 400 Hz per target, the installed fusion_node with
its defaults, primary filter only unless ``--filters``) and attaches ``py-spy record --native`` to the node once data
flows (``--delay`` s after the node starts, for ``--record`` s). Each sample's stack is put in one row:

  exec:wait/ready        the executor outside any callback (SingleThreadedExecutor: wait set, ready list, Task)
  exec:take              the executor taking/deserialising a message before the callback
  cb:take_queued         fusion_node draining the other input subscriptions (take + deserialise)
  cb:pipeline            pushing samples into the target pipelines (mapping, filters, rewind-and-replay)
  cb:static_links        the static-link estimation inside the pipeline (calibrate mode's robust mean)
  cb:publish             building and publishing pose / pose_cov / status / tf
  cb:other, timer:*, ... the rest

py-spy sees only threads that run Python (the main thread here); the node's other threads (Fast DDS) are
reported from /proc as ``other_threads_cpu_s`` beside ``main_thread_cpu_s``. py-spy pauses the process per
sample, so the node runs slower while recorded: the shares matter, not the latencies of such a run. With
``--native`` the samples inside a native call can include time the thread waits there (py-spy's idle test is a
heuristic), e.g. a DDS write on its lock: read ``cb:publish``'s share as an upper bound of publishing's CPU.
Not a figure of ``make bench`` (needs py-spy: ``pip install py-spy``).

Run: python bench/profile_node.py [--targets 1] [--filters all|ckf,fullperc,...] [--executor events|single]
     [--seconds 20] [--out FILE]
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import live_fusion  # noqa: E402

ROWS = (("_on_input", "input_sample", "cb:read_cdr"), ("_on_input", "take_queued", "cb:take_queued"),
        ("_on_input", "StaticLinks", "cb:static_links"),
        ("_on_input", "on_pose", "cb:pipeline"), ("_on_input", "publish", "cb:publish"),
        ("_on_input", "", "cb:other"), ("_on_quality", "", "cb:quality"), ("_on_timer", "", "timer:_on_timer"),
        ("_update_diagnostics", "", "timer:diagnostics"))


def row(stack: str) -> str:
    """The row of one sampled stack (``;``-separated frames, outermost first)."""
    if "run_node" not in stack:
        return "startup/other"
    for outer, inner, name in ROWS:
        if outer in stack and inner in stack.split(outer, 1)[1]:
            return name
    if "take_message" in stack or "_take_subscription" in stack:
        return "exec:take"
    if "spin_once" in stack:
        return "exec:wait/ready"
    return "main:other"


def thread_cpu(pid: int) -> dict[str, float]:
    """CPU seconds per thread of ``pid`` (main = the thread whose id is the pid)."""
    out = {"main": 0.0, "other": 0.0}
    tck = os.sysconf("SC_CLK_TCK")
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            f = (task / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        out["main" if task.name == str(pid) else "other"] += (int(f[11]) + int(f[12])) / tck
    return out


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--targets", type=int, default=1)
    ap.add_argument("--executor", choices=("events", "single"), default=None)
    ap.add_argument("--seconds", type=float, default=20.0, help="seconds of data")
    ap.add_argument("--delay", type=float, default=10.0, help="start recording this long after the node started")
    ap.add_argument("--record", type=float, default=8.0, help="seconds recorded")
    ap.add_argument("--filters", default="", help="side-by-side filters (comma-separated; 'all': every registered one)")
    ap.add_argument("--out", default=str(Path(tempfile.gettempdir()) / "fusion_node_profile.txt"),
                    help="py-spy raw output")
    a = ap.parse_args()
    spies: list[subprocess.Popen] = []
    cpu: dict[str, dict[str, float]] = {}
    real_popen = subprocess.Popen

    class Popen(real_popen):   # attach py-spy to the fusion_node the harness starts
        def __init__(self, args, *pa, **kw) -> None:
            super().__init__(args, *pa, **kw)
            if str(args[0]).endswith("fusion_node"):
                threading.Thread(target=self._spy, daemon=True).start()

        def _spy(self) -> None:
            time.sleep(a.delay)
            cpu["start"] = thread_cpu(self.pid)
            spies.append(real_popen(["py-spy", "record", "--pid", str(self.pid), "-r", "100", "-f", "raw",
                                     "--native", "-o", a.out, "-d", str(int(a.record))],
                                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
            time.sleep(a.record)
            cpu["end"] = thread_cpu(self.pid)

    live_fusion.subprocess.Popen = Popen
    targets = [f"t{k}" for k in range(a.targets)]
    extra: list[str] = []
    if a.filters:
        names = live_fusion.every_filter()[1] if a.filters == "all" else a.filters.split(",")
        extra = ["-p", f"filters:=[{', '.join(names)}]"]
    res = live_fusion.run_live([live_fusion.target_params(targets) + extra], targets, 170 + os.getpid() % 30, a.seconds,
                               executor=a.executor)
    for s in spies:
        s.wait()
    rows: collections.Counter[str] = collections.Counter()
    for line in Path(a.out).read_text().splitlines():
        if line.strip():
            stack, n = line.rsplit(" ", 1)
            rows[row(stack)] += int(n)
    total = sum(rows.values()) or 1
    d = {k: round(cpu["end"][k] - cpu["start"][k], 2) for k in ("main", "other")} if "end" in cpu else {}
    print(json.dumps({"executor": a.executor or "node default", "targets": a.targets, "samples": total,
                      "shares": {k: round(v / total, 3) for k, v in rows.most_common()},
                      "main_thread_cpu_s": d.get("main"), "other_threads_cpu_s": d.get("other"),
                      "recorded_s": a.record, "lost": int(sum(res.lost.values())), "load": res.load}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
