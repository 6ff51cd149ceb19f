"""`record`: rosbag2 recorder (like `ros2 bag record`, which the PyPI wheels do not ship).

Subscribes with raw subscriptions (the CDR bytes exactly as they came off the wire) to the chosen
topics, or to every topic found by polling the graph (``--all``), and writes them with
:class:`.writer.BagWriter` (MCAP by default, sqlite3 optional). The bag time of a
message is its DDS reception time, the MCAP publish time its source time, as in rosbag2.

Durability: the writer finishes its chunk / commits and refreshes metadata.yaml every
``--flush-interval`` seconds (0.5 s default), so a killed recorder loses at most about that much;
``python -m fullperc_eval.bag reindex BAG`` then makes the bag complete again. SIGINT and
SIGTERM drain what DDS already delivered and close the bag cleanly.

Deviations from rosbag2, on purpose: subscriptions use keep_last ``--subscription-depth``
(4000, rosbag2 uses 10) so a recorder that falls briefly behind a 1 kHz reliable stream drops
nothing, nor a burst of a node catching up (fusion_node publishes up to its ``qos_depth``, 2000, per topic in
one callback; at 1000 a busy demo run lost 594 of one topic's messages in one burst); messages are taken from
every subscription's queue every 10 ms instead of through an executor callback each (``--take``,
:meth:`Recorder.take_all`: a quarter of the CPU per message); no services (the node's parameter services
are not served while it polls)/``--use-sim-time``/snapshot mode; ``--duration`` stops after that many seconds.
"""

from __future__ import annotations

import argparse
import re
import signal
import sys
import time
from datetime import datetime
from pathlib import Path
from typing import Any

import yaml

from fullperc_common.drain import take_one

from .errors import BagError
from .metadata import REINDEX_HINT, STORAGES
from .qos import offered_qos_dict, rclpy_qos_from_dict
from .types import get_message, resolve_definition
from .writer import DEFAULT_FLUSH_INTERVAL, BagWriter

NODE_NAME = "rosbag2_recorder"
TAKE_MODES = ("poll", "callback", "executor")   # --take (Recorder)
POLL_PERIOD_S = 0.01   # --take poll: sleep between rounds that emptied every queue
RECOVERY_HELP = f"""\
stopping and recovery:
  SIGINT (Ctrl-C) or SIGTERM: what DDS already delivered is written and the bag is closed cleanly.
  A killed recorder (SIGKILL, power loss, out of memory) loses at most about --flush-interval of data, but
  leaves the bag incomplete (an MCAP file without footer; a sqlite3 file with its -wal log beside it):
  reading it fails with an error that says so. Recover the bag, in place, with
      {REINDEX_HINT} BAG
  (MCAP: rewritten complete, the original kept as <file>.mcap.orig; sqlite3: the log is checkpointed;
  metadata.yaml is rebuilt from the storage files in both cases)."""


# ---------------------------------------------------------------- helpers shared with play

def fully_qualified(topic: str) -> str:
    topic = topic.strip()
    return topic if topic.startswith("/") else "/" + topic


def is_hidden(topic: str) -> bool:
    return any(tok.startswith("_") for tok in topic.split("/") if tok)


def load_qos_overrides(path: str | None) -> dict[str, Any]:
    """``--qos-profile-overrides-path`` YAML: {topic: profile map} -> {topic: rclpy QoSProfile}."""
    if not path:
        return {}
    try:
        data = yaml.safe_load(Path(path).read_text()) or {}
    except (OSError, yaml.YAMLError) as err:
        raise BagError(f"cannot read QoS overrides {path!r}: {err}") from None
    if not isinstance(data, dict):
        raise BagError(f"QoS overrides {path!r} must map topic names to QoS profiles")
    out = {}
    for topic, prof in data.items():
        if not isinstance(prof, dict):
            raise BagError(f"QoS override for {topic!r} must be a map")
        try:
            out[fully_qualified(str(topic))] = rclpy_qos_from_dict(prof)
        except BagError as err:
            raise BagError(f"QoS override for {topic!r}: {err}") from None
    return out


class StopFlag:
    """Set by SIGINT/SIGTERM; the main loop polls it (rclpy's own handlers are disabled)."""

    def __init__(self) -> None:
        self.signum = 0

    def __bool__(self) -> bool:
        return self.signum != 0

    def install(self) -> None:
        for s in (signal.SIGINT, signal.SIGTERM):
            signal.signal(s, self._handle)

    def _handle(self, signum, _frame) -> None:
        self.signum = signum


def split_ros_args(argv: list[str]) -> tuple[list[str], list[str]]:
    """(our arguments, ['--ros-args', ...]) — ROS arguments go to rclpy.init untouched."""
    if "--ros-args" in argv:
        i = argv.index("--ros-args")
        return argv[:i], argv[i:]
    return argv, []


# ---------------------------------------------------------------- recorder

def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="record", description="Record ROS 2 topics into a rosbag2 bag (MCAP or sqlite3), like `ros2 bag record`.",
        epilog=RECOVERY_HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("-o", "--output", help="bag directory (must not exist); default rosbag2_<date>-<time>")
    ap.add_argument("-s", "--storage", choices=STORAGES, default="mcap", help="storage plugin (mcap)")
    ap.add_argument("--topics", nargs="+", default=[], metavar="TOPIC", help="topics to record")
    ap.add_argument("topics_positional", nargs="*", metavar="TOPIC", help=argparse.SUPPRESS)
    ap.add_argument("-a", "--all", "--all-topics", dest="all", action="store_true",
                    help="record every topic found by polling the graph")
    ap.add_argument("-e", "--regex", help="record topics matching this regular expression")
    ap.add_argument("--exclude-regex", help="do not record topics matching this regular expression")
    ap.add_argument("--exclude-topics", nargs="+", default=[], metavar="TOPIC", help="do not record these")
    ap.add_argument("--include-hidden-topics", action="store_true", help="also record hidden topics (_*)")
    ap.add_argument("--include-unpublished-topics", action="store_true",
                    help="also subscribe to topics that have no publisher yet")
    ap.add_argument("-p", "--polling-interval", type=int, default=100, metavar="MS",
                    help="graph polling interval for topic discovery [ms] (100)")
    ap.add_argument("--qos-profile-overrides-path", metavar="YAML", help="per-topic subscription QoS")
    ap.add_argument("-b", "--max-bag-size", type=int, default=0, metavar="BYTES",
                    help="split into a new file after this many bytes (0 = never)")
    ap.add_argument("-d", "--max-bag-duration", type=float, default=0.0, metavar="SEC",
                    help="split into a new file after this many seconds of bag time (0 = never)")
    ap.add_argument("--duration", type=float, default=0.0, metavar="SEC",
                    help="stop recording after this many seconds (0 = until SIGINT/SIGTERM)")
    ap.add_argument("--storage-preset-profile", choices=("none", "fastwrite", "zstd_fast", "zstd_small"),
                    default="none", help="mcap: zstd_* compress the chunks")
    ap.add_argument("--custom-data", nargs="+", default=[], metavar="KEY=VALUE", help="stored in metadata.yaml")
    ap.add_argument("--node-name", default=NODE_NAME)
    ap.add_argument("--flush-interval", type=float, default=DEFAULT_FLUSH_INTERVAL, metavar="SEC",
                    help="write data and metadata.yaml at least this often; bounds loss on a crash (0.5)")
    ap.add_argument("--fsync", action="store_true", help="also fsync at each flush (power-loss safety)")
    ap.add_argument("--take", choices=TAKE_MODES, default="poll",
                    help="how messages are taken from DDS: every subscription's queue every 10 ms, no executor "
                         "(poll, default); an executor callback that takes its topic's queue (callback); one "
                         "executor round per message, rosbag2's way (executor)")
    ap.add_argument("--subscription-depth", type=int, default=4000, metavar="N",
                    help="keep_last depth of the recording subscriptions (4000)")
    return ap


class Recorder:
    """Topic discovery + raw subscriptions feeding a BagWriter (one node, single-threaded)."""

    def __init__(self, node, writer: BagWriter, args: argparse.Namespace) -> None:
        self.node = node
        self.writer = writer
        self.args = args
        self.log = node.get_logger()
        self.explicit = {fully_qualified(t) for t in list(args.topics) + list(args.topics_positional)}
        self.exclude = {fully_qualified(t) for t in args.exclude_topics}
        self.regex = re.compile(args.regex) if args.regex else None
        self.exclude_regex = re.compile(args.exclude_regex) if args.exclude_regex else None
        self.overrides = load_qos_overrides(args.qos_profile_overrides_path)
        self.subs: dict[str, Any] = {}
        self.skipped: set[str] = set()
        self.warned: set[str] = set()
        self.received = 0
        mode = getattr(args, "take", "poll")
        self._no_drain = mode == "executor"   # every message through its own executor callback
        self.polling = mode == "poll"         # _run takes every queue itself (take_all) and never spins
        self.callbacks = 0   # messages that came through an executor callback (the rest were taken directly)

    def wanted(self, topic: str) -> bool:
        if topic in self.exclude or (self.exclude_regex and self.exclude_regex.search(topic)):
            return False
        if topic in self.explicit:
            return True
        if is_hidden(topic) and not self.args.include_hidden_topics:
            return False
        return bool(self.args.all or (self.regex and self.regex.search(topic)))

    @property
    def discovery_done(self) -> bool:
        """rosbag2 stops polling once every explicitly requested topic is subscribed."""
        return not self.args.all and self.regex is None and self.explicit <= set(self.subs) | self.skipped

    def _warn_once(self, key: str, text: str) -> None:
        if key not in self.warned:
            self.warned.add(key)
            self.log.warning(text)

    def discover(self) -> None:
        for name, types in self.node.get_topic_names_and_types():
            if name in self.subs or name in self.skipped or not self.wanted(name):
                continue
            if len(types) != 1:
                self._warn_once(name + "#types", f"not recording {name}: it has more than one type {types}")
                continue
            pubs = self.node.get_publishers_info_by_topic(name)
            if not pubs and not self.args.include_unpublished_topics:
                continue
            self._subscribe(name, types[0], pubs)

    def _subscribe(self, name: str, msgtype: str, pubs: list) -> None:
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

        try:
            cls = get_message(msgtype)
            encoding, msgdef, type_hash = resolve_definition(msgtype)
            # rosbag2: the endpoints' hash if they all agree, "" if they disagree.
            hashes = {str(p.topic_type_hash) for p in pubs}
            if len(hashes) > 1:
                type_hash = ""
            elif hashes and re.fullmatch(r"RIHS01_[0-9a-f]{64}", h := hashes.pop()) and h != "RIHS01_" + "0" * 64:
                type_hash = h
            self.writer.add_topic(name, msgtype, [offered_qos_dict(p.qos_profile) for p in pubs],
                                  msgdef=msgdef, encoding=encoding, type_hash=type_hash)
        except BagError as err:
            self.skipped.add(name)
            self.log.error(f"not recording {name}: {err}")
            return
        qos = self.overrides.get(name)
        if qos is None:
            reliable = bool(pubs) and all(p.qos_profile.reliability == ReliabilityPolicy.RELIABLE for p in pubs)
            latched = bool(pubs) and all(
                p.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in pubs)
            if pubs and not reliable and any(p.qos_profile.reliability == ReliabilityPolicy.RELIABLE for p in pubs):
                self.log.warning(f"{name}: publishers offer mixed reliability; subscribing best effort")
            qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=self.args.subscription_depth,
                             reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)
        writer = self.writer

        def on_message(data: bytes, info: dict) -> None:
            writer.write(name, info["received_timestamp"], data, info["source_timestamp"])
            self.received += 1
            self.callbacks += 1
            self._drain(name)

        self.subs[name] = self.node.create_subscription(cls, name, on_message, qos, raw=True)
        self.log.info(f"Subscribed to topic '{name}' ({msgtype})")

    DRAIN_MAX = 500  # messages taken from one queue at a time; bounds how long one topic holds the loop

    def _drain(self, name: str) -> None:
        """``--take callback``: after its callback, take what is queued on this topic without an executor round
        per message (rclpy's executor costs ~130 us CPU per callback, a take ~4 us)."""
        if self._no_drain or self.polling:
            return
        try:
            self._take_queued(name)
        except (AttributeError, TypeError) as err:
            self._fall_back(err)

    def take_all(self) -> bool:
        """``--take poll``: take what is queued on every subscription, up to :attr:`DRAIN_MAX` per topic; True when
        a queue may hold more (a topic reached its budget: take again at once).

        Why no executor: with ~34 topics at ~3,000 messages/s (``bench/bench_record.py``: the committed bag
        played twice at once, about what the demo graph publishes) rclpy's executor made the recorder spend ~330 us
        of CPU per message -- a core at that rate -- in building wait sets and dispatching a task per ready
        subscription, also when a callback took every other queue with its own (~310 us). DDS queues a
        subscription's messages without an executor (keep_last ``--subscription-depth``: 4000, seconds at these
        rates), so taking them every :data:`POLL_PERIOD_S` loses nothing and costs a take (~4 us) per topic
        and round. Each topic's messages are written in the order they arrived, topics one after another (the
        bag's time is the reception time DDS stamped, not when they were taken; readers sort by it).
        """
        more = False
        try:
            for name in self.subs:
                more |= self._take_queued(name) == self.DRAIN_MAX
        except (AttributeError, TypeError) as err:
            self._fall_back(err)
        return more

    def _fall_back(self, err: Exception) -> None:
        """rclpy's internals changed (:func:`fullperc_common.drain.take_one` raised): one executor round per
        message from now on."""
        self._no_drain, self.polling = True, False
        self.log.warning(f"taking messages directly unavailable ({err}); one executor round per message")

    def _take_queued(self, name: str) -> int:
        """Write up to :attr:`DRAIN_MAX` messages queued on ``name``'s subscription; how many."""
        sub = self.subs.get(name)
        if sub is None:
            return 0
        write = self.writer.write
        n = 0
        while n < self.DRAIN_MAX:
            taken = take_one(sub, raw=True)
            if taken is None:
                break
            data, info = taken
            write(name, info["received_timestamp"], data, info["source_timestamp"])
            n += 1
        self.received += n
        return n


def default_output() -> str:
    return datetime.now().strftime("rosbag2_%Y_%m_%d-%H_%M_%S")


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    ours, ros_args = split_ros_args(argv)
    ap = build_parser()
    args = ap.parse_args(ours)
    if not (args.topics or args.topics_positional or args.all or args.regex):
        ap.error("give --topics, --all or --regex (what to record)")
    if (args.exclude_regex or args.exclude_topics) and not (args.all or args.regex):
        ap.error("--exclude-regex/--exclude-topics need --all or --regex")
    if args.flush_interval <= 0 or args.polling_interval <= 0 or args.subscription_depth <= 0:
        ap.error("--flush-interval, --polling-interval and --subscription-depth must be > 0")
    custom = {}
    for kv in args.custom_data:
        if "=" not in kv:
            ap.error(f"--custom-data expects KEY=VALUE, got {kv!r}")
        k, v = kv.split("=", 1)
        custom[k] = v
    try:
        load_qos_overrides(args.qos_profile_overrides_path)  # fail before touching the disk
        writer = BagWriter(
            args.output or default_output(), storage=args.storage, flush_interval=args.flush_interval,
            fsync=args.fsync, max_bag_size=args.max_bag_size, max_bag_duration=int(args.max_bag_duration * 1e9),
            compression="zstd" if args.storage_preset_profile.startswith("zstd") else "", custom_data=custom)
        writer.open()
    except BagError as err:
        print(f"record: error: {err}", file=sys.stderr)
        return 1
    return _run(writer, args, ros_args)


def _run(writer: BagWriter, args: argparse.Namespace, ros_args: list[str]) -> int:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    stop = StopFlag()
    stop.install()
    rclpy.init(args=["record", *ros_args], signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node(args.node_name)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    rec = Recorder(node, writer, args)
    log = node.get_logger()
    log.info(f"Recording to '{writer.path}' ({writer.storage})")
    t_end = time.monotonic() + args.duration if args.duration > 0 else float("inf")
    poll = args.polling_interval / 1000.0

    def step(timeout: float) -> None:
        """Take what DDS delivered: every queue then a sleep (``--take poll``), or one executor round."""
        if rec.polling:
            if not rec.take_all():
                time.sleep(min(timeout, POLL_PERIOD_S))
        else:
            executor.spin_once(timeout_sec=timeout)

    next_poll = 0.0
    rc = 0
    try:
        while not stop and time.monotonic() < t_end:
            now = time.monotonic()
            if now >= next_poll and not rec.discovery_done:
                rec.discover()
                next_poll = now + poll
            step(min(0.05, poll))
            writer.flush_if_due()
        # Drain what DDS already delivered: go on until nothing arrived for 0.2 s (at most 2 s).
        quiet_since, last, deadline = time.monotonic(), rec.received, time.monotonic() + 2.0
        while time.monotonic() < deadline and time.monotonic() - quiet_since < 0.2:
            step(0.02)
            if rec.received != last:
                last, quiet_since = rec.received, time.monotonic()
    except (BagError, OSError) as err:
        log.error(f"recording failed: {err}")
        rc = 1
    finally:
        try:
            writer.close()
        except (BagError, OSError) as err:
            print(f"record: error closing the bag: {err}", file=sys.stderr)
            rc = 1
        executor.shutdown(timeout_sec=0)
        node.destroy_node()
        rclpy.try_shutdown()
    counts = ", ".join(f"{t.name}: {t.count}" for t in writer.topics.values())
    print(f"record: wrote {writer.message_count} messages to {writer.path} ({counts or 'no topics'}); "
          f"{rec.callbacks} through executor callbacks (--take {args.take})", flush=True)
    return rc


if __name__ == "__main__":
    sys.exit(main())
