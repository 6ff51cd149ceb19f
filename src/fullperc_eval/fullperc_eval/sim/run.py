"""Offline simulation: a whole task's measurements and ground truth as numpy arrays (no ROS, no sockets).

:func:`simulate` measures one planned arc in a scene; :func:`fullperc_eval.sim.runner.run_task` (also
``fullperc_eval.sim.run_task``) plans a task and simulates it. This is the API the dataset/evaluation code uses::

    from fullperc_eval.sim import run_task
    run = run_task("P-B-G-P", seed=0)          # ~30 s of motion, a few seconds to compute
    run.omc.t_ns, run.omc.frame_number          # (F,) OMC frame capture times [ns from task start], numbers
    b = run.omc.bodies["tool"]                  # also "base", "ots_rig"
    b.tracked, b.position, b.quat_xyzw          # (F,), (F, 3) [m, omc], (F, 4) x y z w; NaN when not tracked
    b.mean_error, b.markers_used, b.cameras_seeing, b.rays
    v = run.ots.tools["tool"]                   # also "base"; run.ots.t_ns at the Vega rate
    v.visible, v.position, v.quat_xyzw, v.rms   # pose in the ``ots`` frame; NaN when MISSING
    run.diana.t_ns, run.diana.q, run.diana.dq   # joint states at the arm's push rate
    run.truth.T_omc_tool, run.truth.T_base_tool # (F, 4, 4) truth at the OMC frame times
    run.truth.region                            # (F,) BVV=1 / GVV=2 / PVV=3 of the true target position
    run.truth_ots                               # the same at the Vega frame times
    run.extra_truth["instrument"]               # the extra targets' truth at the OMC frame times (also
                                                # "reference"; omc.bodies / ots.tools hold their measurements;
                                                # sim.targets)
    run.static                                  # T_omc_base, T_omc_ots, T_omc_ots_rig, T_ots_rig_ots,
                                                # T_omc_diana_base, T_flange_tool (true values)
    run.flat()                                  # every array under a "group/name" key; run.save_npz(path)

Ground truth from joint states: T_omc_tool = T_omc_diana_base · FK(q) · T_flange_tool with FK from
:class:`fullperc_drivers.diana_kinematics.DianaKinematics`, and T_base_tool = inv(T_omc_base) · T_omc_tool.

Times are integer nanoseconds from the task start (the live server adds the host clock). The OMC
reports each frame ``omc.latency_s`` after capture, the Vega ``ots.latency_s`` after capture. The Vega's stamps
can be made late by ``ots.stamp_offset_s`` (scene key, default 0: not in scene.yaml, so the profiles' twin_hash
is unchanged) to test time alignment; ``ots.t_ns`` stays the true capture time.
Same task + seed + configuration -> bit-identical arrays (tested).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np

from fullperc_common.transforms import inv_T, make_T, mean_T
from fullperc_fusion.margin.view_margin import BVV, label_points

from .omc_model import BodyFit, NoiseModel, Occluders, fit_body, observe_markers
from .scene import OMC_BODIES, OTS_TOOLS, Scene
from .trajectories import JointArc, arm_geometry, link_capsules

CHUNK = 240  # frames per vectorised block (fixed: the noise draw order depends on it)


@dataclass
class BodySeries:
    tracked: np.ndarray
    position: np.ndarray
    quat_xyzw: np.ndarray
    mean_error: np.ndarray
    markers_used: np.ndarray
    cameras_seeing: np.ndarray
    rays: np.ndarray


@dataclass
class OmcSeries:
    t_ns: np.ndarray
    frame_number: np.ndarray
    latency_s: float
    bodies: dict[str, BodySeries]


@dataclass
class ToolSeries:
    visible: np.ndarray
    position: np.ndarray  # ots frame [m]
    quat_xyzw: np.ndarray
    rms: np.ndarray  # RMS marker fit error [m]
    markers_used: np.ndarray
    partially_out: np.ndarray


@dataclass
class OtsSeries:
    t_ns: np.ndarray
    frame_number: np.ndarray
    latency_s: float
    tools: dict[str, ToolSeries]
    # the Vega's stamps are late by this much relative to the truth (scene ``ots.stamp_offset_s``, default 0): a
    # capture-to-stamp delay its driver does not subtract, for testing time alignment (calibration.time_offset).
    # ``t_ns`` stays the true capture time; only the stamps written (dataset.content_from_sim) carry it
    stamp_offset_s: float = 0.0


@dataclass
class DianaSeries:
    t_ns: np.ndarray
    q: np.ndarray
    dq: np.ndarray


@dataclass
class Truth:
    t_ns: np.ndarray
    T_omc_tool: np.ndarray
    T_base_tool: np.ndarray
    region: np.ndarray
    margin_deg: np.ndarray


@dataclass
class SimRun:
    task: str
    seed: int
    arc: JointArc
    omc: OmcSeries
    ots: OtsSeries
    diana: DianaSeries
    truth: Truth
    truth_ots: Truth
    static: dict[str, np.ndarray]
    camera_names: list[str]
    cameras_true: tuple[np.ndarray, np.ndarray]  # C (K,3), R (K,3,3)
    cameras_believed: tuple[np.ndarray, np.ndarray]
    info: dict = field(default_factory=dict)
    extra_truth: dict[str, Truth] = field(default_factory=dict)   # other targets' truth at the OMC frames (targets)

    @property
    def duration_s(self) -> float:
        return self.arc.duration

    def flat(self) -> dict[str, np.ndarray]:
        """Every array under a ``group/name`` key (for npz files and bit-identity checks)."""
        out: dict[str, np.ndarray] = {}

        def add(prefix: str, obj) -> None:
            for f in fields(obj):
                v = getattr(obj, f.name)
                if isinstance(v, np.ndarray):
                    out[f"{prefix}/{f.name}"] = v
                elif isinstance(v, float | int):
                    out[f"{prefix}/{f.name}"] = np.asarray(v)

        add("omc", self.omc)
        for n, b in self.omc.bodies.items():
            add(f"omc/{n}", b)
        add("ots", self.ots)
        for n, b in self.ots.tools.items():
            add(f"ots/{n}", b)
        add("diana", self.diana)
        add("truth", self.truth)
        add("truth_ots", self.truth_ots)
        for n, tr in self.extra_truth.items():
            add(f"truth_{n}", tr)
        for k, v in self.static.items():
            out[f"static/{k}"] = v
        out["cameras/C_true"], out["cameras/R_true"] = self.cameras_true
        out["cameras/C_believed"], out["cameras/R_believed"] = self.cameras_believed
        out["arc/q0"] = np.asarray(self.arc.q0)
        out["arc/params"] = np.array([self.arc.joint, self.arc.start, self.arc.end, self.arc.move,
                                      self.arc.hold_start, self.arc.hold_end])
        return out

    def save_npz(self, path) -> None:
        np.savez_compressed(path, task=np.asarray(self.task), seed=np.asarray(self.seed),
                            camera_names=np.asarray(self.camera_names), **self.flat())


# ------------------------------------------------------------------------------------------------ geometry
def _time_grid(duration_s: float, rate_hz: float, phase_s: float = 0.0) -> np.ndarray:
    period = 1e9 / rate_hz
    n = int(np.floor((duration_s - phase_s) * rate_hz + 1e-9)) + 1
    return np.round(phase_s * 1e9 + np.arange(n) * period).astype(np.int64)


def _arm_state(scene: Scene, arc: JointArc, t_ns: np.ndarray):
    Q, dQ = arc.sample(t_ns / 1e9)
    origins, flange = arm_geometry(scene.dk, Q)
    T_tool = scene.T_omc_diana_base @ flange @ scene.T_flange_tool
    return Q, dQ, origins, T_tool


def _occluders(scene: Scene, origins: np.ndarray, t_ns: np.ndarray, staff: bool) -> Occluders:
    a, b, r = link_capsules(origins, scene.T_omc_diana_base)
    if staff and scene.staff:
        t = t_ns / 1e9
        sa, sb = zip(*(w.capsule(t) for w in scene.staff), strict=True)
        a = np.concatenate([a, np.stack(sa, axis=1)], axis=1)
        b = np.concatenate([b, np.stack(sb, axis=1)], axis=1)
        r = np.concatenate([r, [w.radius for w in scene.staff]])
    return Occluders(a, b, r, scene.boxes)


def _body_pose(scene: Scene, name: str, T_tool: np.ndarray, t_ns: np.ndarray | None = None) -> np.ndarray:
    F = len(T_tool)
    if name == "tool":
        return T_tool
    if name == "base":
        return np.broadcast_to(scene.T_omc_base, (F, 4, 4))
    if name == "ots_rig":
        T = np.broadcast_to(scene.T_omc_ots_rig, (F, 4, 4))
        if scene.vega_bump is not None and t_ns is not None:   # the rig sits on the Vega head: it moves with it
            after, T_ots = scene.bumped_at(t_ns)
            T = np.where(after[:, None, None], T_ots @ inv_T(scene.T_ots_rig_ots), T)
        return T
    raise KeyError(name)


def _markers(scene: Scene, names, T_tool: np.ndarray,
             t_ns: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, list[slice]]:
    """All markers of ``names`` in omc (F, M, 3), their plate normals (F, M, 3; zero = none), slices per body."""
    Xs, Ns, sl = [], [], []
    k = 0
    for n in names:
        body = scene.bodies[n]
        T = _body_pose(scene, n, T_tool, t_ns)
        X = np.einsum("fij,mj->fmi", T[:, :3, :3], body.markers) + T[:, None, :3, 3]
        nrm = np.zeros_like(X) if body.normal is None else np.broadcast_to(
            (T[:, :3, :3] @ body.normal)[:, None, :], X.shape)
        Xs.append(X)
        Ns.append(nrm)
        sl.append(slice(k, k + len(body.markers)))
        k += len(body.markers)
    return np.concatenate(Xs, axis=1), np.concatenate(Ns, axis=1), sl


def _stack_fits(fits: list[BodyFit]) -> BodyFit:
    return BodyFit(*(np.concatenate([getattr(f, fl.name) for f in fits]) for fl in fields(BodyFit)))


# --------------------------------------------------------------------------------------------- simulation
def _simulate_omc(scene: Scene, arc: JointArc, t_ns: np.ndarray, noise: bool, staff: bool,
                  rng: np.random.Generator | None) -> dict[str, BodyFit]:
    cfg = scene.config["omc"]
    nm = scene.omc_noise if noise else NoiseModel(0.0, 1.0, 0.0)
    per_body: dict[str, list[BodyFit]] = {n: [] for n in OMC_BODIES}
    for a in range(0, len(t_ns), CHUNK):
        tc = t_ns[a:a + CHUNK]
        _, _, origins, T_tool = _arm_state(scene, arc, tc)
        X, N, sl = _markers(scene, OMC_BODIES, T_tool, tc)
        occ = _occluders(scene, origins, tc, staff)
        shape = (len(tc), X.shape[1], scene.omc_cams.K, 2)
        z = rng.standard_normal(shape) if (noise and rng is not None) else np.zeros(shape)
        obs = observe_markers(scene.omc_cams, X, np.ones(X.shape[:2], bool), occ, nm, z, normals=N,
                              max_view_angle_deg=float(cfg["max_view_angle_deg"]),
                              min_cams=int(cfg["min_cameras_per_marker"]))
        for n, s in zip(OMC_BODIES, sl, strict=True):
            sub = type(obs)(seen=obs.seen[:, s], X=obs.X[:, s], n_cams=obs.n_cams[:, s])
            per_body[n].append(fit_body(scene.bodies[n].markers, sub, int(cfg["min_markers_per_body"])))
    return {n: _stack_fits(v) for n, v in per_body.items()}


def _simulate_ots(scene: Scene, arc: JointArc, t_ns: np.ndarray, noise: bool, staff: bool,
                  rng: np.random.Generator | None, tools=OTS_TOOLS) -> dict[str, tuple[BodyFit, np.ndarray]]:
    ots = scene.ots
    if not noise:
        ots = type(ots)(**{**{f.name: getattr(ots, f.name) for f in fields(ots)},
                           "noise": NoiseModel(0.0, 1.0, 0.0)})
    out: dict[str, list] = {n: [] for n in tools}
    for a in range(0, len(t_ns), CHUNK):
        tc = t_ns[a:a + CHUNK]
        _, _, origins, T_tool = _arm_state(scene, arc, tc)
        occ = _occluders(scene, origins, tc, staff)
        X, N, sl = _markers(scene, tools, T_tool, tc)
        shape = (len(tc), X.shape[1], 2, 2)
        z = rng.standard_normal(shape) if (noise and rng is not None) else np.zeros(shape)
        # a bump inside the chunk: the frames before and after it are measured from the Vega's two poses, with the
        # chunk's noise draws, so the frames before a bump are those of the run without it
        after, T_bumped = scene.bumped_at(tc)
        parts = [(slice(0, len(tc)), T_bumped if after.all() else scene.T_omc_ots)]
        if after.any() and not after.all():
            k = int(np.argmax(after))
            parts = [(slice(0, k), scene.T_omc_ots), (slice(k, len(tc)), T_bumped)]
        for n, s in zip(tools, sl, strict=True):
            body = scene.bodies[n]
            for f, T_omc_ots in parts:
                occ_f = Occluders(occ.cap_a[f], occ.cap_b[f], occ.cap_r, occ.boxes)
                fit, part = ots.measure(T_omc_ots, body.markers, X[f, s],
                                        None if body.normal is None else N[f, s][:, 0], occ_f, z[f, s])
                out[n].append((fit, part))
    return {n: (_stack_fits([f for f, _ in v]), np.concatenate([p for _, p in v])) for n, v in out.items()}


def _truth(scene: Scene, arc: JointArc, t_ns: np.ndarray) -> Truth:
    _, _, _, T_tool = _arm_state(scene, arc, t_ns)
    labels, res = label_points(scene.layout, T_tool[:, :3, 3])
    return Truth(t_ns=t_ns, T_omc_tool=T_tool, T_base_tool=inv_T(scene.T_omc_base) @ T_tool,
                 region=labels.astype(np.uint8), margin_deg=res.margin_deg)


def simulate(scene: Scene, arc: JointArc, task: str = "", noise: bool = True, staff: bool = True) -> SimRun:
    """Measure the whole ``arc`` in ``scene``: OMC frames, Vega frames, Diana samples and truth."""
    cfg = scene.config
    rng_omc, rng_ots = scene.noise_rngs()
    omc_t = _time_grid(arc.duration, float(cfg["omc"]["rate_hz"]))
    ots_t = _time_grid(arc.duration, float(cfg["ots"]["rate_hz"]), float(cfg["ots"].get("phase_s", 0.0)))
    dia_t = _time_grid(arc.duration, float(cfg["diana"]["rate_hz"]))

    fits = _simulate_omc(scene, arc, omc_t, noise, staff, rng_omc)
    bodies = {n: BodySeries(f.tracked, f.position, f.quat_xyzw, f.mean_error, f.markers_used, f.cameras_seeing,
                            f.rays) for n, f in fits.items()}
    first = int(cfg["omc"].get("first_frame_number", 1))
    omc = OmcSeries(omc_t, (first + np.arange(len(omc_t))).astype(np.uint32), float(cfg["omc"]["latency_s"]), bodies)

    tools = {}
    for n, (f, part) in _simulate_ots(scene, arc, ots_t, noise, staff, rng_ots).items():
        tools[n] = ToolSeries(f.tracked, f.position, f.quat_xyzw, f.rms_error, f.markers_used, part)
    first_v = int(cfg["ots"].get("first_frame_number", 1))
    ots = OtsSeries(ots_t, (first_v + np.arange(len(ots_t))).astype(np.uint32), float(cfg["ots"]["latency_s"]),
                    tools, float(cfg["ots"].get("stamp_offset_s", 0.0)))
    Q, dQ = arc.sample(dia_t / 1e9)
    return SimRun(task=task, seed=scene.seed, arc=arc, omc=omc, ots=ots, diana=DianaSeries(dia_t, Q, dQ),
                  truth=_truth(scene, arc, omc_t), truth_ots=_truth(scene, arc, ots_t),
                  static=scene.static_transforms(), camera_names=list(scene.omc_cams.names),
                  cameras_true=(scene.omc_cams.C.copy(), scene.omc_cams.R.copy()),
                  cameras_believed=(scene.omc_cams.Cb.copy(), scene.omc_cams.Rb.copy()),
                  info={"noise": noise, "staff": staff, "layout": scene.layout.source,
                        "ots_rate_hz": float(cfg["ots"]["rate_hz"]), "omc_rate_hz": float(cfg["omc"]["rate_hz"]),
                        "scene": scene.config.get("_source", ""),
                        "vega_bump": None if scene.vega_bump is None else scene.vega_bump.as_dict()})


def simulate_ideal_visibility(scene: Scene, arc: JointArc, rate_hz: float = 30.0) -> tuple[float, float]:
    """Noise-free, staff-free visibility of the tool along ``arc``: (Vega fraction in BVV, OMC fraction overall)."""
    t = _time_grid(arc.duration, rate_hz)
    fits = _simulate_omc(scene, arc, t, noise=False, staff=False, rng=None)
    ots = _simulate_ots(scene, arc, t, noise=False, staff=False, rng=None, tools=("tool",))
    region = _truth(scene, arc, t).region
    inb = region == BVV
    frac_b = float(ots["tool"][0].tracked[inb].mean()) if inb.any() else 1.0
    return frac_b, float(fits["tool"].tracked.mean())


# ---------------------------------------------------------------------------------------------- evaluation
def omc_errors(run: SimRun, body: str = "tool") -> dict[str, np.ndarray]:
    """Position errors [m] of the raw OMC measurement of ``body`` on its tracked frames.

    ``omc``: |p_meas - p_true| in the omc frame. ``base``: the target in the ``base`` frame as a user of the
    global chain gets it — inv(T̂_omc_base) · T̂_omc_tool with T̂_omc_base the mean OMC measurement of the base
    marker over the run (a static link estimated from averaged observations) — against the truth in ``base``.
    """
    b = run.omc.bodies[body]
    ok = b.tracked
    e_omc = np.linalg.norm(b.position[ok] - run.truth.T_omc_tool[ok, :3, 3], axis=1)
    base = run.omc.bodies["base"]
    Tb = [make_T(p, q) for p, q in zip(base.position[base.tracked], base.quat_xyzw[base.tracked], strict=True)]
    out = {"omc": e_omc, "tracked": ok}
    if Tb:
        T_base_omc = inv_T(mean_T(Tb))
        p_base = b.position[ok] @ T_base_omc[:3, :3].T + T_base_omc[:3, 3]
        out["base"] = np.linalg.norm(p_base - run.truth.T_base_tool[ok, :3, 3], axis=1)
    return out


__all__ = ["SimRun", "simulate", "simulate_ideal_visibility", "omc_errors"]
