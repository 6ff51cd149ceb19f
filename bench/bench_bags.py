"""Bag write/read throughput of fullperc_eval.bag (writer, reader) against rosbags' own Writer/AnyReader.

Figures (medians over repeats, messages per second, 20 000 raw PoseStamped CDR messages):
  bags_write_mcap   BagWriter.write, MCAP, flushed every 0.5 s     baseline: rosbags Writer (MCAP, v9)
  bags_write_sqlite BagWriter.write, sqlite3 (WAL, periodic commit) baseline: rosbags Writer (SQLITE3, v9)
  bags_read_mcap    BagReader.messages                             baseline: rosbags AnyReader.messages
ratio > 1 means faster than the baseline for the figures in msg/s.
"""

from __future__ import annotations

import shutil
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from benchlib import emit, median_time  # noqa: E402

N = 20_000
TOPIC, TYPE = "/omc/tool/pose", "geometry_msgs/msg/PoseStamped"


def main() -> None:
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import StoragePlugin, Writer

    from fullperc_eval.bag.reader import BagReader
    from fullperc_eval.bag.types import fullperc_typestore
    from fullperc_eval.bag.writer import BagWriter

    ts = fullperc_typestore()
    T = ts.types
    msg = T[TYPE](header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=1, nanosec=2),
                                                  frame_id="base"),
                  pose=T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=1.0, y=2.0, z=3.0),
                                                   orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0,
                                                                                                 z=0.0, w=1.0)))
    raw = bytes(ts.serialize_cdr(msg, TYPE))
    t0 = 1_700_000_000_000_000_000
    tmp = Path(tempfile.mkdtemp(prefix="bench_bags_"))
    counter = iter(range(10**6))

    def fresh() -> Path:
        return tmp / f"b{next(counter)}"

    def ours(storage: str):
        def run():
            with BagWriter(fresh(), storage=storage, typestore=ts) as w:
                w.add_topic(TOPIC, TYPE)
                for i in range(N):
                    w.write(TOPIC, t0 + i * 1_000_000, raw)
        return run

    def theirs(plugin):
        def run():
            with Writer(fresh(), version=9, storage_plugin=plugin) as w:
                c = w.add_connection(TOPIC, TYPE, typestore=ts)
                for i in range(N):
                    w.write(c, t0 + i * 1_000_000, raw)
        return run

    try:
        for name, mine, base in (("bags_write_mcap", ours("mcap"), theirs(StoragePlugin.MCAP)),
                                 ("bags_write_sqlite", ours("sqlite3"), theirs(StoragePlugin.SQLITE3))):
            t_ours, t_base = median_time(mine, repeats=5), median_time(base, repeats=5)
            emit(name, N / t_ours, "msg/s", baseline=N / t_base, messages=N)

        bag = tmp / "read"
        with BagWriter(bag, typestore=ts) as w:
            w.add_topic(TOPIC, TYPE)
            for i in range(N):
                w.write(TOPIC, t0 + i * 1_000_000, raw)

        def read_ours():
            with BagReader(bag) as r:
                assert sum(1 for _ in r.messages()) == N

        def read_theirs():
            with AnyReader([bag]) as r:
                assert sum(1 for _ in r.messages()) == N

        t_ours, t_base = median_time(read_ours, repeats=5), median_time(read_theirs, repeats=5)
        emit("bags_read_mcap", N / t_ours, "msg/s", baseline=N / t_base, messages=N)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
