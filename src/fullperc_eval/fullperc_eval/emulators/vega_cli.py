"""``vega_emulator`` executable: a scripted NDI Polaris Vega on TCP (and a pty), for drivers and third-party clients.

Tools and ROMs default to ``tool`` and ``base`` from ``fullperc_drivers/config/emulator_roms`` (synthetic ROMs, which
a real Vega must never get) at fixed poses; ``--config``
YAML, ``--tool``, ``--pose``, ``--circle`` and ``--hidden`` script other pose sets, the fault options exercise a
client's error handling (see :mod:`.vega_server`). ``--help`` lists everything.
"""

from __future__ import annotations

import argparse
import math
import os
import signal
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from fullperc_common.share import share_path
from fullperc_drivers.ndi.rom import EMULATOR_ROM_DIR

from .vega_device import PoseSource, ToolPose
from .vega_server import FaultConfig, VegaEmulator


def _default_rom_dir() -> Path:
    """``config/emulator_roms`` of fullperc_drivers (installed share directory, else the source tree): the synthetic
    tool ROMs a relative ``rom`` is looked up in."""
    return share_path("fullperc_drivers", "config", EMULATOR_ROM_DIR)


@dataclass
class ScriptedTool:
    """One tool of the executable's pose set: static pose, optional circle and blinking."""

    position_mm: tuple[float, float, float]
    quat_xyzw: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)
    error_mm: float = 0.1
    circle_radius_mm: float = 0.0
    circle_period_s: float = 4.0
    hidden_every_s: float = 0.0  # 0: always shown
    hidden_for_s: float = 0.0

    def pose(self, t_s: float) -> ToolPose | None:
        if self.hidden_every_s > 0 and (t_s % self.hidden_every_s) >= self.hidden_every_s - self.hidden_for_s:
            return None
        p = np.array(self.position_mm, dtype=float)
        if self.circle_radius_mm:
            a = 2 * math.pi * t_s / self.circle_period_s
            p = p + self.circle_radius_mm * np.array([math.cos(a), math.sin(a), 0.0])
        return ToolPose(p, np.array(self.quat_xyzw, dtype=float), self.error_mm)


def scripted_source(tools: dict[str, ScriptedTool], t0_ns: int | None = None) -> PoseSource:
    t0 = time.time_ns() if t0_ns is None else t0_ns

    def source(t_ns: int) -> dict[str, ToolPose | None]:
        t = (t_ns - t0) / 1e9
        return {name: st.pose(t) for name, st in tools.items()}

    return source


DEFAULT_POSES = {
    "tool": dict(position_mm=(0.0, 0.0, -1500.0), quat_xyzw=(0.0, 0.0, 0.0, 1.0)),
    "base": dict(position_mm=(150.0, 80.0, -1700.0), quat_xyzw=(0.0, 0.0, 0.3826834, 0.9238795)),
}


def load_config(path: str | None) -> dict:
    if not path:
        return {}
    with open(path) as f:
        return yaml.safe_load(f) or {}


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="vega_emulator", description="NDI Polaris Vega emulator (Combined API).")
    ap.add_argument("--config", help="YAML: tools: {name: {rom, position_mm, quat_xyzw, error_mm, "
                                     "circle_radius_mm, circle_period_s, hidden_every_s, hidden_for_s}}")
    ap.add_argument("--host", default="127.0.0.1")
    ap.add_argument("--port", type=int, default=8765, help="TCP port (0: any free port)")
    ap.add_argument("--port-file", help="write the bound TCP port here once listening")
    ap.add_argument("--no-tcp", action="store_true")
    ap.add_argument("--pty", action="store_true", help="also serve the serial protocol on a pty")
    ap.add_argument("--pty-link", help="symlink to create to the pty slave")
    ap.add_argument("--tool", action="append", default=[], metavar="NAME=ROM",
                    help="tool name and .rom path (default: tool and base from fullperc_drivers/config/emulator_roms)")
    ap.add_argument("--pose", action="append", default=[], metavar="NAME=x,y,z[,qx,qy,qz,qw]",
                    help="static pose [mm] in the ots frame")
    ap.add_argument("--hidden", action="append", default=[], metavar="NAME", help="tool never visible")
    ap.add_argument("--circle", type=float, default=0.0, metavar="RADIUS_MM", help="move every tool on a circle")
    ap.add_argument("--rate", type=float, default=60.0, help="frame rate [Hz]")
    ap.add_argument("--freeze-tag", default="Polaris Vega 010")
    ap.add_argument("--corrupt-crc", type=float, default=0.0, help="probability per reply")
    ap.add_argument("--garbage", type=float, default=0.0, help="probability per reply")
    ap.add_argument("--delay-prob", type=float, default=0.0)
    ap.add_argument("--delay-s", type=float, default=0.0)
    ap.add_argument("--drop-every", type=float, default=0.0, help="drop the link every N seconds")
    ap.add_argument("--seed", type=int, default=None)
    return ap


def _floats(txt: str, n: tuple[int, ...]) -> list[float]:
    v = [float(x) for x in txt.split(",")]
    if len(v) not in n:
        raise ValueError(f"expected {n} comma-separated numbers, got {txt!r}")
    return v


def make_emulator(args: argparse.Namespace) -> VegaEmulator:
    cfg = load_config(args.config)
    rom_dir = _default_rom_dir()
    tool_cfg: dict[str, dict] = {k: dict(v or {}) for k, v in (cfg.get("tools") or {}).items()}
    if not tool_cfg and not args.tool:
        tool_cfg = {k: dict(v) for k, v in DEFAULT_POSES.items()}
    for spec in args.tool:
        name, rom = spec.split("=", 1)
        tool_cfg.setdefault(name, {})["rom"] = rom
    for spec in args.pose:
        name, vals = spec.split("=", 1)
        v = _floats(vals, (3, 7))
        tool_cfg.setdefault(name, {})["position_mm"] = v[:3]
        if len(v) == 7:
            tool_cfg[name]["quat_xyzw"] = v[3:]
    roms: dict[str, bytes] = {}
    scripted: dict[str, ScriptedTool] = {}
    for i, (name, tc) in enumerate(tool_cfg.items()):
        rom_path = Path(tc.get("rom", f"{name}.rom"))
        if not rom_path.is_absolute() and not rom_path.exists():
            rom_path = rom_dir / rom_path
        roms[name] = rom_path.read_bytes()
        if name in args.hidden:
            continue
        pos = tc.get("position_mm", DEFAULT_POSES.get(name, {}).get("position_mm", (60.0 * i, 0.0, -1500.0)))
        scripted[name] = ScriptedTool(
            tuple(pos), tuple(tc.get("quat_xyzw", (0.0, 0.0, 0.0, 1.0))), float(tc.get("error_mm", 0.1)),
            float(tc.get("circle_radius_mm", args.circle)), float(tc.get("circle_period_s", 4.0)),
            float(tc.get("hidden_every_s", 0.0)), float(tc.get("hidden_for_s", 0.0)))
    faults = FaultConfig(args.corrupt_crc, args.garbage, args.delay_prob, args.delay_s,
                         args.drop_every or None, seed=args.seed)
    return VegaEmulator(scripted_source(scripted), roms, args.rate, args.host, args.port, faults,
                        freeze_tag=args.freeze_tag)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    emu = make_emulator(args)
    emu.start(tcp=not args.no_tcp)
    if not args.no_tcp:
        print(f"vega_emulator listening on {emu.host}:{emu.port}", flush=True)
        if args.port_file:
            tmp = args.port_file + ".tmp"
            Path(tmp).write_text(str(emu.port))
            os.replace(tmp, args.port_file)
    if args.pty or args.pty_link:
        path = emu.open_pty(args.pty_link)
        print(f"vega_emulator serial on {path}", flush=True)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    while not stop.wait(1.0):
        pass
    emu.stop()
    s = emu.stats
    print(f"vega_emulator stopped: {s}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
