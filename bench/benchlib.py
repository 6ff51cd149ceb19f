"""Shared helpers for benchmarks: timing with medians and one JSON line per figure.

These machines are noisy, so every figure is a median over repeats, and where a figure has a
natural baseline (e.g. a plain numpy loop, or the same work without our code) the baseline is
measured in the same run and reported as a ratio.
"""

from __future__ import annotations

import json
import os
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path


def proc_stat(pid: int) -> list[str]:
    """The fields of ``/proc/<pid>/stat`` after the command name (proc(5) field 3 on: state, ppid, ...); the name
    is cut at its last ')' since it may hold spaces and parentheses. OSError where the process is gone."""
    return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of process ``pid`` [s] (Linux /proc; 0.0 where unavailable)."""
    try:
        fields = proc_stat(pid)
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")   # utime, stime: proc(5) 14, 15
    except (OSError, IndexError, ValueError):
        return 0.0


def median_time(fn: Callable[[], object], repeats: int = 7, number: int = 1) -> float:
    """Median wall time of ``number`` calls of ``fn`` over ``repeats`` repeats, per call [s]."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(number):
            fn()
        times.append((time.perf_counter() - t0) / number)
    return statistics.median(times)


def load() -> list[float]:
    """The machine's 1/5/15-minute load averages now: shared machines make every timing depend on them."""
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return []


def emit(name: str, value: float, unit: str, baseline: float | None = None, **extra) -> dict:
    """Print one machine-readable result line; ``ratio`` = value / baseline when given; ``load`` = the load
    averages when the line is printed (unless the caller passes its own, e.g. measured during the run)."""
    rec: dict = {"name": name, "value": round(float(value), 6), "unit": unit}
    if baseline is not None:
        rec["baseline"] = round(float(baseline), 6)
        rec["ratio"] = round(float(value) / float(baseline), 4) if baseline else None
    rec.update(extra)
    rec.setdefault("load", load())
    print(json.dumps(rec), flush=True)
    return rec


def emit_error(name: str, unit: str, why: str, **extra) -> dict:
    """A figure that could not be measured: ``value`` null and ``error`` saying why (the name stays listed)."""
    rec: dict = {"name": name, "value": None, "unit": unit, "error": why, **extra}
    rec.setdefault("load", load())
    print(json.dumps(rec), flush=True)
    return rec


if __name__ == "__main__":
    sys.exit("benchlib is a library; run bench/run_all.py")
