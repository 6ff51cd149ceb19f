"""The operating-room scene: cameras, bodies with marker geometry, obstacles, staff, the arm, true transforms.

Two files define it:
  * the camera layout shared with the margin model (``fullperc_fusion/config/or_layout.yaml``, loaded with
    :func:`fullperc_fusion.margin.layout.load_layout`): OMC camera poses, FOV, range, resolution, the Vega pose and
    its measurement volume — so the region labels and the simulated measurements come from one geometry;
  * this package's ``config/scene.yaml``: everything only the simulator needs (measurement-model
    parameters, miscalibration, marker geometries, obstacles, staff, Diana base pose, tool mount, task
    search settings). Each number there carries its physical justification as a comment.

:func:`build_scene` turns them into a :class:`Scene` for one seed. The seed drives, through independent
``numpy`` streams spawned from one ``SeedSequence``: the OMC extrinsic miscalibration, the staff walks,
the OMC image noise and the OTS image noise (children 0-3; the extra targets, :mod:`.targets`, use 4-6 and 7-9, so
they never change a draw of these). Same seed -> bit-identical scene and measurements.
"""

from __future__ import annotations

import copy
import functools
import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from fullperc_common.share import share_path
from fullperc_common.transforms import inv_T, make_T
from fullperc_drivers.diana_kinematics import DianaKinematics
from fullperc_fusion.margin.layout import Layout, default_layout_path, load_layout

from .occluders import PlacedBox, StaffWalker
from .omc_lens import LensResidual
from .omc_model import CameraSet, NoiseModel
from .ots_model import OtsModel

PROFILES = ("paper", "spec")  # twin profiles (config/profile_<name>.yaml); "base" = scene.yaml alone
DEFAULT_PROFILE = "paper"  # what the command-line tools use when no --profile is given
OMC_BODIES = ("base", "ots_rig", "tool")  # bodies the OMC tracks (docs/nodes.md "Frames, stamps and units")
OTS_TOOLS = ("tool", "base")  # NDI tools the Vega tracks (docs/nodes.md "Frames, stamps and units")


class SceneError(ValueError):
    """scene.yaml is wrong; the message names the field."""


def default_scene_path() -> Path:
    """The installed ``share/fullperc_eval/config/scene.yaml``, else the source copy."""
    return share_path("fullperc_eval", "config", "scene.yaml")


def profile_path(profile: str) -> Path:
    """``config/profile_<profile>.yaml`` (installed, else the source copy)."""
    if profile not in PROFILES:
        raise SceneError(f"unknown twin profile {profile!r} (one of {', '.join(PROFILES)}, or 'base')")
    return share_path("fullperc_eval", "config", f"profile_{profile}.yaml")


def _yaml_text(text: str) -> Any:
    """``yaml.safe_load(text)``, a fresh copy each call (the caller may change it) of what the text parses to."""
    return copy.deepcopy(_parsed(text))


@functools.lru_cache(maxsize=16)
def _parsed(text: str) -> Any:
    """Parsed once per text: every run builds its scene from the same scene and profile files again (each task and
    seed, the planner's checks), and the pure-Python YAML parser was ~0.1 s of every run."""
    return yaml.safe_load(text)


def load_profile(profile: str) -> dict:
    """The profile file: ``overrides`` (merged into scene.yaml), ``plans_file``, ``targets``, ``rationale``."""
    p = profile_path(profile)
    try:
        data = _yaml_text(p.read_text())
    except (OSError, yaml.YAMLError) as e:
        raise SceneError(f"profile file {p}: {e}") from e
    if not isinstance(data, dict) or not isinstance(data.get("overrides"), dict):
        raise SceneError(f"profile file {p}: expected a mapping with 'overrides: {{...}}'")
    data["_source"] = str(p)
    return data


def merge_overrides(base: dict, over: dict) -> dict:
    """Deep merge: mappings merge key by key, every other value (lists included) replaces the base's."""
    out = dict(base)
    for k, v in over.items():
        out[k] = merge_overrides(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def load_scene_config(path: str | os.PathLike | None = None, profile: str | None = None) -> dict:
    """scene.yaml (``path`` or the installed one) with the twin ``profile``'s overrides merged in.

    ``profile`` None or "base": scene.yaml alone (the scene of the bags before the profiles). The result carries
    ``_source`` (the scene file) and ``_profile`` (the profile name, "base" when none).
    """
    p = Path(path) if path is not None else default_scene_path()
    try:
        data = _yaml_text(p.read_text())
    except (OSError, yaml.YAMLError) as e:
        raise SceneError(f"scene file {p}: {e}") from e
    if not isinstance(data, dict):
        raise SceneError(f"scene file {p}: expected a mapping at the top level")
    if profile not in (None, "base"):
        prof = load_profile(profile)
        data = merge_overrides(data, prof["overrides"])
        data["_plans_file"] = prof.get("plans_file")
    data["_source"] = str(p)
    data["_profile"] = profile or "base"
    return data


def _get(cfg: dict, dotted: str) -> Any:
    cur: Any = cfg
    for k in dotted.split("."):
        if not isinstance(cur, dict) or k not in cur:
            raise SceneError(f"scene file {cfg.get('_source', '<memory>')}: missing field '{dotted}'")
        cur = cur[k]
    return cur


def _pose(cfg: dict, dotted: str) -> np.ndarray:
    m = _get(cfg, dotted)
    try:
        p = np.asarray(m["position"], dtype=float)
        q = np.asarray(m.get("orientation", [0, 0, 0, 1]), dtype=float)
    except (KeyError, TypeError, ValueError) as e:
        raise SceneError(f"scene field '{dotted}': needs position [x y z] and orientation [qx qy qz qw]") from e
    if p.shape != (3,) or q.shape != (4,) or not np.all(np.isfinite(p)) or abs(np.linalg.norm(q) - 1) > 1e-3:
        raise SceneError(f"scene field '{dotted}': bad position {p.tolist()} or non-unit quaternion {q.tolist()}")
    return make_T(p, q / np.linalg.norm(q))


@dataclass(frozen=True)
class VegaBump:
    """The Vega stand bumped during a run (issue 15 item 2: a real OR event the link monitor must catch).

    From ``at_s`` seconds of task time on, the Vega head -- and the OMC rig body ``ots_rig`` on it -- is moved by
    ``dx_m`` along ``omc`` x (the stand pushed along the floor) and tilted by ``tilt_deg`` about ``omc`` y through
    the head's origin (the pole leaning over). The step is instantaneous: a bump takes a few tenths of a second,
    far below the monitor's 1 s window, and what the monitor must catch is the pose after it.
    """

    at_s: float
    dx_m: float
    tilt_deg: float = 0.0

    def __post_init__(self) -> None:
        for name in ("at_s", "dx_m", "tilt_deg"):
            v = getattr(self, name)
            if not np.isfinite(v):
                raise ValueError(f"vega bump: {name} must be finite, got {v!r}")
        if self.at_s < 0:
            raise ValueError(f"vega bump: the time must be >= 0 s, got {self.at_s}")

    @classmethod
    def parse(cls, text: str) -> VegaBump:
        """``AT:DX[:TILT]`` (seconds, metres, degrees), the ``sim --vega-bump`` syntax."""
        parts = text.split(":")
        try:
            if len(parts) not in (2, 3):
                raise ValueError
            return cls(*(float(x) for x in parts))
        except (TypeError, ValueError) as e:
            raise ValueError(f"vega bump {text!r}: expected AT:DX[:TILT] (s, m, deg){f' ({e})' if str(e) else ''}"
                             ) from None

    def apply(self, T_omc_ots: np.ndarray) -> np.ndarray:
        """The Vega's pose in ``omc`` after the bump."""
        T = np.array(T_omc_ots, dtype=float)
        T[:3, :3] = Rotation.from_euler("y", self.tilt_deg, degrees=True).as_matrix() @ T[:3, :3]
        T[0, 3] += self.dx_m
        return T

    def as_dict(self) -> dict[str, float]:
        return {"at_s": self.at_s, "dx_m": self.dx_m, "tilt_deg": self.tilt_deg}


@dataclass(frozen=True)
class BodyDef:
    """A rigid body: id, marker centres in its own frame [m] (M, 3), plate normal in its frame (or None)."""

    name: str
    id: int
    markers: np.ndarray
    normal: np.ndarray | None
    rom: str = ""


@dataclass
class Scene:
    """One seeded instance of the OR. All transforms ``T_a_b`` map b-coordinates into a (p_a = T_a_b p_b)."""

    seed: int
    config: dict
    layout: Layout
    omc_cams: CameraSet  # true + believed (miscalibrated) extrinsics
    omc_noise: NoiseModel
    ots: OtsModel
    static_boxes: list[PlacedBox]  # layout occluders + scene.yaml obstacles (the robot cart is added by ``boxes``)
    staff: list[StaffWalker]
    bodies: dict[str, BodyDef]
    dk: DianaKinematics
    T_omc_base: np.ndarray
    T_omc_ots: np.ndarray
    T_ots_rig_ots: np.ndarray
    T_omc_diana_base: np.ndarray
    T_flange_tool: np.ndarray
    noise_seeds: tuple = field(repr=False, default=())  # SeedSequences of the OMC and OTS image noise
    vega_bump: VegaBump | None = None  # the Vega (and its rig) moved during the run; None: it stays put

    def noise_rngs(self) -> tuple[np.random.Generator, np.random.Generator]:
        """Fresh generators for the OMC and OTS image noise (a new run of the same scene repeats exactly)."""
        return np.random.default_rng(self.noise_seeds[0]), np.random.default_rng(self.noise_seeds[1])

    @property
    def boxes(self) -> list[PlacedBox]:
        """Every static box, including the Diana's cart under its current base pose."""
        cart = self.config.get("diana", {}).get("cart")
        if not cart:
            return self.static_boxes
        size = np.asarray(cart["size"], dtype=float)
        R = self.T_omc_diana_base[:3, :3]
        c = self.T_omc_diana_base[:3, 3] + R @ np.array([0.0, 0.0, -size[2] / 2 - float(cart.get("gap", 0.0))])
        return [*self.static_boxes, PlacedBox.of("robot_cart", c, R, size / 2)]

    def with_diana_base(self, T_omc_diana_base: np.ndarray) -> Scene:
        """The same scene (same seed streams) with the arm's cart moved to ``T_omc_diana_base``."""
        return replace(self, T_omc_diana_base=np.asarray(T_omc_diana_base, dtype=float).copy())

    def with_vega_bump(self, bump: VegaBump | None) -> Scene:
        """The same scene with the Vega bumped during the run (:class:`VegaBump`); None: not bumped."""
        return replace(self, vega_bump=bump)

    @property
    def T_omc_ots_rig(self) -> np.ndarray:
        return self.T_omc_ots @ inv_T(self.T_ots_rig_ots)

    def bumped_at(self, t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(mask (F,): task times ``t_ns`` [ns] at or after the Vega bump, the Vega's true pose after it)."""
        t = np.asarray(t_ns)
        if self.vega_bump is None:
            return np.zeros(t.shape, bool), self.T_omc_ots
        return t >= round(self.vega_bump.at_s * 1e9), self.vega_bump.apply(self.T_omc_ots)

    def static_transforms(self) -> dict[str, np.ndarray]:
        """The true static transforms an evaluator needs to turn joint states into ground truth."""
        return {"T_omc_base": self.T_omc_base.copy(), "T_omc_ots": self.T_omc_ots.copy(),
                "T_omc_ots_rig": self.T_omc_ots_rig.copy(), "T_ots_rig_ots": self.T_ots_rig_ots.copy(),
                "T_omc_diana_base": self.T_omc_diana_base.copy(), "T_flange_tool": self.T_flange_tool.copy()}

    def T_omc_tool(self, T_diana_base_flange: np.ndarray) -> np.ndarray:
        """True tool pose(s) in omc from flange pose(s) (..., 4, 4)."""
        return self.T_omc_diana_base @ T_diana_base_flange @ self.T_flange_tool


def _bodies(cfg: dict) -> dict[str, BodyDef]:
    out = {}
    for name in OMC_BODIES:
        b = _get(cfg, f"bodies.{name}")
        mk = np.asarray(b.get("markers_mm"), dtype=float) / 1000.0
        if mk.ndim != 2 or mk.shape[1] != 3 or mk.shape[0] < 3:
            raise SceneError(f"scene field 'bodies.{name}.markers_mm': need >= 3 [x y z] rows")
        n = b.get("normal")
        normal = None if n is None else np.asarray(n, dtype=float) / np.linalg.norm(n)
        out[name] = BodyDef(name, int(b.get("id", len(out) + 1)), mk, normal, str(b.get("rom", "")))
    return out


def _boxes(cfg: dict, layout: Layout) -> list[PlacedBox]:
    """The layout's static occluders (so labels and measurements share them) plus scene.yaml's extra obstacles."""
    out = [PlacedBox.from_layout(b) for b in getattr(layout, "occluders", ())]
    for i, b in enumerate(cfg.get("obstacles") or []):
        try:
            c = np.asarray(b["center"], dtype=float)
            size = np.asarray(b["size"], dtype=float)
            yaw = float(b.get("yaw_deg", 0.0))
        except (KeyError, TypeError, ValueError) as e:
            raise SceneError(f"scene field 'obstacles[{i}]': needs center, size (and optional yaw_deg)") from e
        if c.shape != (3,) or size.shape != (3,) or np.any(size <= 0):
            raise SceneError(f"scene field 'obstacles[{i}]': bad center/size")
        out.append(PlacedBox.of(str(b.get("name", f"box{i}")), c,
                                Rotation.from_euler("z", yaw, degrees=True).as_matrix(), size / 2))
    return out


def build_scene(seed: int = 0, config: dict | str | os.PathLike | None = None, layout: Layout | None = None,
                duration_s: float = 120.0, miscalibration: bool = True, profile: str | None = None) -> Scene:
    """Instantiate the scene for ``seed``. ``duration_s`` bounds the staff paths (they hold still after it).

    ``miscalibration=False`` gives the OMC its true extrinsics (for tests of the ideal system). ``profile``: a twin
    profile merged into the scene file (ignored when ``config`` is already a dict).
    """
    cfg = config if isinstance(config, dict) else load_scene_config(config, profile)
    lay = layout if layout is not None else load_layout(default_layout_path())
    if lay.ots is None:
        raise SceneError(f"layout {lay.source} has no 'ots' section; the simulator needs the Vega pose")
    ss = np.random.SeedSequence(int(seed))
    s_cal, s_staff, s_omc, s_ots = ss.spawn(4)
    r_cal, r_staff = np.random.default_rng(s_cal), np.random.default_rng(s_staff)

    cams = CameraSet.from_specs([c.name for c in lay.cameras], lay.cam_pos, lay.cam_R,
                                [c.fov_h_deg for c in lay.cameras], [c.fov_v_deg for c in lay.cameras],
                                lay.range_m, [c.resolution for c in lay.cameras])
    mc = _get(cfg, "omc.miscalibration")
    if miscalibration:
        cams = cams.miscalibrated(r_cal, float(mc["translation_sigma_m"]), float(mc["rotation_sigma_deg"]))
        try:  # the lens residual common to all cameras (sim.omc_lens); no random draw
            cams = replace(cams, lens=LensResidual.from_config(cfg["omc"].get("lens_residual")))
        except ValueError as e:
            raise SceneError(str(e)) from e
    nz = _get(cfg, "omc.noise")
    omc_noise = NoiseModel(float(nz["sigma_px_ref"]), float(nz["d_ref_m"]), float(nz["exponent"]))

    oc = _get(cfg, "ots")
    onz = oc["noise"]
    ots = OtsModel(frustum=lay.ots.frustum, baseline_m=float(oc["baseline_m"]),
                   noise=NoiseModel(float(onz["sigma_px_ref"]), float(onz["d_ref_m"]), float(onz["exponent"])),
                   fov_deg=float(oc["fov_deg"]), resolution=tuple(oc["resolution"]),
                   max_view_angle_deg=float(oc["max_view_angle_deg"]))

    staff = []
    for i, s in enumerate(cfg.get("staff") or []):
        try:
            staff.append(StaffWalker(str(s.get("name", f"staff{i}")), tuple(float(v) for v in s["zone"]),
                                     float(s["radius"]), float(s["height"]), float(s["speed"]),
                                     float(s.get("pause", 2.0)), float(duration_s), r_staff,
                                     float(s.get("floor_z", 0.0))))
        except (KeyError, TypeError, ValueError) as e:
            raise SceneError(f"scene field 'staff[{i}]': needs zone, radius, height, speed: {e}") from e

    T_omc_ots = lay.ots.T_omc_ots.copy()
    T_ots_ots_rig = _pose(cfg, "bodies.ots_rig.pose_in_ots")
    T_omc_base = _pose(cfg, "bodies.base.pose_in_omc")
    return Scene(seed=int(seed), config=cfg, layout=lay, omc_cams=cams, omc_noise=omc_noise, ots=ots,
                 static_boxes=_boxes(cfg, lay), staff=staff, bodies=_bodies(cfg), dk=DianaKinematics(),
                 T_omc_base=T_omc_base, T_omc_ots=T_omc_ots, T_ots_rig_ots=inv_T(T_ots_ots_rig),
                 T_omc_diana_base=_pose(cfg, "diana.base_in_omc"), T_flange_tool=_pose(cfg, "tool_mount"),
                 noise_seeds=(s_omc, s_ots))
