"""Soak: the long profile of test_vega_emulator_node.py's fault-injection test (issue 14): ``ndi_driver`` against the
``vega_emulator`` with 1 % corrupted replies and a link drop every 30 s, for 120 s.

``make test`` runs that test for a few seconds of the same fault mix (a drop every 2 s until three link losses were
reconnected); this runs it with ``FULLPERC_NDI_SOAK=1``: two minutes, and on top of the in-suite checks the
wall-clock figures that have no place in ``make test`` -- every reconnect within 1 s, and over half the 60 Hz pose
rate across the whole run. Figures (bench/benchlib.py lines)::

  ndi_drops_soak_passed         1 when the test passed (its failure, on stderr, otherwise)
  ndi_drops_reconnect_max_s     the slowest reconnect (each one listed), with link losses and CRC errors counted
  ndi_drops_pose_rate_hz        tool poses received per second over the run

Exit status 1 when the test failed.

  source scripts/env.sh && python soak/soak_ndi_drops.py
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))

from benchlib import emit, emit_error  # noqa: E402

TEST = "src/fullperc_eval/test/test_vega_emulator_node.py::test_soak_corrupted_replies_and_periodic_drops"


def main() -> int:
    with tempfile.TemporaryDirectory(prefix="soak_ndi_drops_") as tmp:
        report = Path(tmp) / "report.json"
        env = {**os.environ, "FULLPERC_NDI_SOAK": "1", "FULLPERC_NDI_SOAK_REPORT": str(report)}
        proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:xdist", "-p", "no:cacheprovider", TEST],
                              cwd=ROOT, env=env, capture_output=True, text=True)
        ok = proc.returncode == 0
        emit("ndi_drops_soak_passed", 1 if ok else 0, "bool", test=TEST)
        if not ok:
            print(proc.stdout[-6000:], proc.stderr[-2000:], sep="\n", file=sys.stderr)
        if not report.exists():
            emit_error("ndi_drops_reconnect_max_s", "s", "the test wrote no figures (it failed before)")
            return 1
        r = json.loads(report.read_text())
    d = r["reconnect_durations_s"]
    emit("ndi_drops_reconnect_max_s", max(d) if d else float("nan"), "s", each=d, link_losses=r["link_losses"],
         reconnects=r["reconnects"], crc_errors=r["crc_errors"], retries=r["retries"], timeouts=r["timeouts"])
    emit("ndi_drops_pose_rate_hz", r["poses"] / r["elapsed_s"], "Hz", poses=r["poses"],
         elapsed_s=round(r["elapsed_s"], 1), fault_free_rate_hz=60.0)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
