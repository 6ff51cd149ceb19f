"""The six evaluation tasks of the paper's Table 1 and the generator that realises them on the Diana.

A task is a region order, e.g. ``"P-B-G-P"``: the target starts in the poor view volume, enters the
OTS volume (best), leaves it into the good view volume, and ends in the poor one. :func:`plan_task`
finds a single-joint arc (the paper's protocol) whose ground-truth target path crosses the regions in
exactly that order, using the margin model of :mod:`fullperc_fusion.margin.view_margin` on the same layout the
simulated cameras use:

1. place the arm's cart (seeded, inside ``diana.base_zone`` of scene.yaml: beside the table, any yaw) and draw a
   start configuration q0 (inside the joint limits, 5 deg clear of them);
2. for each moving joint, sweep it over its range at ``sweep_step_deg``, drop poses where the arm hits the
   table/equipment or dips below the base, and label the target positions (BVV/GVV/PVV);
3. look for a window of consecutive label runs equal to the order, where each inner region is crossed over
   at least ``min_region_path_m`` of path and the first/last regions contribute ``lead_path_m`` (less if the
   run is shorter, but at least ``min_region_path_m``);
4. check the physics on the noise-free scene without staff: in the B part the Vega must measure the tool in
   at least ``min_ots_fraction`` of its frames, and over the whole arc the OMC must track it in at least
   ``min_omc_fraction`` of its frames (a task no tracker can see would test nothing). An arc whose B part the
   Vega sees in >= ``good_ots_fraction`` is taken at once, else the best of the first ``max_candidates``
   valid arcs. (The margin model's BVV already requires the Vega's line of sight to the target origin past the
   static occluders; what it cannot know is the tool's own extent and facing, the two lenses' offsets and the
   arm's links, so near a frustum face the Vega may still miss the tool.)
5. sample the final :class:`~fullperc_eval.sim.trajectories.JointArc` at the OMC frame times and assert that
   the compressed label sequence is exactly the order.

The search is deterministic (its own seed, ``tasks.search_seed`` in scene.yaml, mixed with the task index),
so a task is the same arc for every run seed. If no arc is found within ``max_attempts`` start
configurations, :class:`TaskPlanningError` is raised naming the task and what was tried — never a silent
fallback to a different order.

Shipped plans. A cold search takes seconds to a minute per task, so the plans of the default scene are committed
in ``fullperc_eval/config/task_plans.yaml`` (installed by ``make build``), the first level of :func:`plan_task`'s
cache. Every shipped plan is re-checked before use (:func:`check_arc_order`: the margin model labels its path
with exactly the task's order and no pose collides); a plan that fails the check is reported with a
``StalePlanWarning`` and the task is planned again. Regenerate the file after changing the layout, the scene
geometry or the search::

    python -m fullperc_eval.sim --write-plans            # all six tasks, cold, into the source tree
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from fullperc_common.runs import runs
from fullperc_common.share import share_path
from fullperc_fusion.margin.view_margin import BVV, GVV, PVV, label_points

from .occluders import points_in_boxes
from .run import simulate_ideal_visibility
from .scene import build_scene
from .trajectories import JointArc, arm_geometry, link_capsules

TASKS: tuple[str, ...] = ("G-B-P", "P-G-B", "P-G-B-P", "P-B-G", "B-G-P", "P-B-G-P")
_LETTER = {"B": BVV, "G": GVV, "P": PVV}
_NAME = {BVV: "B", GVV: "G", PVV: "P"}


class TaskPlanningError(RuntimeError):
    """No single-joint arc realises the requested region order in this scene."""


def parse_task(task: str) -> tuple[int, ...]:
    """``"P-B-G"`` -> (PVV, BVV, GVV); rejects unknown letters and repeated neighbours."""
    parts = task.strip().upper().split("-")
    if len(parts) < 2 or any(p not in _LETTER for p in parts):
        raise ValueError(f"task {task!r}: expected letters B/G/P joined by '-', e.g. 'P-B-G-P'")
    if any(a == b for a, b in zip(parts, parts[1:], strict=False)):
        raise ValueError(f"task {task!r}: the same region twice in a row is not a crossing")
    return tuple(_LETTER[p] for p in parts)


def compress(labels: np.ndarray) -> tuple[int, ...]:
    """Run-length compress a label sequence to the order of regions visited: [3,3,1,1,2] -> (3, 1, 2)."""
    return tuple(label for label, _, _ in runs(labels))


def order_name(order: tuple[int, ...]) -> str:
    return "-".join(_NAME[int(o)] for o in order)


@dataclass(frozen=True)
class TaskPlan:
    """A planned task: the arc, and how it was found (for the record)."""

    task: str
    arc: JointArc
    T_omc_diana_base: np.ndarray  # where the generator placed the arm's cart
    attempts: int
    region_path_m: tuple[float, ...]  # path length of the target in each region of the order
    ots_fraction_b: float = float("nan")  # share of the B part where the Vega sees the tool (noise-free, no staff)
    omc_fraction: float = float("nan")  # share of the arc where the OMC tracks the tool (noise-free, no staff)


def _settings(scene) -> dict:
    d = {"search_seed": 7, "max_attempts": 400, "sweep_step_deg": 1.0, "joint_margin_deg": 5.0,
         "min_region_path_m": 0.04, "lead_path_m": 0.10, "max_arc_deg": 160.0, "move_s": 24.0, "hold_s": 2.0,
         "min_clearance_m": 0.05, "min_ots_fraction": 0.0,
         "good_ots_fraction": 0.8, "max_candidates": 4, "min_omc_fraction": 0.8, "check_rate_hz": 30.0,
         "moving_joints": [0, 1, 2, 3, 4, 5]}
    d.update(scene.config.get("tasks") or {})
    return d


def feasible_poses(scene, origins: np.ndarray, p_tool_omc: np.ndarray, clearance: float) -> np.ndarray:
    """(N,) True where the arm's links (beyond the base column) and the tool stay ``clearance`` + link radius
    clear of every box (table, patient, the robot's cart, ...) and above the floor."""
    a, b, r = link_capsules(origins, scene.T_omc_diana_base)
    a, b, r = a[:, 1:], b[:, 1:], r[1:]  # the base column stands on the cart
    u = np.linspace(0.0, 1.0, 6)
    pts = a[:, :, None, :] + (b - a)[:, :, None, :] * u[None, None, :, None]  # (N, L, 6, 3)
    ok = np.all(pts[..., 2] >= r[None, :, None] + clearance, axis=(1, 2)) & (p_tool_omc[:, 2] >= clearance)
    for li in range(len(r)):
        ok &= ~np.any(points_in_boxes(pts[:, li], scene.boxes, margin=r[li] + clearance), axis=1)
    ok &= ~points_in_boxes(p_tool_omc, scene.boxes, margin=clearance + 0.05)
    return ok


def _candidate_windows(labels: np.ndarray, s: np.ndarray, order: tuple[int, ...], min_path: float,
                       lead: float) -> list[tuple[int, int]]:
    """Index windows [i0, i1] of a feasible sweep whose compressed labels equal ``order``.

    s: cumulative path length along the sweep. The first run contributes its last ``lead`` metres, the last run
    its first ``lead`` metres; every run must offer at least ``min_path`` metres.
    """
    r = runs(labels)  # (label, first, last inclusive); the *_e below are end-exclusive indices (last + 1)
    n = len(order)
    out = []
    for k in range(len(r) - n + 1):
        win = r[k:k + n]
        if tuple(w[0] for w in win) != order:
            continue
        lengths = [s[min(last + 1, len(s) - 1)] - s[first] for _, first, last in win]
        if min(lengths) < min_path:
            continue
        first_b, first_e = win[0][1], win[0][2] + 1
        last_b, last_e = win[-1][1], win[-1][2] + 1
        # start `lead` metres before the first boundary, end `lead` metres after the last one
        i0 = int(np.searchsorted(s, s[first_e] - lead, side="left"))
        i0 = min(max(i0, first_b), first_e - 1)
        i1 = int(np.searchsorted(s, s[last_b] + lead, side="right")) - 1
        i1 = max(min(i1, last_e - 1), last_b)
        out.append((i0, i1))
    return out


def tool_positions(scene, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Joint origins (N,7,3) in diana_base, flange (N,4,4) in diana_base, tool origin (N,3) in omc."""
    origins, flange = arm_geometry(scene.dk, Q)
    T = scene.T_omc_diana_base @ flange @ scene.T_flange_tool
    return origins, flange, T[:, :3, 3]


def _physics(scene, arc: JointArc, order: tuple[int, ...], st: dict) -> tuple[bool, str, float, float]:
    frac_ots_b, frac_omc = simulate_ideal_visibility(scene, arc, rate_hz=float(st["check_rate_hz"]))
    if BVV in order and frac_ots_b < st["min_ots_fraction"]:
        return False, "Vega sees the tool too little in the B part", frac_ots_b, frac_omc
    if frac_omc < st["min_omc_fraction"]:
        return False, "OMC tracks the tool too little", frac_ots_b, frac_omc
    return True, "", frac_ots_b, frac_omc


def _boundary_points(scene, step: float = 0.05) -> dict[frozenset, np.ndarray]:
    """Midpoints between grid neighbours of different regions in the robot's reach, per region pair.

    Boundaries such as PVV|BVV are thin in a good layout (the OTS looks where the OMC sees well), so a random
    start configuration rarely puts the target next to one; the generator aims the arm at these points instead.
    """
    key = (id(scene.layout), step)
    if key in _BOUNDARY_CACHE:
        return _BOUNDARY_CACHE[key]
    zone = (scene.config.get("diana") or {}).get("base_zone") or {}
    bx = zone.get("x", [scene.T_omc_diana_base[0, 3]] * 2)
    by = zone.get("y", [scene.T_omc_diana_base[1, 3]] * 2)
    reach = 1.1
    z0 = scene.T_omc_diana_base[2, 3] + 0.2856
    xs = np.arange(bx[0] - reach, bx[1] + reach + 1e-9, step)
    ys = np.arange(by[0] - reach, by[1] + reach + 1e-9, step)
    zs = np.arange(max(0.1, z0 - reach), z0 + reach + 1e-9, step)
    G = np.stack(np.meshgrid(xs, ys, zs, indexing="ij"), axis=-1)
    P = G.reshape(-1, 3)
    lab = label_points(scene.layout, P)[0].astype(np.int64)
    lab[points_in_boxes(P, scene.static_boxes, margin=0.05)] = 0
    for box in scene.static_boxes:  # under a box (e.g. below the table top) the arm cannot get in
        local = (P - box.center) @ box.R
        under = np.all(np.abs(local[:, :2]) <= box.half[:2] + 0.1, axis=1) & (local[:, 2] < box.half[2])
        lab[under] = 0
    L = lab.reshape(G.shape[:3])
    out: dict[frozenset, list] = {}
    for ax in range(3):
        a = [slice(None)] * 3
        b = [slice(None)] * 3
        a[ax] = slice(0, -1)
        b[ax] = slice(1, None)
        la, lb = L[tuple(a)], L[tuple(b)]
        m = (la != lb) & (la > 0) & (lb > 0)
        mid = (G[tuple(a)][m] + G[tuple(b)][m]) / 2
        for pa, pb, pt in zip(la[m], lb[m], mid, strict=True):
            out.setdefault(frozenset((int(pa), int(pb))), []).append(pt)
    res = {k: np.asarray(v) for k, v in out.items()}
    _BOUNDARY_CACHE[key] = res
    return res


_BOUNDARY_CACHE: dict = {}


def _ik_position(scene, q0: np.ndarray, target_omc: np.ndarray, iters: int = 60, tol: float = 0.005):
    """Damped least-squares IK of the tool origin to ``target_omc`` starting from q0 (joint limits clipped)."""
    lo, hi = scene.dk.joint_limits
    q = q0.copy()
    eps = 1e-5
    for _ in range(iters):
        _, _, p = tool_positions(scene, q[None])
        e = target_omc - p[0]
        if np.linalg.norm(e) < tol:
            return q
        Qd = q[None] + eps * np.eye(7)
        _, _, pd = tool_positions(scene, Qd)
        J = ((pd - p[0]) / eps).T  # (3, 7)
        dq = J.T @ np.linalg.solve(J @ J.T + 1e-4 * np.eye(3), e)
        n = np.linalg.norm(dq)
        if n > 0.2:
            dq *= 0.2 / n
        q = np.clip(q + dq, lo, hi)
    return None


def _face_tool_to_vega(scene, q: np.ndarray) -> np.ndarray:
    """Turn joint 7 (it spins the tool about its mount axis, the target origin stays put) so the tool's plate
    faces the Vega as well as it can at q — as a user mounts a tracked tool to face the camera."""
    normal = scene.bodies["tool"].normal
    if normal is None:
        return q
    lo, hi = scene.dk.joint_limits
    cand = np.linspace(lo[6] + 0.1, hi[6] - 0.1, 72)
    Q = np.tile(q, (len(cand), 1))
    Q[:, 6] = cand
    _, flange = arm_geometry(scene.dk, Q)
    T = scene.T_omc_diana_base @ flange @ scene.T_flange_tool
    to_vega = scene.T_omc_ots[:3, 3] - T[:, :3, 3]
    cosang = np.einsum("nij,j,ni->n", T[:, :3, :3], normal, to_vega) / np.linalg.norm(to_vega, axis=1)
    out = q.copy()
    out[6] = cand[int(np.argmax(cosang))]
    return out


PLAN_VERSION = 2  # bump when the search changes: invalidates cached plans (2: BVV needs the Vega's line of sight)
PLANS_FILE = "task_plans.yaml"


class StalePlanWarning(UserWarning):
    """A shipped or cached plan no longer realises its task in the current scene; the task is planned again."""


def _cache_key(task: str, scene) -> str:
    cfg = {k: v for k, v in scene.config.items() if k != "_source"}
    try:
        layout_text = Path(scene.layout.source).read_text()
    except OSError:
        layout_text = repr(scene.layout)
    blob = json.dumps([PLAN_VERSION, task, cfg, layout_text], sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:24]


def _cache_dir() -> Path:
    return Path(os.environ.get("FULLPERC_CACHE", Path.home() / ".cache" / "fullperc")) / "task_plans"


def plans_file_of(scene) -> str:
    """The shipped plans file of ``scene``: its twin profile's ``plans_file``, else ``task_plans.yaml``."""
    return str(scene.config.get("_plans_file") or PLANS_FILE)


def source_plans_path(name: str = PLANS_FILE) -> Path:
    """``config/<name>`` in the source tree (what ``--write-plans`` writes)."""
    return Path(__file__).resolve().parents[2] / "config" / name


def default_plans_path(name: str = PLANS_FILE) -> Path | None:
    """The installed ``share/fullperc_eval/config/<name>``, else the source copy, else None."""
    try:
        return share_path("fullperc_eval", "config", name)
    except FileNotFoundError:
        return None


def plan_to_dict(plan: TaskPlan) -> dict:
    a = plan.arc
    return {"task": plan.task,
            "arc": {"q0": [float(v) for v in a.q0], "joint": int(a.joint), "start": float(a.start),
                    "end": float(a.end), "move": float(a.move), "hold_start": float(a.hold_start),
                    "hold_end": float(a.hold_end)},
            "T_omc_diana_base": np.asarray(plan.T_omc_diana_base, float).tolist(), "attempts": int(plan.attempts),
            "region_path_m": [float(v) for v in plan.region_path_m], "ots_fraction_b": float(plan.ots_fraction_b),
            "omc_fraction": float(plan.omc_fraction)}


def plan_from_dict(d: dict) -> TaskPlan:
    """Inverse of :func:`plan_to_dict`; raises KeyError/TypeError/ValueError on a malformed entry."""
    a = d["arc"]
    if "rest" in a:  # disk cache format of PLAN_VERSION 1
        arc = JointArc(tuple(float(v) for v in a["q0"]), *a["rest"])
    else:
        arc = JointArc(tuple(float(v) for v in a["q0"]), int(a["joint"]), float(a["start"]), float(a["end"]),
                       float(a["move"]), float(a["hold_start"]), float(a["hold_end"]))
    if len(arc.q0) != 7:
        raise ValueError(f"q0 has {len(arc.q0)} joints, expected 7")
    T = np.asarray(d["T_omc_diana_base"], dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError("T_omc_diana_base must be a finite 4x4 matrix")
    return TaskPlan(str(d["task"]), arc, T, int(d["attempts"]), tuple(float(v) for v in d["region_path_m"]),
                    float(d["ots_fraction_b"]), float(d["omc_fraction"]))


def load_shipped_plans(path: str | os.PathLike | None = None) -> dict[str, dict]:
    """Task -> plan entry (dict) of a plans file; {} when there is none. A malformed file raises ValueError."""
    p = Path(path) if path is not None else default_plans_path()
    if p is None:
        return {}
    try:
        data = yaml.safe_load(Path(p).read_text())
    except (OSError, yaml.YAMLError) as e:
        raise ValueError(f"task plans file {p}: {e}") from e
    if not isinstance(data, dict) or not isinstance(data.get("plans"), dict):
        raise ValueError(f"task plans file {p}: expected a mapping with 'plans: {{task: plan}}'")
    if data.get("plan_version") != PLAN_VERSION:
        warnings.warn(f"task plans file {p} was written by plan_version {data.get('plan_version')!r}, this search is "
                      f"{PLAN_VERSION}: ignored (regenerate: python -m fullperc_eval.sim --write-plans)",
                      StalePlanWarning, stacklevel=2)
        return {}
    return data["plans"]


_MEM_CACHE: dict[str, TaskPlan] = {}
_SHIPPED: dict[str, dict[str, dict]] = {}   # plans file name -> its plans


def _shipped(task: str, name: str = PLANS_FILE) -> TaskPlan | None:
    if name not in _SHIPPED:
        _SHIPPED[name] = load_shipped_plans(default_plans_path(name))
    d = _SHIPPED[name].get(task)
    if d is None:
        return None
    try:
        return plan_from_dict(d)
    except (KeyError, TypeError, ValueError) as e:
        warnings.warn(f"shipped plan for {task} is malformed ({e}); planning it again", StalePlanWarning,
                      stacklevel=3)
        return None


def plan_task(task: str, scene, cache: bool = True) -> TaskPlan:
    """:func:`search_task` with a cache: memory, the shipped plans file, ``$FULLPERC_CACHE``/~/.cache/fullperc.

    The search is deterministic, so the cache only saves time (seconds to a minute per order). Every plan taken
    from the shipped file or the disk cache is re-checked on the current scene (:func:`check_arc_order`) before it
    is used; a shipped plan that fails is reported (:class:`StalePlanWarning`) and the task is planned again. The
    disk cache key covers the task, scene.yaml and the layout file's text.
    """
    order = parse_task(task)
    key = _cache_key(task, scene)
    rate = float(scene.config["omc"]["rate_hz"])

    def problem(plan: TaskPlan) -> str:
        return check_arc_order(scene.with_diana_base(plan.T_omc_diana_base), plan.arc, order, rate_hz=rate)

    if cache:
        plan = _MEM_CACHE.get(key)
        if plan is not None:
            return plan
        plan = _shipped(task, plans_file_of(scene))
        if plan is not None:
            err = problem(plan)
            if not err:
                _MEM_CACHE[key] = plan
                return plan
            warnings.warn(f"shipped plan for {task} ({plans_file_of(scene)}) is stale in this scene: {err}; planning "
                          "it again (regenerate the file: python -m fullperc_eval.sim --write-plans)",
                          StalePlanWarning, stacklevel=2)
        f = _cache_dir() / f"{key}.json"
        try:
            plan = plan_from_dict(json.loads(f.read_text()))
        except (OSError, ValueError, KeyError, TypeError):
            plan = None
        if plan is not None and not problem(plan):
            _MEM_CACHE[key] = plan
            return plan
    plan = search_task(task, scene)
    _MEM_CACHE[key] = plan
    if cache:
        try:
            _cache_dir().mkdir(parents=True, exist_ok=True)
            tmp = _cache_dir() / f"{key}.json.tmp{os.getpid()}"
            tmp.write_text(json.dumps(plan_to_dict(plan)))
            tmp.replace(_cache_dir() / f"{key}.json")
        except OSError:
            pass  # a read-only home only costs time
    return plan


def search_task(task: str, scene) -> TaskPlan:
    """Find a single-joint arc realising ``task`` in ``scene`` (see module docstring); raises TaskPlanningError."""
    order = parse_task(task)
    st = _settings(scene)
    lo, hi = scene.dk.joint_limits
    m = np.radians(st["joint_margin_deg"])
    idx = TASKS.index(task) if task in TASKS else len(TASKS)
    rng = np.random.default_rng([int(st["search_seed"]), idx])
    step = np.radians(st["sweep_step_deg"])
    rejected: dict[str, int] = {}
    best: TaskPlan | None = None
    found = 0
    zone = (scene.config.get("diana") or {}).get("base_zone")
    base_scene = scene
    for attempt in range(1, int(st["max_attempts"]) + 1):
        # every other attempt: aim the target at a boundary between two neighbouring regions of the order
        target = None
        if attempt % 4 != 1:  # three attempts in four aim at a boundary, the rarest boundaries most often
            bpts = _boundary_points(base_scene)
            pairs = [frozenset(p) for p in zip(order, order[1:], strict=False)]
            pairs = [p for p in pairs if p in bpts and len(bpts[p])]
            if pairs:
                w = np.array([1.0 / len(bpts[p]) for p in pairs])
                bnd = bpts[pairs[int(rng.choice(len(pairs), p=w / w.sum()))]]
                target = bnd[int(rng.integers(len(bnd)))]
        if zone:
            for _ in range(100):  # with a target: put the cart within reach of it
                x = rng.uniform(*zone["x"])
                y = rng.uniform(*zone["y"])
                if target is None or 0.25 <= np.hypot(x - target[0], y - target[1]) <= 0.85:
                    break
            yaw = np.radians(rng.uniform(*zone["yaw_deg"]))
            T = base_scene.T_omc_diana_base.copy()
            T[:3, :3] = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
            T[:2, 3] = (x, y)
            scene = base_scene.with_diana_base(T)
        q0 = rng.uniform(lo + m, hi - m)
        if target is not None:
            qi = _ik_position(scene, q0, target)
            if qi is None or np.any(qi < lo + m) or np.any(qi > hi - m):
                rejected["no IK to a boundary"] = rejected.get("no IK to a boundary", 0) + 1
                continue
            q0 = qi
        q0 = _face_tool_to_vega(scene, q0)
        joints = list(st["moving_joints"])
        rng.shuffle(joints)
        for j in joints:
            angles = np.arange(lo[j] + m, hi[j] - m + 1e-12, step)
            Q = np.tile(q0, (len(angles), 1))
            Q[:, j] = angles
            origins, _, p = tool_positions(scene, Q)
            ok = feasible_poses(scene, origins, p, st["min_clearance_m"])
            labels = np.zeros(len(angles), dtype=np.int64)
            if ok.any():
                labels[ok] = label_points(scene.layout, p[ok])[0]
            s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
            # split the sweep at infeasible poses (label 0 never matches an order)
            # the order may appear along the sweep (joint moving up) or against it (joint moving down)
            cands = [(i0, i1, True) for i0, i1 in
                     _candidate_windows(labels, s, order, st["min_region_path_m"], st["lead_path_m"])]
            if order[::-1] != order:
                cands += [(i0, i1, False) for i0, i1 in
                          _candidate_windows(labels, s, order[::-1], st["min_region_path_m"], st["lead_path_m"])]
            for i0, i1, forward in cands:
                if np.degrees(angles[i1] - angles[i0]) > st["max_arc_deg"]:
                    rejected["arc too long"] = rejected.get("arc too long", 0) + 1
                    continue
                a, b = (angles[i0], angles[i1]) if forward else (angles[i1], angles[i0])
                q_start = q0.copy()
                q_start[j] = a
                arc = JointArc(tuple(float(v) for v in q_start), int(j), float(a), float(b), float(st["move_s"]),
                               float(st["hold_s"]), float(st["hold_s"]))
                if arc.peak_velocity > scene.dk.model.velocityLimit[j]:
                    rejected["too fast"] = rejected.get("too fast", 0) + 1
                    continue
                err = check_arc_order(scene, arc, order, rate_hz=float(scene.config["omc"]["rate_hz"]))
                if err:
                    rejected["dense check"] = rejected.get("dense check", 0) + 1
                    continue
                good, why, f_ots, f_omc = _physics(scene, arc, order, st)
                if not good:
                    rejected[why] = rejected.get(why, 0) + 1
                    continue
                t = np.linspace(0, arc.duration, 400)
                _, _, pp = tool_positions(scene, arc.sample(t)[0])
                lab = label_points(scene.layout, pp)[0]
                seg = np.concatenate([[0.0], np.linalg.norm(np.diff(pp, axis=0), axis=1)])
                lens = tuple(float(seg[1:][lab[1:] == r].sum()) for r in order)
                plan = TaskPlan(task, arc, scene.T_omc_diana_base.copy(), attempt, lens, f_ots, f_omc)
                if best is None or f_ots > best.ots_fraction_b:
                    best = plan
                found += 1
                # a Vega that sees the B part is what the task is for: take the first such arc, else the
                # best of the first `max_candidates` valid ones
                if BVV not in order or f_ots >= st["good_ots_fraction"] or found >= int(st["max_candidates"]):
                    return best
                break  # next start configuration
    if best is not None:
        return best
    raise TaskPlanningError(
        f"task {task}: no single-joint arc of the Diana crosses {order_name(order)} in this scene after "
        f"{st['max_attempts']} start configurations (rejections: {rejected or 'no window with that order'}); "
        "check the layout (OTS volume, cameras) and the Diana base pose in scene.yaml")


def check_arc_order(scene, arc: JointArc, order: tuple[int, ...], rate_hz: float = 120.0) -> str:
    """'' when the target path of ``arc`` sampled at ``rate_hz`` visits exactly ``order``, else a reason."""
    t = np.arange(0.0, arc.duration, 1.0 / rate_hz)
    Q, _ = arc.sample(t)
    origins, _, p = tool_positions(scene, Q)
    ok = feasible_poses(scene, origins, p, 0.0)
    if not ok.all():
        return f"{int((~ok).sum())} poses collide with obstacles"
    labels = label_points(scene.layout, p)[0]
    got = compress(labels)
    if got != tuple(order):
        return f"visits {order_name(got)}"
    st = _settings(scene)
    clear = st.get("base_marker_clearance_m")
    if clear is not None:   # the tool must not sweep through the reference marker
        d = np.linalg.norm(p - scene.T_omc_base[:3, 3], axis=1).min()
        if d < float(clear):
            return f"passes {d:.3f} m from the base marker (< {float(clear):.3f} m)"
    b_range = st.get("max_b_range_m")
    if b_range is not None and np.any(labels == BVV):   # the B part in the Vega's recommended (middle) range
        d = np.linalg.norm(p[labels == BVV] - scene.T_omc_ots[:3, 3], axis=1).max()
        if d > float(b_range):
            return f"B part reaches {d:.2f} m from the Vega (> {float(b_range):.2f} m)"
    return ""


def write_plans(path: str | os.PathLike | None = None, tasks=TASKS, log=print, profile: str | None = None) -> Path:
    """Plan ``tasks`` cold on the scene of ``profile`` (seed 0) and write them as its shipped plans file."""
    scene = build_scene(0, profile=profile)
    out = Path(path) if path is not None else source_plans_path(plans_file_of(scene))
    plans = {}
    if out.exists():  # keep the entries of tasks not planned now (in TASKS order)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", StalePlanWarning)
            old = load_shipped_plans(out)
        plans = {t: old[t] for t in TASKS if t in old and t not in tasks}
    for task in tasks:
        t0 = time.monotonic()
        plan = search_task(task, scene)
        plans[task] = plan_to_dict(plan)
        log(f"{task}: {time.monotonic() - t0:.1f} s, {plan.attempts} start configurations, joint {plan.arc.joint}, "
            f"Vega sees {100 * plan.ots_fraction_b:.0f} % of the B part, OMC {100 * plan.omc_fraction:.0f} %")
    how = "--write-plans" + (f" --profile {profile}" if profile not in (None, "base") else "")
    header = (f"# Precomputed task plans of the {scene.config['_profile']} scene (seed-independent: the search has its "
              "own seed).\n"
              f"# Generated by `python -m fullperc_eval.sim {how}`; do not edit by hand.\n"
              "# plan_task() uses these first and re-checks each against the margin model before use\n"
              "# (a stale plan is reported and re-planned).\n"
              f"# layout: {Path(scene.layout.source).name}, scene: {Path(scene.config.get('_source', '')).name}\n")
    plans = {t: plans[t] for t in TASKS if t in plans}
    body = yaml.safe_dump({"plan_version": PLAN_VERSION, "plans": plans}, sort_keys=False, default_flow_style=None,
                          width=120)
    tmp = out.with_suffix(out.suffix + f".tmp{os.getpid()}")
    tmp.write_text(header + body)
    tmp.replace(out)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m fullperc_eval.sim",
                                 description="Plan the evaluation tasks; --write-plans regenerates the shipped file.")
    ap.add_argument("--write-plans", action="store_true", help="plan cold and write the shipped plans file")
    ap.add_argument("--out", default=None, help=f"plans file (default: {source_plans_path()})")
    ap.add_argument("--tasks", nargs="+", default=list(TASKS), choices=TASKS, metavar="TASK")
    ap.add_argument("--profile", default="base", help="twin profile whose plans to write: paper, spec or base "
                    "(scene.yaml alone; default)")
    args = ap.parse_args(argv)
    if not args.write_plans:
        ap.print_help()
        return 2
    try:
        out = write_plans(args.out, args.tasks, profile=args.profile)
    except (TaskPlanningError, OSError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
