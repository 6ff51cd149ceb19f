"""``python -m fullperc_eval.bag info|reindex BAG``: what metadata.yaml says about a bag; recover a bag.

``reindex`` (:func:`.recover.reindex`) is the command the reader's and the recorder's error messages name
when a bag was left incomplete by a killed recorder. ``echo``, ``pub`` and ``call`` run the topic and service
tools of :mod:`.topic_tools` (also installed as executables of their own), for systems without the ros2 CLI:
``python -m fullperc_eval.bag call /fusion_node/calibrate std_srvs/srv/Trigger``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .errors import BagError
from .metadata import METADATA_FILE
from .reader import BagReader
from .recover import reindex


def format_info(reader: BagReader) -> str:
    lines = [f"Files:             {', '.join(reader.info.get('relative_file_paths') or [])}",
             f"Storage id:        {reader.storage}",
             f"Duration:          {reader.duration / 1e9:.3f} s",
             f"Start:             {reader.start_time} ns",
             f"Messages:          {reader.message_count}",
             "Topic information:"]
    for t in reader.topics.values():
        lines.append(f"  Topic: {t.name} | Type: {t.msgtype} | Count: {t.count} | "
                     f"Serialization Format: {t.serialization_format}")
    return "\n".join(lines)


TOOLS = {"echo": "echo_main", "pub": "pub_main", "call": "call_main"}   # the commands of .topic_tools


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] in TOOLS:   # its own parser, options and exit status
        from . import topic_tools

        return getattr(topic_tools, TOOLS[argv[0]])(argv[1:])
    ap = argparse.ArgumentParser(prog="python -m fullperc_eval.bag", description=__doc__.split("\n")[0],
                                 epilog="also: echo TOPIC ..., pub TOPIC TYPE ..., call SERVICE TYPE ... "
                                        "(python -m fullperc_eval.bag call -h)")
    sub = ap.add_subparsers(dest="cmd", required=True)
    sub.add_parser("info", help="print what metadata.yaml says about a bag").add_argument("bag")
    sub.add_parser("reindex", help="recover a bag: complete killed MCAP files, checkpoint "
                                  "sqlite3 logs, rebuild metadata.yaml").add_argument("bag")
    args = ap.parse_args(argv)
    try:
        if args.cmd == "info":
            print(format_info(BagReader(args.bag)))
        else:
            meta, reports = reindex(args.bag)
            for r in reports:
                if r.recovered and r.file.endswith(".db3"):
                    print(f"{r.file}: recovered {r.messages} messages (write-ahead log checkpointed)")
                elif r.recovered:
                    print(f"{r.file}: recovered {r.messages} messages"
                          + (f" (stopped at: {r.error})" if r.error else "") + f"; original kept as {r.file}.orig")
                else:
                    print(f"{r.file}: complete")
            info = meta["rosbag2_bagfile_information"]
            print(f"wrote {Path(args.bag) / METADATA_FILE}: {info['message_count']} messages, "
                  f"{len(info['topics_with_message_count'])} topics")
    except BagError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
