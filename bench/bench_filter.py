"""Fusion filter cost: median time of one filter step per kind, and samples/s through TargetPipeline.

``filter_step_us[<name>]`` (issue 16 item 3, goal <= 20 us; ``cbkf`` and ``fullperc`` first, then every other
registered filter but the pass-through): one ``predict`` + ``update`` of the filter the pipeline uses
(``filters.registry.make_filter``; the paper's four in closed form per axis, paper_fast.py; ``fullperc`` its fast
form, filters/fullperc.py) on prebuilt Measurements, as the pipeline calls it, over a 120 Hz global stream with a
local sample paired to every second one (3 ms lag), positions only with the filters' fixed noise; median over
interleaved repeats of the mean per step. Baseline (same run, interleaved): the filter's general form, the tests'
reference (``filters.FusionFilter`` for the paper's kinds, ``fullperc_reference.FullpercReference`` for
``fullperc``), else the bare numpy KF step below.
``filter_step_us[fullperc,6dof]``: the same stream as ``fullperc`` is fed in the pipeline -- every sample with its
orientation and its model covariance (measurement_models: the OMC's from fit error and view margin, rotated into
base, with ``sys_var``; the local one with a calibrated link's covariance through a 1.5 m lever arm, which couples
position, rotation and the axes) -- against the reference on the same items.
``fullperc_rot_noise_scale_step_us``: the fast form on the 6dof items with the OMC's rotation noise scale
(``rot_noise_adapt_time`` 1 s, the default; rot_noise_scale.py) against the same filter with it off: its cost.
``fullperc_array_floor_us``: the array operations of one fullperc step in its fast form alone (predict F P F^T + Q,
U = P H^T, S, the LAPACK solve, P - U K^T, the reset, the symmetrisations, the Step's arrays; k = 6 rows, a global
sample with orientation) with no filter logic: the floor of a joint 21-state step in numpy.
``pipeline_samples_per_s_fullperc``: ``fullperc`` alone through TargetPipeline (its model covariances and
orientation, snapshots included), against the same run with the reference registered in its place.
Older lines: ``<kind>_step_*`` time ``FusionFilter.step`` (Measurement construction included) against a bare 6-state
constant-velocity numpy KF step (predict + 3-D update written inline, no validation, no NIS, no biased
estimator) -- the floor for a Python/numpy filter step in general matrix form.
Run: python bench/bench_filter.py
"""

from __future__ import annotations

import dataclasses
import statistics
import time

import numpy as np
from benchlib import emit, emit_error, median_time
from scipy.linalg.lapack import dgesv
from scipy.spatial.transform import Rotation as Rot

from fullperc_common.so3 import R_to_quat, so3_exp
from fullperc_common.transforms import inv_T, make_T
from fullperc_fusion.filters.api import SOURCE_GLOBAL, SOURCE_LOCAL, Measurement
from fullperc_fusion.filters.fullperc_params import FullpercParams
from fullperc_fusion.filters.fullperc_reference import FullpercReference
from fullperc_fusion.filters.measurement_models import local_covariance, omc_covariance, omc_systematic_var, rotate_cov
from fullperc_fusion.filters.paper_family import FILTER_KINDS, FusionFilter, PassThrough
from fullperc_fusion.filters.registry import FILTERS, make_filter
from fullperc_fusion.pipeline.ordered import FILTER_NAMES, TargetConfig, TargetPipeline

N = 2000


def bare_kf_steps(zs, dt=1 / 120, q=0.05, r=9e-8):
    I3 = np.eye(3)
    F = np.block([[I3, dt * I3], [0 * I3, I3]])
    Q = q * np.block([[dt**3 / 3 * I3, dt**2 / 2 * I3], [dt**2 / 2 * I3, dt * I3]])
    H = np.hstack([I3, 0 * I3])
    R = r * I3
    x = np.r_[zs[0], 0, 0, 0]
    P = np.eye(6) * 1e-4
    for z in zs:
        x = F @ x
        P = F @ P @ F.T + Q
        K = P @ H.T @ np.linalg.inv(H @ P @ H.T + R)
        x = x + K @ (z - H @ x)
        P = (np.eye(6) - K @ H) @ P
    return x


def filter_steps(kind, zs, paired):
    f = FusionFilter(kind)
    for k, z in enumerate(zs):
        t = (k + 1) * 8_333_333
        if paired:
            f.step(z_global=z, t_global=t, z_local=z, t_local=t)
        else:
            f.step(z_global=z, t_global=t)


def step_items(zs) -> list[tuple[int, list[Measurement]]]:
    """(stamp, measurements) as the pipeline feeds them: global at 120 Hz, every second one paired with a local
    sample stamped 3 ms later."""
    items = []
    for k, z in enumerate(zs):
        t = 10**18 + k * 8_333_333
        ms = [Measurement(t, SOURCE_GLOBAL, z + 2e-3)]
        if k % 2 == 0:
            ms.append(Measurement(t + 3_000_000, SOURCE_LOCAL, z))
        items.append((max(m.t_ns for m in ms), ms))
    return items


def step_items_6dof(n: int) -> list[tuple[int, list[Measurement]]]:
    """``step_items``' timing with what the pipeline gives ``fullperc``: a tool moving on a 0.1 m circle and
    turning at ~0.3 rad/s, noise at the models' level (0.1 mm, 2-3 mrad; the global source 2 mm off), orientations
    and model covariances (module docstring)."""
    rng = np.random.default_rng(2)
    R_ots = Rot.from_euler("z", 150, degrees=True).as_matrix()
    T_base_ots = make_T([3.0, 1.0, 0.5], R=R_ots)
    A = np.diag([3e-5] * 3 + [3e-4] * 3) @ rng.normal(size=(6, 6))
    link_cov = A @ A.T + np.diag([1e-9] * 3 + [1e-7] * 3)
    w = np.array([0.1, -0.2, 0.2])
    items = []
    for k in range(n):
        t = 10**18 + k * 8_333_333
        z = np.array([0.5 + 0.1 * np.cos(k / 240), 0.2 + 0.1 * np.sin(k / 240), 0.3])
        R = so3_exp(w * k / 120)
        Cg = rotate_cov(omc_covariance(rng.uniform(0.05e-3, 0.2e-3), rng.uniform(100, 600)), R_ots)
        ms = [Measurement(t, SOURCE_GLOBAL, z + 2e-3 + rng.normal(0, 1e-4, 3),
                          R_to_quat(so3_exp(rng.normal(0, 3e-3, 3)) @ R), Cg,
                          extras={"sys_var": omc_systematic_var(1e-4, 300.0)[0]})]
        if k % 2 == 0:
            T_ots_tool = inv_T(T_base_ots) @ make_T(z, R=R)
            Cl = local_covariance(T_base_ots, T_ots_tool, link_cov)
            ms.append(Measurement(t + 3_000_000, SOURCE_LOCAL, z + rng.normal(0, 1e-4, 3),
                                  R_to_quat(so3_exp(rng.normal(0, 2e-3, 3)) @ R), Cl))
        items.append((max(m.t_ns for m in ms), ms))
    return items


def array_floor_step(k: int = 6, n: int = 500) -> float:
    """Seconds per step of only the numpy work of one fast-form fullperc step (module docstring)."""
    rng = np.random.default_rng(0)
    A = rng.normal(size=(21, 21))
    P, F, Q, I21 = A @ A.T, np.eye(21), np.eye(21) * 1e-6, np.eye(21)
    H0, Rm, th = np.zeros((k, 21)), np.eye(k), np.arange(9)
    t0 = time.perf_counter()
    for _ in range(n):
        Pp = F @ P @ F.T + Q
        Pp = 0.5 * (Pp + Pp.T)
        H = H0.copy()
        H.put([0, 1, 2], 1.0)
        yv = np.array([0.0] * k)
        U = Pp @ H.T
        S = H @ U + Rm
        B = np.empty((k, 22))
        B[:, 0] = yv
        B[:, 1:] = U.T
        Z = dgesv(S, B)[2]
        Z[:, 0].tolist()
        S.tolist()
        Gt = Z[:, 1:]
        (yv @ Gt).tolist()
        P1 = Pp - U @ Gt
        Gr = I21.copy()
        Gr.put(th, 0.0)
        P2 = Gr @ P1 @ Gr.T
        P2 = 0.5 * (P2 + P2.T)
        float(P2.sum())
        for _ in range(4):
            np.array([0.0, 0.0, 0.0])
        P2.ravel()[th].reshape(3, 3)
    return (time.perf_counter() - t0) / n


REFERENCES = {"fullperc": FullpercReference}   # general forms of the other registered filters (tests' references)


def time_steps(f, items) -> float:
    """Mean seconds per predict + update over ``items`` on a fresh filter ``f``."""
    t0 = time.perf_counter()
    for t, ms in items:
        f.predict(t)
        f.update(*ms)
    return (time.perf_counter() - t0) / len(items)


STEP_FIGURES = ("cbkf", "fullperc")   # issue 16's names first; every other registered filter follows


def filter_step_figures(zs, repeats=9) -> None:
    """``filter_step_us[<name>]`` for every registered filter but pass-throughs; a name of STEP_FIGURES that is
    not registered is still listed, with an error. Baseline (interleaved, same items): the general form
    (``FusionFilter`` for the paper's kinds, :data:`REFERENCES`), else the bare 6-state numpy KF step.
    Then ``filter_step_us[fullperc,6dof]`` (module docstring) against its reference."""
    items = step_items(zs)
    names = [n for n in dict.fromkeys([*STEP_FIGURES, *FILTERS])
             if n not in FILTERS or FILTERS[n].factory is not PassThrough]
    runs = [(n, n, items) for n in names]
    if "fullperc" in FILTERS:
        runs.append(("fullperc,6dof", "fullperc", step_items_6dof(len(zs))))
    for label, name, its in runs:
        if name not in FILTERS:
            emit_error(f"filter_step_us[{label}]", "us", f"filter '{name}' is not registered in "
                       f"filters.registry.FILTERS ({', '.join(FILTERS)})")
            continue
        ref = (lambda name=name: FusionFilter(name)) if name in FILTER_KINDS else REFERENCES.get(name)
        fast, base = [], []
        try:
            for _ in range(repeats):   # interleaved: both see the same machine load
                fast.append(time_steps(make_filter(name), its))
                if ref is not None:
                    base.append(time_steps(ref(), its))
                else:
                    t0 = time.perf_counter()
                    bare_kf_steps(zs)
                    base.append((time.perf_counter() - t0) / len(zs))
        except Exception as e:  # noqa: BLE001 - a new filter may not take these items: say so, keep the others
            emit_error(f"filter_step_us[{label}]", "us", f"{type(e).__name__}: {e}")
            continue
        note = {"cbkf": "closed form per axis (as the pipeline uses it) vs general FusionFilter",
                "fullperc": "fast form (as the pipeline uses it) vs general FullpercReference; positions only, "
                            "fixed noise (the cbkf line's items)",
                "fullperc,6dof": "fast form vs general FullpercReference; orientation and model covariances on "
                                 "every sample, as the pipeline feeds fullperc"}.get(label)
        if note is None:
            note = ("closed form per axis vs general FusionFilter" if name in FILTER_KINDS else
                    "make_filter(name) vs its general form" if ref is not None else
                    "make_filter(name) as the pipeline uses it vs a bare 6-state numpy KF step")
        emit(f"filter_step_us[{label}]", statistics.median(fast) * 1e6, "us", baseline=statistics.median(base) * 1e6,
             note=note + "; goal <= 20 us")


def pipeline_events(seconds=10.0):
    T_omc_base = make_T([1.0, 0.5, 0.8], Rot.from_euler("z", 30, degrees=True).as_quat())
    T_omc_ots = make_T([3.0, 1.0, 1.5], Rot.from_euler("z", 150, degrees=True).as_quat())
    T_ots_base = inv_T(T_omc_ots) @ T_omc_base
    rng = np.random.default_rng(0)
    ev = []
    for k in range(int(seconds * 120)):
        t = k / 120
        ns = 10**18 + round(t * 1e9)
        Tt = make_T([0.5 + 0.1 * np.cos(t), 0.1 * np.sin(t), 0.3])
        Tm = T_omc_base @ Tt
        Tm[:3, 3] += rng.normal(0, 3e-4, 3)
        ev += [("omc", "base", ns, T_omc_base), ("omc", "tool", ns, Tm)]
        if k % 2 == 0:
            ev += [("ots", "base", ns + 3_000_000, T_ots_base),
                   ("ots", "tool", ns + 3_000_000, inv_T(T_omc_ots) @ T_omc_base @ Tt)]
    return ev


def run_pipeline(ev, filters):
    pipe = TargetPipeline(TargetConfig(filters=filters))
    n = 0
    for dev, body, ns, T in ev:
        (pipe.push_omc if dev == "omc" else pipe.push_ots)(body, ns, T)
        n += len(pipe.poll())
    return n + len(pipe.flush())


def rot_scale_cost(n: int, repeats: int = 9) -> None:
    """``fullperc_rot_noise_scale_step_us`` (module docstring), interleaved."""
    if "fullperc" not in FILTERS:
        return
    items = step_items_6dof(n)
    on, off = [], []
    for _ in range(repeats):
        on.append(time_steps(make_filter("fullperc"), items))
        off.append(time_steps(make_filter("fullperc", FullpercParams(rot_noise_adapt_time=0.0)), items))
    emit("fullperc_rot_noise_scale_step_us", statistics.median(on) * 1e6, "us", baseline=statistics.median(off) * 1e6,
         note="fullperc fast form on the 6dof items with the OMC rotation noise scale (default) vs with it off")


def main() -> None:
    zs = np.random.default_rng(1).normal(0, 1e-3, size=(N, 3)) + [0.5, 0.2, 0.3]
    filter_step_figures(zs)
    rot_scale_cost(len(zs))
    floor = statistics.median(array_floor_step() for _ in range(9))
    emit("fullperc_array_floor_us", floor * 1e6, "us", note="numpy work of one joint 21-state fullperc step alone "
         "(k = 6), no filter logic: the floor of filter_step_us[fullperc,6dof] in this form")
    base = median_time(lambda: bare_kf_steps(zs), repeats=5) / N
    emit("bare_numpy_kf6_step", base * 1e6, "us")
    for kind in FILTER_KINDS:
        for paired in (False, True):
            t = median_time(lambda kind=kind, paired=paired: filter_steps(kind, zs, paired), repeats=5) / N
            emit(f"{kind}_step_{'paired' if paired else 'global'}", t * 1e6, "us", baseline=base * 1e6)
    ev = pipeline_events()
    n_in = sum(1 for e in ev if e[1] == "tool")
    for filters in (("cbkf",), FILTER_NAMES):
        dt = median_time(lambda filters=filters: run_pipeline(ev, filters), repeats=3)
        emit(f"pipeline_samples_per_s_{'+'.join(filters)}", n_in / dt, "samples/s",
             note="target samples (OMC 120 Hz + OTS 60 Hz) pushed, synchronised, fused; real time needs 180/s")
    if "fullperc" in FILTERS:
        fast, ref = [], []
        entry = FILTERS["fullperc"]
        for _ in range(3):   # interleaved; the registry entry swapped for the reference only around its run
            fast.append(median_time(lambda: run_pipeline(ev, ("fullperc",)), repeats=1))
            FILTERS["fullperc"] = dataclasses.replace(entry, factory=FullpercReference)
            try:
                ref.append(median_time(lambda: run_pipeline(ev, ("fullperc",)), repeats=1))
            finally:
                FILTERS["fullperc"] = entry
        emit("pipeline_samples_per_s_fullperc", n_in / statistics.median(fast), "samples/s",
             baseline=n_in / statistics.median(ref),
             note="fullperc alone through TargetPipeline (model covariances, orientation) vs the same pipeline with "
                  "the general FullpercReference registered instead")


if __name__ == "__main__":
    main()
