"""CPU of every process of the demo graph over one whole run: where a live OR setup spends its cores.

Runs ``supervisor demo --task B-G-P --set vega_outage=6:12`` (the graph of ``make demo``: simulator, three drivers,
fusion_node with five filters and two targets, margin_node, recorder; then the offline evaluation in the supervisor)
on a private domain, samples ``/proc`` every 0.25 s for the supervisor's descendants, and prints one JSON line per
executable (``graph_cpu_s[<exe>]``: utime + stime of its process at its last sample, in seconds) and the graph's
total. A process's CPU is read while it runs, so the last ~0.25 s before it exits can be missed.

Why: the per-process figures in docs/performance.md ("The executor") came from this; they move with the executor a
node spins on (``FULLPERC_EXECUTOR=single`` gives the other one for every node) and with what each node publishes.
Not a figure of ``make bench`` (a minute of a busy graph).

Run: python bench/graph_cpu.py [--repeats 1]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchlib import cpu_seconds, emit, proc_stat  # noqa: E402

PERIOD_S = 0.25


def _children() -> dict[int, int]:
    """pid -> parent pid of every process now."""
    out = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                out[int(d)] = int(proc_stat(int(d))[1])   # ppid
            except (OSError, IndexError, ValueError):
                pass
    return out


def family(root: int, parents: dict[int, int]) -> set[int]:
    """``root`` and every process descending from it, given each process's parent."""
    out = {root}
    while new := {c for c, pp in parents.items() if pp in out} - out:
        out |= new
    return out


def _exe_name(pid: int) -> str:
    """The executable a process runs: the installed script's name (``fusion_node``), else argv[0]'s."""
    try:
        argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    except OSError:
        return "?"
    args = [a.decode(errors="replace") for a in argv if a]
    script = next((a for a in args[1:] if not a.startswith("-")), args[0] if args else "?")
    return Path(script).name


def one_run() -> dict[str, float]:
    """CPU seconds per executable of one demo run."""
    from fullperc_common.testing import claim_domain, installed_exe

    with claim_domain() as lease, tempfile.TemporaryDirectory() as tmp:
        env = dict(os.environ, ROS_DOMAIN_ID=str(lease.domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
        p = subprocess.Popen([installed_exe("fullperc_eval", "supervisor"), "demo", "--task", "B-G-P", "--out", tmp,
                              "--set", "vega_outage=6:12"], env=env, stdout=subprocess.DEVNULL,
                             stderr=subprocess.DEVNULL)
        seen: dict[int, tuple[str, float]] = {}
        while p.poll() is None:
            for pid in family(p.pid, _children()):
                cpu = cpu_seconds(pid)
                if cpu > 0:
                    seen[pid] = (seen[pid][0] if pid in seen else _exe_name(pid), cpu)
            time.sleep(PERIOD_S)
        if p.returncode != 0:
            raise SystemExit(f"graph_cpu: the demo exited {p.returncode}")
    per_exe: dict[str, float] = {}
    for name, cpu in seen.values():
        per_exe[name] = per_exe.get(name, 0.0) + cpu
    return per_exe


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=1)
    args = ap.parse_args()
    runs = [one_run() for _ in range(args.repeats)]
    names = sorted({n for r in runs for n in r}, key=lambda n: -max(r.get(n, 0.0) for r in runs))
    for n in names:
        vals = sorted(r.get(n, 0.0) for r in runs)
        emit(f"graph_cpu_s[{n}]", statistics.median(vals), "s", runs=vals,
             executor=os.environ.get("FULLPERC_EXECUTOR", "node defaults"))
    totals = sorted(sum(r.values()) for r in runs)
    emit("graph_cpu_s[total]", statistics.median(totals), "s", runs=totals)


if __name__ == "__main__":
    main()
