"""Soak: the NDI driver's bring-up and polling over a serial line (pty) with line noise before the replies.

For each seed the Vega emulator (:class:`VegaEmulator`, serial pty, two tools) prefixes each reply with 1-16 random
bytes with probability ``--prob``; the driver (:class:`NdiDriver`, the whole serial bring-up: INIT at 9600, COMM to
115200, INIT, tools, TSTART) runs until 150 frames arrived. ``--busy N`` runs N busy loops beside (a loaded machine:
noise and a slow reader together are what made read timeouts). Figures (bench/benchlib.py lines)::

  ndi_noise_run               per seed: commands, read timeouts, CRC errors, bring-ups that failed (link_losses)
  ndi_noise_read_timeouts     all seeds: read timeouts in all, and per 1,000 commands

Exit status 1 when a seed does not reach its frames (the bring-up never got through) within 60 s.

  source scripts/env.sh && python soak/soak_ndi_noise.py [--prob 0.2] [--seeds 0-9] [--busy 2]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import sys
import threading
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from fullperc_drivers.ndi.driver import DriverConfig, NdiDriver, ToolConfig
from fullperc_eval.emulators.vega_device import ToolPose
from fullperc_eval.emulators.vega_server import FaultConfig, VegaEmulator

CONFIG = Path(__file__).resolve().parents[1] / "src" / "fullperc_drivers" / "config" / "emulator_roms"   # synthetic
NAMES = ["tool", "base"]
FRAMES = 150


def _source(t_ns: int) -> dict[str, ToolPose]:
    t = t_ns / 1e9
    out = {}
    for i, n in enumerate(NAMES):
        a = 0.7 * t + i
        p = np.array([-300.0 + 120 * i + 40 * np.cos(a), 40 * np.sin(a), -1300.0 - 60 * i])
        out[n] = ToolPose(p, Rotation.from_rotvec([0.1 * i, 0.3 * np.sin(a), 0.2]).as_quat(), 0.05)
    return out


def _busy() -> None:
    while True:
        pass


def run_seed(seed: int, prob: float) -> dict:
    emu = VegaEmulator(_source, {n: (CONFIG / f"{n}.rom").read_bytes() for n in NAMES},
                       faults=FaultConfig(garbage_prob=prob, seed=seed))
    emu.start(tcp=False)
    got, lock = [0], threading.Lock()

    def on_frame(_fr) -> None:
        with lock:
            got[0] += 1

    cfg = DriverConfig(tools=[ToolConfig(n, (CONFIG / f"{n}.rom").read_bytes()) for n in NAMES], rate_hz=0,
                       transport="serial", serial_device=emu.open_pty())
    d = NdiDriver(cfg, on_frame=on_frame)
    t0 = time.monotonic()
    d.start()
    try:
        while got[0] < FRAMES and time.monotonic() - t0 < 60:
            time.sleep(0.05)
    finally:
        d.stop()
        emu.stop()
    c = d.counters
    return {"name": "ndi_noise_run", "seed": seed, "prob": prob, "frames": got[0], "ok": got[0] >= FRAMES,
            "commands": c.commands, "timeouts": c.timeouts, "crc_errors": c.crc_errors, "garbled": c.garbled,
            "link_losses": c.link_losses, "noise_replies": emu.stats.garbage, "seconds": time.monotonic() - t0}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--prob", type=float, default=0.2, help="share of replies with noise before them")
    ap.add_argument("--seeds", default="0-9", help="A-B (inclusive)")
    ap.add_argument("--busy", type=int, default=2, help="busy loops beside the driver")
    args = ap.parse_args(argv)
    a, _, b = args.seeds.partition("-")
    seeds = range(int(a), int(b or a) + 1)
    busy = [mp.Process(target=_busy, daemon=True) for _ in range(args.busy)]
    for p in busy:
        p.start()
    try:
        runs = []
        for s in seeds:
            r = run_seed(s, args.prob)
            runs.append(r)
            print(json.dumps(r), flush=True)
    finally:
        for p in busy:
            p.terminate()
    timeouts, commands = sum(r["timeouts"] for r in runs), sum(r["commands"] for r in runs)
    print(json.dumps({"name": "ndi_noise_read_timeouts", "value": timeouts, "unit": "timeouts",
                      "per_1000_commands": 1000 * timeouts / max(commands, 1), "commands": commands,
                      "seeds": len(runs), "prob": args.prob, "busy": args.busy,
                      "bring_ups_failed": sum(not r["ok"] for r in runs)}), flush=True)
    return 0 if all(r["ok"] for r in runs) else 1


if __name__ == "__main__":
    sys.exit(main())
