"""``make soak``: run every soak/soak_*.py in its own process and pass their JSON lines through, as they come.

Soaks run for minutes (the NDI link alone for 5), so their lines are forwarded live; everything else a soak
prints goes to stderr. One JSON line per figure, the bench/benchlib.py format. Not part of ``make test``.
Exit status is non-zero if any soak failed (a soak exits 1 when a figure misses its target).

  source scripts/env.sh && python soak/run_all.py [ndi record fuzz signals]   (default: all)
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path


def main() -> int:
    here = Path(__file__).resolve().parent
    only = sys.argv[1:]
    failed = []
    for path in sorted(here.glob("soak_*.py")):
        if only and path.stem not in only and path.stem.removeprefix("soak_") not in only:
            continue
        print(f"# {path.name}", file=sys.stderr, flush=True)
        t0 = time.monotonic()
        proc = subprocess.Popen([sys.executable, str(path)], stdout=subprocess.PIPE, text=True)
        assert proc.stdout is not None
        for line in proc.stdout:
            line = line.rstrip("\n")
            try:
                json.loads(line)
                print(line, flush=True)
            except ValueError:
                print(line, file=sys.stderr, flush=True)
        rc = proc.wait()
        print(f"# {path.name}: exit {rc} after {time.monotonic() - t0:.0f} s", file=sys.stderr, flush=True)
        if rc != 0:
            failed.append(path.name)
            print(json.dumps({"name": path.stem, "error": f"exit {rc}"}), flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
