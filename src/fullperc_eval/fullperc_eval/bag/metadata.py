"""metadata.yaml of a rosbag2 bag (Jazzy, version 9) and the per-topic / per-file records it is built from.

Key order and content follow rosbag2_storage's yaml.hpp (the conventions are those of the project's reference
notes on rosbag2 bags, ``reference/bags_ros2.md`` §1). The file is replaced atomically, so a reader (or a
recovery after a kill) never sees a half-written one.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from .errors import BagError

METADATA_VERSION = 9
METADATA_FILE = "metadata.yaml"
STORAGES = ("mcap", "sqlite3")
STORAGE_EXT = {"mcap": ".mcap", "sqlite3": ".db3"}
REINDEX_HINT = "python -m fullperc_eval.bag reindex"  # the command that rebuilds metadata.yaml (see .cli)


@dataclass
class TopicInfo:
    """One recorded topic: what goes into topics_with_message_count (+ the schema for MCAP)."""

    name: str
    msgtype: str
    offered_qos: list[dict[str, Any]] = field(default_factory=list)
    type_hash: str = ""
    serialization_format: str = "cdr"
    msgdef: str = ""
    encoding: str = "ros2msg"
    count: int = 0

    def metadata(self) -> dict[str, Any]:
        return {
            "topic_metadata": {
                "name": self.name,
                "type": self.msgtype,
                "serialization_format": self.serialization_format,
                "offered_qos_profiles": list(self.offered_qos),
                "type_description_hash": self.type_hash,
            },
            "message_count": self.count,
        }


@dataclass
class FileInfo:
    path: str  # relative to the bag directory
    count: int = 0
    start: int | None = None
    end: int | None = None

    def add(self, t: int) -> None:
        self.count += 1
        self.start = t if self.start is None else min(self.start, t)
        self.end = t if self.end is None else max(self.end, t)


def build_metadata(storage: str, topics: Iterable[TopicInfo], files: Sequence[FileInfo], *,
                   compression_format: str = "", compression_mode: str = "",
                   custom_data: dict[str, str] | None = None, ros_distro: str | None = None) -> dict:
    """metadata.yaml content (v9) in rosbag2's key order (rosbag2_storage yaml.hpp)."""
    starts = [f.start for f in files if f.start is not None]
    ends = [f.end for f in files if f.end is not None]
    start = min(starts) if starts else 0
    duration = (max(ends) - start) if ends else 0
    info = {
        "version": METADATA_VERSION,
        "storage_identifier": storage,
        "duration": {"nanoseconds": int(duration)},
        "starting_time": {"nanoseconds_since_epoch": int(start)},
        "message_count": int(sum(f.count for f in files)),
        "topics_with_message_count": [t.metadata() for t in topics],
        "compression_format": compression_format,
        "compression_mode": compression_mode,
        "relative_file_paths": [f.path for f in files],
        "files": [{
            "path": f.path,
            "starting_time": {"nanoseconds_since_epoch": int(f.start or 0)},
            "duration": {"nanoseconds": int((f.end - f.start) if f.count else 0)},
            "message_count": int(f.count),
        } for f in files],
        "custom_data": dict(custom_data) if custom_data else None,
        "ros_distro": ros_distro if ros_distro is not None else (os.environ.get("ROS_DISTRO") or "jazzy"),
    }
    return {"rosbag2_bagfile_information": info}


# libyaml's emitter when PyYAML was built with it (the wheels are): the same text as yaml.safe_dump, ~5x faster. The
# recorder rewrites metadata.yaml at every flush (writer.py); with the pure-Python emitter that was 10 s of a demo
# recording's 50 s (79 rewrites of a 28 kB file, profiled), on a machine where fusion_node needs the CPU
_DUMPER = getattr(yaml, "CSafeDumper", yaml.SafeDumper)
# ... and its parser for reading it: the same safe constructor and resolver (the same Python objects), ~9x faster;
# every evaluation opens the bag's metadata first (60 ms of a 12 kB file with the pure-Python parser, a tenth of an
# offline evaluation of a 28 s bag)
_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def dump_yaml(data, **kw) -> str:
    """``yaml.safe_dump(data, **kw)``, through libyaml when available."""
    return yaml.dump(data, Dumper=_DUMPER, **kw)


def write_metadata(bagdir: Path, metadata: dict) -> None:
    """Atomically replace metadata.yaml (a reader never sees a half-written file)."""
    bagdir = Path(bagdir)
    tmp = bagdir / (METADATA_FILE + ".tmp")
    tmp.write_text(dump_yaml(metadata, sort_keys=False, default_flow_style=False))
    os.replace(tmp, bagdir / METADATA_FILE)


def load_metadata(bagdir: Path) -> dict:
    """The rosbag2_bagfile_information map of a bag directory; BagError with a hint if absent/bad."""
    bagdir = Path(bagdir)
    path = bagdir / METADATA_FILE
    if not bagdir.exists():
        raise BagError(f"bag {str(bagdir)!r} does not exist")
    if not bagdir.is_dir():
        raise BagError(f"bag {str(bagdir)!r} is not a directory (give the rosbag2 bag directory)")
    if not path.is_file():
        raise BagError(f"bag {str(bagdir)!r} has no {METADATA_FILE} (recorder killed before its first flush, "
                       f"or not a rosbag2 bag); rebuild it with: {REINDEX_HINT} {bagdir}")
    try:
        data = yaml.load(path.read_text(), Loader=_LOADER)
        info = data["rosbag2_bagfile_information"]
        for key in ("version", "storage_identifier", "topics_with_message_count", "relative_file_paths"):
            info[key]  # noqa: B018 - presence check
    except (yaml.YAMLError, TypeError, KeyError, UnicodeDecodeError) as err:
        raise BagError(f"{path} is not a valid rosbag2 metadata file ({type(err).__name__}: {err}); "
                       f"rebuild it with: {REINDEX_HINT} {bagdir}") from None
    return info
