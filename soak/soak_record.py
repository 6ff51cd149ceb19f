"""Soak: the installed ``record`` at 1 kHz x 10 topics, stopped with SIGINT and killed with SIGKILL (issue 14).

For each storage (mcap, sqlite3), twice: a publisher process (this file, ``publish``) sends 10 reliable topics at
1 kHz -- a ``geometry_msgs/PointStamped`` whose ``point.x`` is the sequence number and whose stamp is the publish
time -- after waiting until ``record`` is matched on all of them, and logs every stamp.

* SIGINT: once the publisher has sent everything and every message is acknowledged, ``record`` gets SIGINT. It must
  exit 0 and its bag must hold every published message of every topic: ``record_sigint_lost`` = published - recorded.
* SIGKILL: half way through, ``record`` is killed. Reading the bag must fail with an error naming the recovery
  command; that command, run as the error spells it (``python -m fullperc_eval.bag reindex BAG``), must recover it
  (``record_sigkill_recovered``: 1 when it exits 0 and every topic reads back as a gap-free prefix of what was
  published), and ``record_sigkill_lost_s`` is the worst topic's time from the publish stamp of its last recovered
  message to the kill (the recorder flushes every 0.5 s).

Prints one JSON line per figure and storage (bench/benchlib.py format), e.g.
``{"name": "record_sigint_lost[mcap]", "value": 0, "unit": "messages", "of": 50000}``; the details on stderr.

  source scripts/env.sh && python soak/soak_record.py [--seconds 5] [--storages mcap sqlite3]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))

from benchlib import emit  # noqa: E402

TOPICS = [f"/soak/rec{i}" for i in range(10)]
RATE_HZ = 1000.0
TIMEOUT_S = 300  # liveness bound for a hung process, not a performance limit


# ------------------------------------------------------------------ publisher process

def publisher_main(argv: list[str]) -> int:
    import rclpy
    from geometry_msgs.msg import PointStamped
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    from fullperc_common.node_main import wait_for_acks

    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, required=True)
    ap.add_argument("--log", required=True)
    args = ap.parse_args(argv)
    rclpy.init()
    node = rclpy.create_node("soak_record_publisher")
    qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=args.n + 10, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.VOLATILE)
    pubs = [node.create_publisher(PointStamped, t, qos) for t in TOPICS]
    end = time.monotonic() + 120
    while any(p.get_subscription_count() == 0 for p in pubs):
        if time.monotonic() > end:
            print("no subscriber", flush=True)
            return 3
        time.sleep(0.02)
    print("READY", flush=True)
    stamps = []
    msg = PointStamped()
    msg.header.frame_id = "soak"
    t0 = time.monotonic()
    for seq in range(args.n):
        left = t0 + seq / RATE_HZ - time.monotonic()
        if left > 0:
            time.sleep(left)
        stamp = time.time_ns()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
        msg.point.x = float(seq)
        for p in pubs:
            p.publish(msg)
        stamps.append(stamp)
        if seq == args.n // 2:
            print("HALF", flush=True)
    acked = not wait_for_acks(node, 60.0)
    Path(args.log).write_text(json.dumps({"stamps": stamps, "acked": acked,
                                          "late_s": time.monotonic() - t0 - args.n / RATE_HZ}))
    print("DONE", flush=True)
    try:
        while rclpy.ok():
            time.sleep(0.1)
    except KeyboardInterrupt:
        pass
    return 0


# ------------------------------------------------------------------ the soak

class Proc:
    def __init__(self, args: list[str], log: Path, env: dict[str, str]) -> None:
        self.log_path = log
        self.p = subprocess.Popen(args, stdout=open(log, "wb"), stderr=subprocess.STDOUT,  # noqa: SIM115
                                  env=env, start_new_session=True)

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    def send(self, sig: int) -> None:
        try:
            os.killpg(self.p.pid, sig)
        except ProcessLookupError:
            pass

    def stop(self, sig: int = signal.SIGINT, timeout: float = 30) -> int:
        if self.p.poll() is None:
            self.send(sig)
            try:
                self.p.wait(timeout)
            except subprocess.TimeoutExpired:
                self.send(signal.SIGKILL)
                self.p.wait()
        return self.p.returncode


def wait_until(pred, timeout: float, what: str) -> None:
    end = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > end:
            raise TimeoutError(f"timed out after {timeout:.0f} s waiting for {what}")
        time.sleep(0.05)


def run_once(storage: str, kill: int, seconds: float, tmp: Path, env: dict[str, str]):
    """Record while the publisher runs; stop the recorder with ``kill``. Returns (bag, stamps, t_kill_ns, rc)."""
    from fullperc_common.testing import installed_exe

    n = int(seconds * RATE_HZ)
    name = f"{storage}_{signal.Signals(kill).name}"
    bag = tmp / name
    rec = Proc([installed_exe("fullperc_eval", "record"), "-o", str(bag), "-s", storage, "--topics", *TOPICS],
               tmp / f"record_{name}.log", env)
    pub = Proc([sys.executable, __file__, "publish", "--n", str(n), "--log", str(tmp / f"pub_{name}.json")],
               tmp / f"publisher_{name}.log", env)
    try:
        if kill == signal.SIGKILL:
            wait_until(lambda: "HALF" in pub.log() or pub.p.poll() is not None, TIMEOUT_S, "the publisher half way")
            t_kill = time.time_ns()
            rec.send(signal.SIGKILL)
            rec.p.wait(30)
        wait_until(lambda: "DONE" in pub.log() or pub.p.poll() is not None, TIMEOUT_S, "the publisher to finish")
        if "DONE" not in pub.log():
            raise RuntimeError(f"publisher failed:\n{pub.log()[-2000:]}")
        if kill != signal.SIGKILL:
            t_kill = time.time_ns()
            rc = rec.stop(kill, timeout=60)
        else:
            rc = rec.p.returncode
    finally:
        pub.stop()
        rec.stop(signal.SIGKILL)
    log = json.loads((tmp / f"pub_{name}.json").read_text())
    if not log["acked"]:
        print(f"{name}: the publisher's messages were not all acknowledged", file=sys.stderr)
    print(f"{name}: publisher ended {log['late_s']:.3f} s behind its 1 kHz schedule", file=sys.stderr)
    return bag, log["stamps"], t_kill, rc, rec


def read_seqs(bag: Path) -> dict[str, list[int]]:
    from fullperc_eval.bag.reader import BagReader

    out: dict[str, list[int]] = {t: [] for t in TOPICS}
    with BagReader(bag) as r:
        for m in r.messages():
            out[m.topic].append(int(r.deserialize(m.data, m.msgtype).point.x))
    return out


def sigint_soak(storage: str, seconds: float, tmp: Path, env: dict[str, str]) -> bool:
    bag, stamps, _, rc, rec = run_once(storage, signal.SIGINT, seconds, tmp, env)
    seqs = read_seqs(bag)
    n = len(stamps)
    lost = sum(n - len(set(s)) for s in seqs.values())
    dups = sum(len(s) - len(set(s)) for s in seqs.values())
    clean = rc == 0 and "Traceback" not in rec.log()
    emit(f"record_sigint_lost[{storage}]", lost, "messages", of=n * len(TOPICS), exit_code=rc, duplicates=dups)
    if not clean or lost:
        print(f"record {storage} SIGINT: exit {rc}, lost {lost}\n{rec.log()[-2000:]}", file=sys.stderr)
    return clean and lost == 0 and dups == 0


def sigkill_soak(storage: str, seconds: float, tmp: Path, env: dict[str, str]) -> bool:
    from fullperc_eval.bag.errors import BagError
    from fullperc_eval.bag.reader import BagReader

    bag, stamps, t_kill, rc, _ = run_once(storage, signal.SIGKILL, seconds, tmp, env)
    try:
        BagReader(bag).open()
        hint = None
        print(f"record {storage} SIGKILL: the killed bag opened without an error", file=sys.stderr)
    except BagError as e:
        m = re.search(r"recover it with: (.+?) " + re.escape(str(bag)) + r"\s*$", str(e))
        hint = m.group(1) if m else None
        if hint is None:
            print(f"record {storage} SIGKILL: the error names no recovery command: {e}", file=sys.stderr)
    cmd = shlex.split(hint or "python -m fullperc_eval.bag reindex")
    if cmd[0] == "python":
        cmd[0] = sys.executable  # the venv's python, what `python` is after `source scripts/env.sh`
    p = subprocess.run([*cmd, str(bag)], capture_output=True, text=True, timeout=TIMEOUT_S, env=env)
    print(f"record {storage} SIGKILL: {' '.join([*cmd, str(bag)])} -> exit {p.returncode}: {p.stdout.strip()}"
          f"{p.stderr.strip()}", file=sys.stderr)
    recovered, lost_s, kept = False, float("nan"), 0
    if p.returncode == 0:
        try:
            seqs = read_seqs(bag)
            prefix = all(s == list(range(len(s))) and s for s in seqs.values())
            kept = sum(len(s) for s in seqs.values())
            lost_s = max((t_kill - stamps[len(s) - 1]) / 1e9 for s in seqs.values()) if prefix else float("nan")
            recovered = bool(prefix)
            if not prefix:
                print(f"record {storage} SIGKILL: a topic is not a gap-free prefix of what was published",
                      file=sys.stderr)
        except BagError as e:
            print(f"record {storage} SIGKILL: the recovered bag does not read: {e}", file=sys.stderr)
    published_before = sum(1 for s in stamps if s < t_kill) * len(TOPICS)
    emit(f"record_sigkill_lost_s[{storage}]", lost_s, "s", recovered_messages=kept,
         published_before_kill=published_before)
    emit(f"record_sigkill_recovered[{storage}]", int(recovered), "bool", of=1, command=f"{hint} BAG",
         killed_exit=rc)
    return recovered and hint is not None and lost_s <= 1.0


def main() -> int:
    if len(sys.argv) > 1 and sys.argv[1] == "publish":
        return publisher_main(sys.argv[2:])
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=5.0, help="publishing time per run [s] (5)")
    ap.add_argument("--storages", nargs="+", default=["mcap", "sqlite3"], choices=["mcap", "sqlite3"])
    ap.add_argument("--domain", type=int, default=None, help="ROS_DOMAIN_ID (default: derived from the pid)")
    a = ap.parse_args()
    domain = a.domain if a.domain is not None else 1 + (os.getpid() * 17 + 30) % 100
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYTHONUNBUFFERED="1")
    tmp = Path(tempfile.mkdtemp(prefix="soak_record_"))
    ok = True
    for storage in a.storages:
        ok &= sigint_soak(storage, a.seconds, tmp, env)
        ok &= sigkill_soak(storage, a.seconds, tmp, env)
    if ok:
        shutil.rmtree(tmp, ignore_errors=True)
    else:
        print(f"bags and logs kept in {tmp}", file=sys.stderr)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
