"""Measuring one of the twin's extra targets (a target without a robot: :mod:`.walker`, :mod:`.breathing`).

An extra target is anything with a marker body, an NDI tool definition, its own random streams and a true pose over
time (:class:`ExtraTarget`). :func:`measure_target` measures it over a run's OMC and Vega frames with the same models
as the arm-held tool (:mod:`.omc_model`, :mod:`.ots_model`; the arm's links, the room's staff, the static boxes and
the Vega bump) and adds it to the run. One function for every kind, so a new kind of motion is a pose function, not
a copy of the measurement loop.

Why its own streams: a target draws its motion and both devices' image noise from children of the run seed's
``SeedSequence`` that no other body uses (:attr:`ExtraTarget.streams`), and the carriers it adds as occluders hide
only the extra targets, never the tool, the base marker or the rig. So adding, removing or changing one extra
target never changes a sample of those, nor of the extra targets measured before it (``test_sim_walker.py``,
``test_sim_breathing.py``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np

from fullperc_common.transforms import inv_T
from fullperc_fusion.margin.view_margin import label_points

from .omc_model import NoiseModel, Occluders, fit_body, observe_markers
from .run import CHUNK, BodySeries, SimRun, ToolSeries, Truth, _arm_state, _occluders
from .scene import BodyDef, Scene, SceneError

TAKEN = ("tool", "base", "ots_rig")   # the scene's own bodies: no extra target may take their names


def enabled_section(cfg: dict, section: str) -> dict | None:
    """An extra target's section of a scene config, or None when it is absent or ``enabled: false``."""
    sec = cfg.get(section)
    return sec if sec and sec.get("enabled", True) else None


def target_body(cfg: dict, section: str) -> BodyDef:
    """The OMC rigid body of an extra target's ``section``: markers [mm] in metres, the plate normal normalised, the
    NDI ROM's part number. SceneError naming the file and the field for a missing or malformed field, fewer than 3
    markers, or a name of the scene's own bodies."""
    sec, src = cfg[section], cfg.get("_source", "<memory>")
    try:
        mk = np.asarray(sec["markers_mm"], dtype=float) / 1000.0
        n = np.asarray(sec.get("normal", [1, 0, 0]), dtype=float)
        body = BodyDef(str(sec["name"]), int(sec["id"]), mk, n / np.linalg.norm(n), str(sec.get("rom", "")))
    except (KeyError, TypeError, ValueError, ZeroDivisionError) as e:
        raise SceneError(f"scene file {src}: field '{section}': {type(e).__name__}: {e}") from None
    if mk.ndim != 2 or mk.shape[1] != 3 or len(mk) < 3:
        raise SceneError(f"scene file {src}: '{section}.markers_mm' needs >= 3 [x y z] rows")
    if body.name in TAKEN:
        raise SceneError(f"scene file {src}: '{section}.name' {body.name!r} is taken by another body")
    return body


@dataclass(frozen=True)
class Carrier:
    """A person (a vertical capsule) who moves with an extra target and occludes the extra targets."""

    axis: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]   # t_s [s] -> axis end points (F, 3), (F, 3) in omc
    radius: float                                                 # [m]


class ExtraTarget(Protocol):
    """What :func:`measure_target` needs of one extra target (one seeded instance)."""

    body: BodyDef                  # OMC rigid body: name, id, marker geometry [m], plate normal
    rom_file: str                  # NDI tool definition in fullperc_drivers/config/emulator_roms
    streams: tuple[int, int, int]  # SeedSequence children of the run seed: motion, OMC noise, Vega noise

    def poses(self, t_s: np.ndarray) -> np.ndarray:
        """(F, 4, 4) true poses in omc at task times ``t_s`` [s]."""
        ...


def _occ(scene: Scene, run: SimRun, carriers: list[Carrier], t_ns: np.ndarray, staff: bool) -> Occluders:
    """The run's occluders at ``t_ns`` (arm links, staff, boxes) plus ``carriers``."""
    _, _, origins, _ = _arm_state(scene, run.arc, t_ns)
    occ = _occluders(scene, origins, t_ns, staff)
    if not carriers:
        return occ
    axes = [c.axis(t_ns / 1e9) for c in carriers]
    return Occluders(np.concatenate([occ.cap_a, *(a[:, None] for a, _ in axes)], axis=1),
                     np.concatenate([occ.cap_b, *(b[:, None] for _, b in axes)], axis=1),
                     np.concatenate([occ.cap_r, [c.radius for c in carriers]]), occ.boxes)


def target_truth(scene: Scene, T: np.ndarray, t_ns: np.ndarray) -> Truth:
    """A target's truth at ``t_ns`` from its true poses ``T`` in omc: in omc and ``base``, with region labels."""
    labels, res = label_points(scene.layout, T[:, :3, 3])
    return Truth(t_ns=t_ns, T_omc_tool=T, T_base_tool=inv_T(scene.T_omc_base) @ T, region=labels.astype(np.uint8),
                 margin_deg=res.margin_deg)


def measure_target(run: SimRun, scene: Scene, target: ExtraTarget, carriers: list[Carrier], noise: bool = True,
                   staff: bool = True) -> SimRun:
    """Measure ``target`` over ``run``'s OMC and Vega frames, ``carriers`` occluding it too; adds it to ``run``.

    Adds ``run.omc.bodies[name]``, ``run.ots.tools[name]`` and ``run.extra_truth[name]`` (truth at the OMC frames)
    in place and returns ``run``. The noise is drawn chunk by chunk (:data:`.run.CHUNK`) from the target's own
    streams, the OMC's frames first.
    """
    d = target.body
    cfg = scene.config
    rng_omc, rng_ots = (np.random.default_rng(np.random.SeedSequence(scene.seed, spawn_key=(k,)))
                        for k in target.streams[1:])
    nm = scene.omc_noise if noise else NoiseModel(0.0, 1.0, 0.0)
    ots = scene.ots if noise else replace(scene.ots, noise=NoiseModel(0.0, 1.0, 0.0))
    M = len(d.markers)
    omc_fits, ots_fits, parts = [], [], []
    for which, t_all in (("omc", run.omc.t_ns), ("ots", run.ots.t_ns)):
        for a in range(0, len(t_all), CHUNK):
            tc = t_all[a:a + CHUNK]
            T = target.poses(tc / 1e9)
            X = np.einsum("fij,mj->fmi", T[:, :3, :3], d.markers) + T[:, None, :3, 3]
            N = T[:, :3, :3] @ d.normal
            occ = _occ(scene, run, carriers, tc, staff)
            if which == "omc":
                z = rng_omc.standard_normal((len(tc), M, scene.omc_cams.K, 2)) if noise else \
                    np.zeros((len(tc), M, scene.omc_cams.K, 2))
                obs = observe_markers(scene.omc_cams, X, np.ones((len(tc), M), bool), occ, nm, z,
                                      normals=np.broadcast_to(N[:, None], X.shape),
                                      max_view_angle_deg=float(cfg["omc"]["max_view_angle_deg"]),
                                      min_cams=int(cfg["omc"]["min_cameras_per_marker"]))
                omc_fits.append(fit_body(d.markers, obs, int(cfg["omc"]["min_markers_per_body"])))
                continue
            z = rng_ots.standard_normal((len(tc), M, 2, 2)) if noise else np.zeros((len(tc), M, 2, 2))
            after, T_bumped = scene.bumped_at(tc)
            for sel, T_ots in ((~after, scene.T_omc_ots), (after, T_bumped)):
                if not sel.any():
                    continue
                o = Occluders(occ.cap_a[sel], occ.cap_b[sel], occ.cap_r, occ.boxes)
                fit, part = ots.measure(T_ots, d.markers, X[sel], N[sel], o, z[sel])
                ots_fits.append(fit)
                parts.append(part)

    def cat(fits, name):
        return np.concatenate([getattr(f, name) for f in fits])

    run.omc.bodies[d.name] = BodySeries(cat(omc_fits, "tracked"), cat(omc_fits, "position"),
                                        cat(omc_fits, "quat_xyzw"), cat(omc_fits, "mean_error"),
                                        cat(omc_fits, "markers_used"), cat(omc_fits, "cameras_seeing"),
                                        cat(omc_fits, "rays"))
    run.ots.tools[d.name] = ToolSeries(cat(ots_fits, "tracked"), cat(ots_fits, "position"), cat(ots_fits, "quat_xyzw"),
                                       cat(ots_fits, "rms_error"), cat(ots_fits, "markers_used"), np.concatenate(parts))
    run.extra_truth[d.name] = target_truth(scene, target.poses(run.omc.t_ns / 1e9), run.omc.t_ns)
    return run
