"""`play`: rosbag2 player (like `ros2 bag play`, which the PyPI wheels do not ship).

Publishes the recorded CDR bytes unchanged, each message when the playback clock reaches its bag
(receive) time: playback clock = bag start + ``--start-offset`` + rate * wall time since start.
Messages are scheduled against absolute wall times, so lateness never accumulates.

Publisher QoS follows rosbag2: the recorded offer when all recorded offers agree (history forced to
keep_last), else reliable/volatile; ``--qos-profile-overrides-path`` wins. Deviations, on purpose:
publisher depth ``--publisher-depth`` (1000, rosbag2 uses 10) so a reliable subscriber that lags
at 1 kHz loses nothing; ``--wait-for-subscribers`` holds playback until every publisher is matched;
at the end, reliable publishers wait (bounded) until their messages are acknowledged.
"""

from __future__ import annotations

import argparse
import re
import sys
import time
from typing import Any

from .errors import BagError
from .metadata import TopicInfo
from .qos import rclpy_qos_from_dict
from .reader import BagReader
from .record import StopFlag, fully_qualified, load_qos_overrides, split_ros_args
from .types import get_message

NODE_NAME = "rosbag2_player"
CLOCK_TOPIC = "/clock"


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="play", description="Replay a rosbag2 bag (MCAP or sqlite3), like "
                                 "`ros2 bag play`.")
    ap.add_argument("bag_path", help="bag directory")
    ap.add_argument("-r", "--rate", type=float, default=1.0, help="playback rate (> 0), 1.0 = recorded speed")
    ap.add_argument("-l", "--loop", action="store_true", help="repeat until stopped")
    ap.add_argument("--start-offset", type=float, default=0.0, metavar="SEC",
                    help="start this many seconds after the bag start (>= 0)")
    ap.add_argument("--playback-duration", type=float, default=0.0, metavar="SEC",
                    help="play only this many seconds of bag time (0 = all)")
    ap.add_argument("-d", "--delay", type=float, default=0.0, metavar="SEC", help="sleep before each pass")
    ap.add_argument("--topics", nargs="+", default=[], metavar="TOPIC", help="play only these topics")
    ap.add_argument("-e", "--regex", help="play only topics matching this regular expression")
    ap.add_argument("-x", "--exclude-regex", help="do not play topics matching this regular expression")
    ap.add_argument("--exclude-topics", nargs="+", default=[], metavar="TOPIC", help="do not play these topics")
    ap.add_argument("--clock", type=float, nargs="?", const=40.0, default=0.0, metavar="HZ",
                    help="publish the bag time on /clock at HZ (40 if no value)")
    ap.add_argument("--qos-profile-overrides-path", metavar="YAML", help="per-topic publisher QoS")
    ap.add_argument("-m", "--remap", nargs="+", default=[], metavar="OLD:=NEW", help="rename topics")
    ap.add_argument("--read-ahead-queue-size", type=int, default=1000, metavar="N",
                    help="messages read ahead by a reader thread (1000)")
    ap.add_argument("--node-name", default=NODE_NAME)
    ap.add_argument("--publisher-depth", type=int, default=1000, metavar="N",
                    help="keep_last depth of the publishers (1000)")
    ap.add_argument("--wait-for-subscribers", type=float, nargs="?", const=30.0, default=None, metavar="TIMEOUT",
                    help="before playing, wait until every publisher has a subscriber (30 s if no value)")
    return ap


def select_topics(reader: BagReader, args: argparse.Namespace) -> list[str]:
    explicit = [fully_qualified(t) for t in args.topics]
    exclude = {fully_qualified(t) for t in args.exclude_topics}
    rx = re.compile(args.regex) if args.regex else None
    xrx = re.compile(args.exclude_regex) if args.exclude_regex else None
    missing = [t for t in explicit if t not in reader.topics]
    if missing:
        print(f"play: warning: topics not in the bag: {', '.join(missing)}", file=sys.stderr)
    out = []
    for name in reader.topics:
        if explicit and name not in explicit:
            continue
        if rx and not rx.search(name):
            continue
        if name in exclude or (xrx and xrx.search(name)):
            continue
        if args.clock and name == CLOCK_TOPIC:  # rosbag2 drops a recorded /clock when it publishes one
            continue
        out.append(name)
    return out


def publisher_qos(info: TopicInfo, depth: int):
    """rosbag2 adapt_offer_to_recorded_offers: the common recorded offer, else reliable/volatile."""
    keys = ("reliability", "durability", "deadline", "liveliness", "liveliness_lease_duration")
    offers = info.offered_qos
    if offers and all(all(o[k] == offers[0][k] for k in keys) for o in offers):
        prof = {k: offers[0][k] for k in keys}
        prof["lifespan"] = offers[0]["lifespan"]
    else:
        prof = {"reliability": "reliable", "durability": "volatile"}
    prof.update(history="keep_last", depth=depth)
    return rclpy_qos_from_dict(prof)


def parse_remaps(items: list[str]) -> dict[str, str]:
    out = {}
    for item in items:
        if ":=" not in item:
            raise BagError(f"--remap expects OLD:=NEW, got {item!r}")
        old, new = item.split(":=", 1)
        out[fully_qualified(old)] = fully_qualified(new)
    return out


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    ours, ros_args = split_ros_args(argv)
    ap = build_parser()
    args = ap.parse_args(ours)
    if not args.rate > 0:
        ap.error("--rate must be > 0")
    if args.start_offset < 0 or args.delay < 0 or args.playback_duration < 0 or args.clock < 0:
        ap.error("--start-offset, --delay, --playback-duration and --clock must be >= 0")
    if args.publisher_depth <= 0 or args.read_ahead_queue_size <= 0:
        ap.error("--publisher-depth and --read-ahead-queue-size must be > 0")
    try:
        reader = BagReader(args.bag_path)
        reader.open()
        topics = select_topics(reader, args)
        if not topics and not args.clock:
            raise BagError("no topics to play (check --topics / --regex / --exclude-*)")
        classes: dict[str, Any] = {}
        unknown = []
        for name in topics:
            try:
                classes[name] = get_message(reader.topics[name].msgtype)
            except BagError as err:
                unknown.append(f"{name}: {err}")
        if unknown:
            raise BagError("cannot play topics of unknown message types (exclude them with --exclude-topics):\n  "
                           + "\n  ".join(unknown))
        overrides = load_qos_overrides(args.qos_profile_overrides_path)
        remaps = parse_remaps(args.remap)
        qos = {name: overrides.get(name) or publisher_qos(reader.topics[name], args.publisher_depth)
               for name in topics}
    except BagError as err:
        print(f"play: error: {err}", file=sys.stderr)
        return 1
    try:
        return _run(reader, args, ros_args, topics, classes, qos, remaps)
    except BagError as err:
        print(f"play: error: {err}", file=sys.stderr)
        return 1
    finally:
        reader.close()


def _run(reader, args, ros_args, topics, classes, qos, remaps) -> int:
    import rclpy
    from rclpy.duration import Duration
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions

    stop = StopFlag()
    stop.install()
    # The read-ahead thread must not hold the GIL for the default 5 ms while a message is due.
    sys.setswitchinterval(0.0005)
    rclpy.init(args=["play", *ros_args], signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node(args.node_name)
    log = node.get_logger()
    try:
        pubs = {name: node.create_publisher(classes[name], remaps.get(name, name), qos[name]) for name in topics}
        clock_pub = clock_cls = None
        if args.clock:
            from rosgraph_msgs.msg import Clock as clock_cls

            clock_pub = node.create_publisher(clock_cls, CLOCK_TOPIC, QoSProfile(
                history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.BEST_EFFORT,
                durability=DurabilityPolicy.VOLATILE))
        if args.wait_for_subscribers is not None:
            everyone = list(pubs.values()) + ([clock_pub] if clock_pub else [])
            end = time.monotonic() + args.wait_for_subscribers
            while not stop and any(p.get_subscription_count() == 0 for p in everyone):
                if time.monotonic() > end:
                    waiting = [p.topic_name for p in everyone if p.get_subscription_count() == 0]
                    log.warning(f"no subscriber after {args.wait_for_subscribers:.0f} s on {waiting}; playing anyway")
                    break
                time.sleep(0.02)
        start = reader.start_time + int(round(args.start_offset * 1e9))
        stop_t = start + int(round(args.playback_duration * 1e9)) if args.playback_duration > 0 else None
        clock_period = 1e9 / args.clock if args.clock else None
        published = 0
        lateness: list[int] = []  # publish wall time - scheduled wall time [ns], for the summary
        max_publish = 0  # longest publish() call [ns]: tells DDS blocking from scheduling stalls
        log.info(f"Playing {reader.path} ({len(topics)} topics) at rate {args.rate}")
        while not stop:
            if args.delay:
                _sleep_until(time.monotonic_ns() + int(args.delay * 1e9), stop)
            wall0 = time.monotonic_ns()
            next_clock = wall0

            def bag_now(w: int, wall0: int = wall0) -> int:
                return start + int((w - wall0) * args.rate)

            for msg in ReadAhead(reader.messages(topics, start=start, stop=stop_t), args.read_ahead_queue_size):
                due = wall0 + int((msg.timestamp - start) / args.rate)
                while not stop:
                    now = time.monotonic_ns()
                    if clock_pub is not None and now >= next_clock:
                        clock_pub.publish(clock_cls(clock=_stamp(bag_now(now))))
                        next_clock += int(clock_period)
                        continue
                    if now >= due:
                        break
                    target = due if clock_pub is None else min(due, next_clock)
                    _sleep_until(target, stop)
                if stop:
                    break
                t_pub = time.monotonic_ns()
                pubs[msg.topic].publish(msg.data)
                done = time.monotonic_ns()
                lateness.append(done - due)
                max_publish = max(max_publish, done - t_pub)
                published += 1
            if not args.loop:
                break
        if not stop:
            # Let reliable subscribers receive the tail before the publishers disappear.
            for p in pubs.values():
                p.wait_for_all_acked(Duration(seconds=2))
        log.info(f"Played {published} messages; {_lateness_summary(lateness)}; "
                 f"longest publish() {max_publish / 1e6:.3f} ms")
        return 0
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


class ReadAhead:
    """Iterate ``source`` in a reader thread, up to ``size`` items ahead of the consumer.

    rosbags decodes a whole MCAP chunk at once (several ms); in the publishing thread that
    would make every message due meanwhile late. Errors in the reader are re-raised here.
    """

    _END = object()

    def __init__(self, source, size: int) -> None:
        import queue
        import threading

        self._q: queue.Queue = queue.Queue(maxsize=size)
        self._done = threading.Event()
        self._error: BaseException | None = None
        self._source = source
        self._thread = threading.Thread(target=self._fill, name="bag-read-ahead", daemon=True)
        self._thread.start()

    def _put(self, item) -> bool:
        import queue

        while not self._done.is_set():
            try:
                self._q.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def _fill(self) -> None:
        try:
            for item in self._source:
                if not self._put(item):
                    return
        except BaseException as err:  # noqa: BLE001 - handed to the consumer
            self._error = err
        self._put(self._END)

    def __iter__(self):
        try:
            while True:
                item = self._q.get()
                if item is self._END:
                    if self._error is not None:
                        raise self._error
                    return
                yield item
        finally:
            self._done.set()


def _lateness_summary(lateness: list[int]) -> str:
    """Median / 95th percentile / max of how late messages were published [ms]."""
    if not lateness:
        return "no messages published"
    import numpy as np

    a = np.asarray(lateness, dtype=float) / 1e6
    return (f"lateness median {np.median(a):.3f} ms, p95 {np.percentile(a, 95):.3f} ms, "
            f"max {a.max():.3f} ms")


def _stamp(ns: int):
    from builtin_interfaces.msg import Time

    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def _sleep_until(t_ns: int, stop: StopFlag) -> None:
    """Sleep until monotonic time t_ns in short slices so a signal stops playback promptly."""
    while not stop:
        left = t_ns - time.monotonic_ns()
        if left <= 0:
            return
        time.sleep(min(left / 1e9, 0.05))


if __name__ == "__main__":
    sys.exit(main())
