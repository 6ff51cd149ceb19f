"""The twin's second tracked target: a hand-held instrument carried through the room by a staff member.

The paper's point is *full* perception of the OR; the arm-held ``tool`` alone is one target. This module adds a
second one with a different kind of motion -- a person walking, not a robot turning one joint -- defined in
``scene.yaml``'s ``second_target`` section (absent or ``enabled: false``: no second target):

* **path**: waypoints in ``omc`` (hand height), walked one after the other with a minimum-jerk profile per leg
  (zero velocity and acceleration at each waypoint, so the path is smooth) at ``speed`` m/s on average, holding
  ``dwell_s`` at each waypoint; after the last one the instrument stays there. The waypoints are fixed (the same for
  every seed) and chosen through the regions of the margin model: the periphery (PVV), the far side of the table
  (GVV), the head end between table and anaesthesia cart (occluded), the Vega's volume on the robot side (BVV);
* **hand**: seeded jitter on top of the path -- a slow sway (sum of sinusoids, ``sway_mm`` RMS per axis at
  ``sway_hz``), physiological tremor (``tremor_mm`` at ``tremor_hz``) and a wobble of the orientation
  (``rotation_deg`` RMS per axis at the sway frequencies). The plate faces up and towards the Vega, as a person
  shows an instrument to a tracker;
* **carrier**: a vertical capsule (the person) standing ``carrier.offset_m`` behind the hand, away from the table
  centre. It occludes the instrument's own markers (the person's body between an instrument and the cameras
  behind them: the "occluded stretches") and the other extra targets (the patient reference, :mod:`.breathing`),
  but **not** the arm-held tool, the base marker or the rig: those keep their data bit for bit, so the committed
  bags and benchmarks of the six paper tasks do not change with this target (a simplification; the room's other
  staff occlude everything).

Measurements: :func:`.target_model.measure_target` (the same OMC and Vega models as the arm-held tool, with the
arm's links, the room's staff, the static boxes and the carrier as occluders, and the Vega bump), with **separate
random streams** (children 4, 5, 6 of the seed's ``SeedSequence``; the scene uses 0-3), so adding this target never
changes a draw of the others. Ground truth: the instrument's true pose, ``run.extra_truth[name]``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from .run import SimRun
from .scene import BodyDef, Scene, SceneError
from .target_model import Carrier, enabled_section, measure_target, target_body

STREAMS = (4, 5, 6)   # SeedSequence children of the run seed: path jitter, OMC noise, Vega noise


@dataclass(frozen=True)
class HandHeldDef:
    """``scene.yaml`` ``second_target``: the instrument, its path, its carrier and the hand's jitter."""

    body: BodyDef
    rom_file: str                 # NDI tool definition in fullperc_drivers/config/emulator_roms (ndi_driver uploads it)
    waypoints: np.ndarray         # (N, 3) [m] in omc
    dwell_s: np.ndarray           # (N,) [s] held at each waypoint
    speed: float                  # [m/s] mean walking speed of a leg
    normal_to_vega: float         # horizontal weight of the plate normal towards the Vega (0 = face up)
    carrier_radius: float
    carrier_height: float
    carrier_offset: float         # [m] body axis behind the hand, away from the table centre
    sway_mm: float
    sway_hz: tuple[float, float]
    tremor_mm: float
    tremor_hz: tuple[float, float]
    rotation_deg: float

    @property
    def name(self) -> str:
        return self.body.name


def load_hand_held(cfg: dict) -> HandHeldDef | None:
    """The ``second_target`` section of a scene config, or None when it is absent or ``enabled: false``."""
    sec = enabled_section(cfg, "second_target")
    if sec is None:
        return None
    src = cfg.get("_source", "<memory>")
    body = target_body(cfg, "second_target")
    try:
        wp = np.asarray([w["at"] for w in sec["path"]], dtype=float)
        dwell = np.asarray([float(w.get("dwell_s", 0.0)) for w in sec["path"]])
        car, jit = sec.get("carrier", {}), sec.get("jitter", {})
        d = HandHeldDef(
            body=body, rom_file=str(sec["rom_file"]), waypoints=wp, dwell_s=dwell, speed=float(sec["speed"]),
            normal_to_vega=float(sec.get("normal_to_vega", 0.7)), carrier_radius=float(car.get("radius", 0.2)),
            carrier_height=float(car.get("height", 1.75)), carrier_offset=float(car.get("offset_m", 0.3)),
            sway_mm=float(jit.get("sway_mm", 0.0)), sway_hz=tuple(jit.get("sway_hz", (0.3, 1.5))),
            tremor_mm=float(jit.get("tremor_mm", 0.0)), tremor_hz=tuple(jit.get("tremor_hz", (8.0, 12.0))),
            rotation_deg=float(jit.get("rotation_deg", 0.0)))
    except (KeyError, TypeError, ValueError, ZeroDivisionError) as e:
        raise SceneError(f"scene file {src}: field 'second_target': {type(e).__name__}: {e}") from None
    if wp.ndim != 2 or wp.shape[1] != 3 or len(wp) < 2 or not d.speed > 0:
        raise SceneError(f"scene file {src}: 'second_target.path' needs >= 2 waypoints 'at: [x, y, z]', speed > 0")
    return d


@dataclass(frozen=True)
class BandNoise:
    """Smooth zero-mean jitter (F, 3): ``n`` sinusoids per axis with seeded frequencies in a band and phases, scaled
    to ``rms`` per axis. Drawn once, so every call at the same times gives the same values."""

    freq: np.ndarray     # (n, 3) [Hz]
    phase: np.ndarray    # (n, 3) [rad]
    rms: float

    @classmethod
    def draw(cls, rng: np.random.Generator, rms: float, band: tuple[float, float], n: int = 4) -> BandNoise:
        return cls(rng.uniform(band[0], band[1], (n, 3)), rng.uniform(0.0, 2 * np.pi, (n, 3)), float(rms))

    def __call__(self, t: np.ndarray) -> np.ndarray:
        s = np.sin(2 * np.pi * self.freq[None] * np.asarray(t, float)[:, None, None] + self.phase[None]).sum(axis=1)
        return s * (self.rms / np.sqrt(len(self.freq) / 2.0))


class HandHeldPath:
    """The instrument's true pose and its carrier over time (one seeded instance; a
    :class:`~.target_model.ExtraTarget`)."""

    streams = STREAMS

    def __init__(self, d: HandHeldDef, T_omc_ots: np.ndarray, seed: int) -> None:
        self.d = d
        self.body, self.rom_file = d.body, d.rom_file
        self.carrier_capsule = Carrier(self.carrier, d.carrier_radius)
        self.vega = np.asarray(T_omc_ots, float)[:3, 3]
        legs = np.linalg.norm(np.diff(d.waypoints, axis=0), axis=1)
        # leg k runs from waypoint k (after its dwell) to k + 1; a minimum-jerk leg of mean speed v lasts len / v
        t, knots = 0.0, []
        for k, length in enumerate(legs):
            t += d.dwell_s[k]
            knots.append((t, t + length / d.speed))
            t += length / d.speed
        self.knots = np.asarray(knots)
        self.duration = t + d.dwell_s[-1]
        rng = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(STREAMS[0],)))
        self.sway = BandNoise.draw(rng, d.sway_mm * 1e-3, d.sway_hz)
        self.tremor = BandNoise.draw(rng, d.tremor_mm * 1e-3, d.tremor_hz)
        self.wobble = BandNoise.draw(rng, np.radians(d.rotation_deg), d.sway_hz)

    def position_nominal(self, t_s: np.ndarray) -> np.ndarray:
        """(F, 3) the path without jitter: waypoints joined by minimum-jerk legs."""
        t = np.asarray(t_s, float)
        wp = self.d.waypoints
        out = np.repeat(wp[:1], len(t), axis=0)
        for k, (a, b) in enumerate(self.knots):
            u = np.clip((t - a) / (b - a), 0.0, 1.0)
            s = u**3 * (10 - 15 * u + 6 * u**2)
            on = t >= a
            out[on] = wp[k] + (wp[k + 1] - wp[k]) * s[on, None]
        return out

    def poses(self, t_s: np.ndarray) -> np.ndarray:
        """(F, 4, 4) true instrument poses in omc at task times ``t_s`` [s]."""
        t = np.asarray(t_s, float)
        d = self.d
        p = self.position_nominal(t) + self.sway(t) + self.tremor(t)
        # plate normal (body +x): up, tilted towards the Vega; long axis (body +z) horizontal, across that
        to_vega = self.vega[None, :2] - p[:, :2]
        to_vega /= np.linalg.norm(to_vega, axis=1, keepdims=True)
        n = np.column_stack([d.normal_to_vega * to_vega, np.ones(len(t))])
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        z = np.column_stack([-to_vega[:, 1], to_vega[:, 0], np.zeros(len(t))])
        y = np.cross(z, n)
        R = np.stack([n, y, z], axis=2)
        wobble = Rotation.from_rotvec(self.wobble(t)).as_matrix()
        T = np.tile(np.eye(4), (len(t), 1, 1))
        T[:, :3, :3] = wobble @ R
        T[:, :3, 3] = p
        return T

    def carrier(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The person's capsule axis (F, 3) x 2 at times ``t_s``: behind the hand, away from the table centre."""
        p = self.position_nominal(t_s)[:, :2]
        away = p / np.maximum(np.linalg.norm(p, axis=1, keepdims=True), 1e-6)
        xy = p + self.d.carrier_offset * away
        r, h = self.d.carrier_radius, self.d.carrier_height
        return (np.column_stack([xy, np.full(len(xy), r)]), np.column_stack([xy, np.full(len(xy), h - r)]))


def add_hand_held(run: SimRun, scene: Scene, noise: bool = True, staff: bool = True) -> SimRun:
    """Measure the scene's second target over ``run``'s frames and add it to ``run`` (in place; also returned).

    Adds ``run.omc.bodies[name]``, ``run.ots.tools[name]``, ``run.extra_truth[name]`` (truth at the OMC frames) and
    its entry in ``run.info['extra_targets']``. A scene without a ``second_target`` section leaves the run unchanged.
    """
    path = hand_held(scene)
    if path is None:
        return run
    measure_target(run, scene, path, [path.carrier_capsule], noise=noise, staff=staff)
    run.info.setdefault("extra_targets", {})[path.d.name] = {
        "kind": "hand_held", "omc_id": path.d.body.id, "rom_file": path.d.rom_file, "path_s": round(path.duration, 3)}
    return run


def hand_held(scene: Scene) -> HandHeldPath | None:
    """The scene's seeded instrument path (None without a ``second_target`` section or with ``enabled: false``)."""
    d = load_hand_held(scene.config)
    return None if d is None else HandHeldPath(d, scene.T_omc_ots, scene.seed)
