"""Run every bench/bench_*.py in its own process and pass their JSON lines through.

Each benchmark prints one JSON object per figure; anything else it prints goes to stderr here.
Exit status is non-zero if any benchmark failed.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path


def main() -> int:
    here = Path(__file__).resolve().parent
    only = sys.argv[1:]
    failed = []
    for path in sorted(here.glob("bench_*.py")):
        if only and path.stem not in only and path.stem.removeprefix("bench_") not in only:
            continue
        print(f"# {path.name}", file=sys.stderr, flush=True)
        proc = subprocess.run([sys.executable, str(path)], capture_output=True, text=True)
        for line in proc.stdout.splitlines():
            try:
                json.loads(line)
                print(line, flush=True)
            except ValueError:
                print(line, file=sys.stderr)
        sys.stderr.write(proc.stderr)
        if proc.returncode != 0:
            failed.append(path.name)
            print(json.dumps({"name": path.stem, "error": f"exit {proc.returncode}"}), flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
