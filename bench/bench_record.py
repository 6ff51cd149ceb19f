"""CPU the recorder spends per message, by ``--take`` mode (``fullperc_eval.bag.record``).

In the demo graph the recorder was the biggest CPU consumer of eight processes on two cores (docs/bags.md "What
recording costs"), and every core-second it takes is one ``fusion_node`` does not get. Here: the installed ``play``
replays the committed ``bags/paper/B-G-P`` bag twice at once (the second copy remapped under ``/copy``: 34 topics,
~3,000 messages/s, about what the demo graph publishes) to the installed ``record`` subscribed to all of them, for
``SECONDS`` of bag time. The figure is the recorder's CPU time (utime + stime from ``/proc``) between the moment its
subscriptions are up and the end of the replay, over the messages it wrote in that time -- start-up and the final
close are not in it.

``record_cpu_us_per_msg[take=poll ...]`` (the default: every queue taken every 10 ms, no executor) is reported
against ``take=callback`` (an executor callback per topic with messages, taking that topic's queue: the mode before)
and ``take=executor`` (one rclpy executor round per message, rosbag2's way), modes interleaved, ``REPEATS`` runs
each, medians. ``lost`` is the messages played but not written (0 expected: the subscriptions hold 1000 per topic).

Run: python bench/bench_record.py   (or make bench)
"""

from __future__ import annotations

import os
import re
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from benchlib import cpu_seconds, emit, emit_error  # noqa: E402

ROOT = Path(os.environ.get("FULLPERC_ROOT", HERE.parent))
BAG = ROOT / "bags/paper/B-G-P"
SECONDS = 12.0
REPEATS = 3
MODES = ("poll", "callback", "executor")


def _exe(name: str) -> str:
    return str(ROOT / "install/fullperc_eval/lib/fullperc_eval" / name)


def _topics() -> list[str]:
    import yaml

    info = yaml.safe_load((BAG / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    # the demo graph's load: not the twin's patient reference, which the demo does not fuse (docs/targets.md)
    names = [t["topic_metadata"]["name"] for t in info["topics_with_message_count"]]
    return [n for n in names if "/reference" not in n]


def one_run(mode: str, env: dict[str, str], tmp: Path) -> tuple[float, int, int]:
    """(CPU seconds while the replay ran, messages written, messages played) of one recording in ``mode``."""
    topics = _topics()
    copies = [f"/copy{t}" for t in topics]
    run = tmp / f"{mode}-{time.monotonic_ns()}"
    run.mkdir()
    logs = {k: open(run / f"{k}.log", "w") for k in ("record", "play", "play_copy")}   # noqa: SIM115
    procs: list[subprocess.Popen] = []
    try:
        common = ["--playback-duration", str(SECONDS), "--wait-for-subscribers", "60", "--topics", *topics]
        procs.append(subprocess.Popen([_exe("play"), str(BAG), *common], env=env, stdout=logs["play"],
                                      stderr=subprocess.STDOUT))
        procs.append(subprocess.Popen([_exe("play"), str(BAG), *common, "--node-name", "player_copy", "-m",
                                       *(f"{t}:={c}" for t, c in zip(topics, copies, strict=True))],
                                      env=env, stdout=logs["play_copy"], stderr=subprocess.STDOUT))
        # the players wait for their subscribers, the recorder subscribes to topics it finds published: its CPU
        # from when it has subscribed to every topic (start-up, discovery and subscribing are not in the figure;
        # the players start within one poll of that)
        rec = subprocess.Popen([_exe("record"), "-o", str(run / "bag"), "--take", mode, "--topics", *topics,
                                *copies], env=env, stdout=logs["record"], stderr=subprocess.STDOUT)
        procs.insert(0, rec)
        deadline = time.monotonic() + 60
        while (run / "record.log").read_text().count("Subscribed to topic") < 2 * len(topics):
            if time.monotonic() > deadline or rec.poll() is not None:
                raise RuntimeError(f"record ({mode}) did not subscribe: {(run / 'record.log').read_text()[-500:]}")
            time.sleep(0.02)
        cpu0 = cpu_seconds(rec.pid)
        for p in procs[1:]:
            p.wait(timeout=SECONDS * 10 + 60)
        time.sleep(0.5)   # what DDS still holds for the recorder
        cpu1 = cpu_seconds(rec.pid)
        rec.send_signal(signal.SIGINT)
        rec.wait(timeout=60)
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
        for f in logs.values():
            f.close()
    text = {k: (run / f"{k}.log").read_text() for k in logs}
    m = re.search(r"record: wrote (\d+) messages", text["record"])
    if m is None or rec.returncode != 0:
        raise RuntimeError(f"record ({mode}) failed: rc={rec.returncode}, log tail: {text['record'][-500:]}")
    played = sum(int(g[-1]) for k in ("play", "play_copy") if (g := re.findall(r"Played (\d+) messages", text[k])))
    return cpu1 - cpu0, int(m.group(1)), played


def main() -> int:
    if not Path(_exe("record")).exists():
        emit_error("record_cpu_us_per_msg", "us", "not built: run make build")
        return 1
    from fullperc_common.testing import claim_domain

    per_msg: dict[str, list[float]] = {m: [] for m in MODES}
    lost: dict[str, int] = dict.fromkeys(MODES, 0)
    written: dict[str, list[int]] = {m: [] for m in MODES}
    with claim_domain() as lease, tempfile.TemporaryDirectory() as tmp:
        env = dict(os.environ, ROS_DOMAIN_ID=str(lease.domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
        for _ in range(REPEATS):
            for mode in MODES:
                cpu, n, played = one_run(mode, env, Path(tmp))
                per_msg[mode].append(cpu / max(n, 1) * 1e6)
                written[mode].append(n)
                lost[mode] += max(0, played - n)
    med = {m: statistics.median(v) for m, v in per_msg.items()}
    for base in ("callback", "executor"):
        emit(f"record_cpu_us_per_msg[take=poll vs {base}]", med["poll"], "us", baseline=med[base],
             messages=statistics.median(written["poll"]), lost=lost["poll"], baseline_lost=lost[base],
             runs=REPEATS, note=f"recorder CPU per message written, 34 topics ~3k msg/s, --take poll vs {base}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
