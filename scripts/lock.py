"""Write requirements/lock-cpXY.txt: the exact versions of every distribution in the venv.

Installing from the lock reproduces the tested closure. Distributions that come only as
.egg-info inside the ROS wheels (e.g. ``rclpy 7.1.5`` beside ``ros_rclpy 7.1.6``) are not on
the index and are skipped, as is pip itself.
"""

from __future__ import annotations

import sys
from importlib import metadata
from pathlib import Path

SKIP = {"pip", "setuptools", "wheel"}


def main() -> None:
    rows = {}
    for dist in metadata.distributions():
        path = str(getattr(dist, "_path", ""))
        if not path.endswith(".dist-info"):
            continue
        name = dist.metadata["Name"]
        if name.lower() in SKIP:
            continue
        rows[name.lower()] = f"{name}=={dist.version}"
    tag = f"cp{sys.version_info[0]}{sys.version_info[1]}"
    out = Path(__file__).resolve().parent.parent / "requirements" / f"lock-{tag}.txt"
    header = (
        f"# Exact closure for Python {sys.version_info[0]}.{sys.version_info[1]}, written by `make lock`.\n"
        "# scripts/setup.sh installs from this file; edit requirements/*.txt and re-run `make lock`.\n"
        "setuptools<80\n"
    )
    out.write_text(header + "\n".join(rows[k] for k in sorted(rows)) + "\n")
    print(f"wrote {out} ({len(rows)} distributions)")


if __name__ == "__main__":
    main()
