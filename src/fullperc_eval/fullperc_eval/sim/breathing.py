"""The twin's third tracked target: a patient reference frame on the patient, moving only as the patient breathes.

A navigated percutaneous procedure tracks the patient too: a reference marker frame fixed on the patient (on a post
or an adhesive base on the skin near the site) whose motion is the breathing's, a few millimetres at 12-20 breaths
a minute. It is a third kind of motion beside the arm's slow arc and the walking hand (:mod:`.walker`): almost
static, so it is the target where the OMC's hops (a camera coming into or leaving its view) show plainest. Defined
in ``scene.yaml``'s ``reference_target`` section (absent or ``enabled: false``: no reference target):

* **place**: ``pose_in_omc`` is the frame's pose at end-exhale (position [m] and quaternion x y z w in omc), set up
  facing the trackers as such a frame is;
* **breathing**: the displacement along ``direction`` (mostly up, a little towards the feet) is
  ``A_k (1 - cos(2 pi u)) / 2`` in breath k (u = 0..1 over its period ``T_k``): zero at end-exhale, the most
  reproducible point of a breath, ``A_k`` at end-inhale, velocity zero at both, so the motion is smooth across
  breaths. Per seed a mean rate is drawn in ``rate_per_min`` and a mean depth (peak to peak) in ``amplitude_mm``;
  each breath varies about them by ``cycle_variation`` (relative SD), clipped to the same ranges, and the run starts
  at a seeded point of the first breath. The frame tilts with the rising surface under it: ``tilt_deg_per_mm`` per
  millimetre of displacement, about the table's long axis (omc x);
* **no carrier**: nobody holds it; it is occluded by what is in the room -- the arm's links, the staff, the static
  boxes -- and by the instrument's carrier (the nurse, :mod:`.walker`) when she passes between it and a camera or
  the Vega. Like the instrument it occludes nothing else.

Measurements: :func:`.target_model.measure_target`, with **separate random streams** (children 7, 8, 9 of the
seed's ``SeedSequence``: breathing, OMC noise, Vega noise; the scene uses 0-3, the instrument 4-6), so adding it
never changes a draw of the other bodies (``test_sim_breathing.py``). Ground truth: ``run.extra_truth[name]``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from fullperc_common.transforms import make_T

from .run import SimRun
from .scene import BodyDef, Scene, SceneError
from .target_model import Carrier, enabled_section, measure_target, target_body

STREAMS = (7, 8, 9)   # SeedSequence children of the run seed: breathing, OMC noise, Vega noise
SECTION = "reference_target"
CYCLES = 64           # breaths drawn per seed (>= 192 s at 20 /min; the motion repeats after them): a fixed count, so
                      # the draws do not depend on a run's length


@dataclass(frozen=True)
class BreathingDef:
    """``scene.yaml`` ``reference_target``: the frame, where it sits and how the patient breathes."""

    body: BodyDef
    rom_file: str                       # NDI tool definition in fullperc_drivers/config/emulator_roms
    T_rest: np.ndarray                  # (4, 4) the frame's pose in omc at end-exhale
    rate_per_min: tuple[float, float]   # breaths per minute: the seed's mean and every breath within this range
    amplitude_mm: tuple[float, float]   # peak-to-peak displacement [mm] of a breath, likewise
    direction: np.ndarray               # (3,) unit direction of the displacement in omc
    tilt_deg_per_mm: float              # tilt about omc x per mm of displacement [deg/mm]
    cycle_variation: float              # relative SD of a breath's period and depth about the seed's means

    @property
    def name(self) -> str:
        return self.body.name


def load_breathing(cfg: dict) -> BreathingDef | None:
    """The ``reference_target`` section of a scene config, or None when it is absent or ``enabled: false``."""
    sec = enabled_section(cfg, SECTION)
    if sec is None:
        return None
    src = cfg.get("_source", "<memory>")
    body = target_body(cfg, SECTION)
    try:
        b = sec["breathing"]
        direction = np.asarray(b.get("direction", [0, 0, 1]), dtype=float)
        d = BreathingDef(
            body=body,
            rom_file=str(sec["rom_file"]), T_rest=make_T(sec["pose_in_omc"]["position"],
                                                          sec["pose_in_omc"]["orientation"]),
            rate_per_min=tuple(float(v) for v in b["rate_per_min"]),
            amplitude_mm=tuple(float(v) for v in b["amplitude_mm"]),
            direction=direction / np.linalg.norm(direction), tilt_deg_per_mm=float(b.get("tilt_deg_per_mm", 0.0)),
            cycle_variation=float(b.get("cycle_variation", 0.0)))
    except (KeyError, TypeError, ValueError, IndexError, ZeroDivisionError) as e:
        raise SceneError(f"scene file {src}: field '{SECTION}': {type(e).__name__}: {e}") from None
    if not (np.isfinite(d.T_rest).all() and np.isfinite(d.direction).all()):
        raise SceneError(f"scene file {src}: '{SECTION}.pose_in_omc' and 'breathing.direction' must be finite")
    for key in ("rate_per_min", "amplitude_mm"):
        lo_hi = getattr(d, key)
        if len(lo_hi) != 2 or not 0 < lo_hi[0] <= lo_hi[1]:
            raise SceneError(f"scene file {src}: '{SECTION}.breathing.{key}' needs [low, high], 0 < low <= high")
    return d


class BreathingMotion:
    """The reference frame's true pose over time (one seeded instance; a :class:`~.target_model.ExtraTarget`)."""

    streams = STREAMS

    def __init__(self, d: BreathingDef, seed: int) -> None:
        self.d = d
        self.body, self.rom_file = d.body, d.rom_file
        rng = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(STREAMS[0],)))
        (r_lo, r_hi), (a_lo, a_hi) = d.rate_per_min, d.amplitude_mm
        self.rate_per_min = float(rng.uniform(r_lo, r_hi))       # the seed's mean rate and depth
        self.amplitude_m = float(rng.uniform(a_lo, a_hi)) * 1e-3
        cv = d.cycle_variation
        self.period_s = np.clip(60.0 / self.rate_per_min * (1.0 + cv * rng.standard_normal(CYCLES)),
                                60.0 / r_hi, 60.0 / r_lo)
        self.depth_m = np.clip(self.amplitude_m * (1.0 + cv * rng.standard_normal(CYCLES)), a_lo * 1e-3, a_hi * 1e-3)
        self.start_s = np.concatenate([[0.0], np.cumsum(self.period_s)])   # breath k: [start_s[k], start_s[k + 1])
        self.t0_s = float(rng.uniform(0.0, self.period_s[0]))               # where in the first breath the run starts

    def displacement(self, t_s: np.ndarray) -> np.ndarray:
        """(F,) displacement [m] along the breathing direction at task times ``t_s`` [s]: 0 at end-exhale."""
        t = np.mod(np.asarray(t_s, float) + self.t0_s, self.start_s[-1])
        k = np.clip(np.searchsorted(self.start_s, t, side="right") - 1, 0, CYCLES - 1)
        u = (t - self.start_s[k]) / self.period_s[k]
        return self.depth_m[k] * 0.5 * (1.0 - np.cos(2.0 * np.pi * u))

    def poses(self, t_s: np.ndarray) -> np.ndarray:
        """(F, 4, 4) true poses of the frame in omc at task times ``t_s`` [s]."""
        s = self.displacement(t_s)
        tilt = Rotation.from_rotvec(np.outer(np.radians(self.d.tilt_deg_per_mm) * s * 1e3, [1.0, 0.0, 0.0]))
        T = np.tile(np.eye(4), (len(s), 1, 1))
        T[:, :3, :3] = tilt.as_matrix() @ self.d.T_rest[:3, :3]
        T[:, :3, 3] = self.d.T_rest[:3, 3] + s[:, None] * self.d.direction
        return T


def breathing_reference(scene: Scene) -> BreathingMotion | None:
    """The scene's seeded reference frame (None without a ``reference_target`` section or with ``enabled: false``)."""
    d = load_breathing(scene.config)
    return None if d is None else BreathingMotion(d, scene.seed)


def add_reference(run: SimRun, scene: Scene, carriers: list[Carrier], noise: bool = True,
                  staff: bool = True) -> SimRun:
    """Measure the scene's reference frame over ``run``'s frames, ``carriers`` (the other targets' people) occluding
    it too, and add it to ``run`` (in place; also returned); a scene without the section leaves the run unchanged.

    Adds ``run.omc.bodies[name]``, ``run.ots.tools[name]``, ``run.extra_truth[name]`` and its entry in
    ``run.info['extra_targets']`` (with the seed's breathing rate [1/min] and depth [mm]).
    """
    ref = breathing_reference(scene)
    if ref is None:
        return run
    measure_target(run, scene, ref, carriers, noise=noise, staff=staff)
    run.info.setdefault("extra_targets", {})[ref.d.name] = {
        "kind": "breathing", "omc_id": ref.d.body.id, "rom_file": ref.d.rom_file,
        "rate_per_min": round(ref.rate_per_min, 3), "amplitude_mm": round(ref.amplitude_m * 1e3, 3)}
    return run
