"""Raw-sensor statistics behind the constants of ``fullperc_fusion.filters.measurement_models`` (issue 18), and the
noise-model file of an installation (``fit_noise_model``, :mod:`fullperc_fusion.filters.noise_model_file`).

Noise-model calibration, not filter tuning: every tracked /omc/<tool>/pose and /ots/<tool>/pose sample of the
bags is mapped into ``base`` by the node's own frame chain and compared with the Diana forward kinematics (the
bag's calibration.yaml); no filter runs. Printed per profile (one directory of task bags):

* OMC per-axis error variance regressed on [1, fit_error^2, 300/margin] (total, and the white part from
  consecutive differences / sqrt 2), the margin from ``margin.margin_at`` on the default layout;
* the OMC rotation error's regression on the same terms;
* the rms per-axis increment of the OMC's position and rotation error over lags 8 ms .. 10 s (the structure
  function: white level, then the systematic part decorrelating);
* the Vega tool's per-axis error by distance and its orientation error;
* the OMC position bias's length and std over distance (``bias_length``, ``bias_field_std``): the semivariogram of
  the raw (OMC - local chain) differences, the two devices against each other, no truth (:mod:`.bias_variogram`).

Run::

    fit_noise_model bags/spec bags/paper                   # the statistics of each directory
    fit_noise_model my_calibration_bags --write noise.yaml # pooled over the directories given: the noise model
                                                            # fusion_node reads (fullperc.noise_model_file)

(``python scripts/raw_sensor_stats.py`` is the same from a source checkout.) A directory holds bag directories, each
with its ``calibration.yaml`` (the arm's base in the OMC frame, ``fullperc_eval.bag.calibration``): the arm holds
the tracked tool, its joint angles give the truth.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from fullperc_common.transforms import inv_T
from fullperc_eval.bag.calibration import load_calibration
from fullperc_eval.bag.errors import BagError
from fullperc_eval.bag.fast_decode import DecodeError
from fullperc_eval.bag.reader import BagReader
from fullperc_eval.evaluation.bias_variogram import LENGTH_GRID, differences, fit_semivariogram, semivariogram
from fullperc_eval.evaluation.config import replay_config
from fullperc_eval.evaluation.ground_truth import GroundTruth
from fullperc_eval.evaluation.replay_data import _stamp_ns
from fullperc_fusion.filters.measurement_models import OmcModelParams
from fullperc_fusion.margin.layout import default_layout_path, load_layout
from fullperc_fusion.margin.view_margin import margin_at
from fullperc_fusion.pipeline.frame_chain import pose_to_T
from fullperc_fusion.pipeline.ordered import TargetPipeline

JOINT_TOPIC = "/diana/joint_states"
QUALITY_TYPE = "fullperc_msgs/msg/TrackingQuality"
# columns of a sample row
T, EX, EY, EZ, FIT, MARGIN, DIST, RX, RY, RZ, PX, PY, PZ = range(13)


def bag_rows(bag: Path, layout) -> tuple[np.ndarray, np.ndarray]:
    """(OMC rows, OTS rows) of one bag: time [s], position error (3) [m], fit error [m], margin [deg] (OMC),
    distance to the Vega [m] (OTS), rotation error vector (3) [rad], true position in base (3) [m]; errors in base,
    measured minus true.

    Read in bulk (:func:`_bulk_samples`): the same rows as :func:`bag_rows_per_message`, which feeds every message
    through the node's pipeline one by one and stays the reference (``test/test_model_constants.py`` pins the two
    equal on a committed bag). Why: that path spent most of a bag's ~2.5 s in rosbags' per-message deserialiser and
    in the pipeline's per-sample validation, synchroniser and filter, none of which decides a row. Where the bulk
    path cannot reproduce it (:class:`_NotBulk`) the per-message path runs.
    """
    try:
        samples, jt, jq, fit = _bulk_samples(Path(bag))
    except _NotBulk:
        return bag_rows_per_message(bag, layout)
    return _sample_rows(Path(bag), layout, samples, jt, jq, fit)


def bag_samples(bag: Path) -> list[tuple[str, int, np.ndarray, np.ndarray]]:
    """The target's raw samples of one bag in bag order: (device "omc" | "ots", stamp [ns], pose in the device
    frame, pose in ``base`` by the node's frame chain) -- what :func:`bag_rows` compares with the truth, without the
    truth (``bias_variogram`` compares the two devices with each other). Read in bulk where it can be."""
    try:
        return _bulk_samples(Path(bag))[0]
    except _NotBulk:
        return _samples_per_message(Path(bag))[0]


def bag_rows_per_message(bag: Path, layout) -> tuple[np.ndarray, np.ndarray]:
    """:func:`bag_rows` the plain way: every message of the chain's bodies, their qualities and the joint states
    deserialised by rosbags and pushed through the node's own pipeline (``TargetPipeline``) in bag order; an OMC
    target sample counts once ``T_omc_base`` is known, an OTS one once the local chain maps it."""
    return _sample_rows(Path(bag), layout, *_samples_per_message(Path(bag)))


def _samples_per_message(bag: Path) -> tuple[list, list, list, dict[tuple[str, int], float]]:
    """(samples, joint stamps, joint positions, fit errors) of :func:`bag_rows_per_message` (its docstring)."""
    cfg, _ = replay_config()
    cfg.filters = ("omc",)
    pipe = TargetPipeline(cfg)
    c = cfg.chain
    quality, wanted = _wanted(cfg)
    reader = BagReader(bag)
    reader.open()
    fit: dict[tuple[str, int], float] = {}
    jt, jq, samples = [], [], []
    try:
        for m in reader.messages([t for t in reader.topics if t in wanted]):
            msg = reader.deserialize(m.data, m.msgtype)
            if m.topic == "/diana/joint_states":
                jt.append(_stamp_ns(msg.header))
                jq.append(np.asarray(msg.position, dtype=float))
            elif m.topic in quality:
                fit[(quality[m.topic], _stamp_ns(msg.header))] = float(msg.fit_error)
            else:   # a chain body's /omc|/ots pose: ``wanted`` holds nothing else
                dev, body = m.topic.split("/")[1:3]
                t = _stamp_ns(msg.header)
                pp, qq = msg.pose.position, msg.pose.orientation
                Td = pose_to_T((np.array([pp.x, pp.y, pp.z]), np.array([qq.x, qq.y, qq.z, qq.w])))
                if dev == "omc":
                    pipe.push_omc(body, t, Td)
                    if body == c.omc_target and pipe.chain.links.T_omc_base is not None:
                        samples.append(("omc", t, Td, pipe.chain.global_T(Td)))
                else:
                    pipe.push_ots(body, t, Td)
                    if body == c.ots_target and pipe.chain.links.local_ready:
                        Tl, _ = pipe.chain.local_T(t, Td)
                        if Tl is not None:
                            samples.append(("ots", t, Td, Tl))
                pipe.poll()
    finally:
        reader.close()
    return samples, jt, jq, fit


def _wanted(cfg) -> tuple[dict[str, str], set[str]]:
    """(the target's quality topics -> device, every topic a row needs): only the chain's bodies (the pipeline
    ignores the rest) and the target's own quality: every body's quality message of a frame has the same stamp, so
    a quality is the target's only by its topic."""
    c = cfg.chain
    quality = {f"/omc/{c.omc_target}/quality": "omc", f"/ots/{c.ots_target}/quality": "ots"}
    wanted = {JOINT_TOPIC, *quality, *(f"/omc/{b}/pose" for b in (c.omc_target, c.omc_base, c.omc_rig)),
              *(f"/ots/{b}/pose" for b in (c.ots_target, c.ots_base))}
    return quality, wanted


class _NotBulk(Exception):
    """Something :func:`_bulk_samples` does not reproduce (another chain or link monitor setting, an invalid pose, a
    record of another type or one the bulk decoder cannot read): :func:`bag_rows` reads the bag per message."""


def _bulk_samples(bag: Path) -> tuple[list, np.ndarray, np.ndarray, dict[tuple[str, int], float]]:
    """What :func:`bag_rows_per_message` collects before its rows -- (samples, joint stamps, joint positions, fit
    errors) -- from the records decoded in bulk (:mod:`fullperc_eval.bag.fast_decode`).

    Only what decides a sample runs per record, in bag order: the chain's own static-link estimation
    (``FrameChain.observe_omc`` / ``observe_ots`` with pose_to_T's matrices, while the links are being estimated),
    and at each target sample the link in use. The rest of the node's pipeline does not change the links with this
    configuration: its synchroniser and filter only consume them, and its link monitor only counts a bump unless
    ``link_monitor.recalibrate`` is set (then, or with another local chain, this raises :class:`_NotBulk`). The
    samples are then mapped with one stacked product per link estimate (as :mod:`.batch` does for the replay)."""
    from fullperc_eval.bag.fast_decode import decode_joint_states, decode_pose_stamped, decode_tracking_quality
    from fullperc_eval.bag.reader import JOINT_TYPE, POSE_TYPE, _raw_messages

    from .batch import _matrices, _norm

    cfg, _ = replay_config()
    cfg.filters = ("omc",)
    c = cfg.chain
    if c.local_chain != "static" or cfg.monitor.recalibrate or c.omc_target in (c.omc_base, c.omc_rig) \
            or c.ots_target == c.ots_base:
        raise _NotBulk
    chain = TargetPipeline(cfg).chain
    links = chain.links
    quality, wanted = _wanted(cfg)
    # per pose topic: 0 OMC target, 1 OTS target, 2 OMC link body, 3 OTS base
    kind = {f"/omc/{c.omc_target}/pose": 0, f"/ots/{c.ots_target}/pose": 1, f"/ots/{c.ots_base}/pose": 3,
            **{f"/omc/{b}/pose": 2 for b in (c.omc_base, c.omc_rig)}}
    reader = BagReader(bag)
    topics = [t for t in reader.topics if t in wanted]
    want_type = {t: JOINT_TYPE if t == JOINT_TOPIC else QUALITY_TYPE if t in quality else POSE_TYPE for t in topics}
    if any(reader.topics[t].msgtype != want_type[t] for t in topics):
        raise _NotBulk
    decoders = {JOINT_TYPE: decode_joint_states, POSE_TYPE: decode_pose_stamped, QUALITY_TYPE: decode_tracking_quality}
    try:
        raw = _raw_messages(reader, topics)
        per = {}
        for k, t in enumerate(topics):
            idx = np.flatnonzero(raw.topic == k)
            per[t] = (idx, decoders[want_type[t]]([raw.data[i] for i in idx],
                                                  lambda d, ty=want_type[t]: reader.deserialize(d, ty)))
    except (BagError, DecodeError):
        raise _NotBulk from None   # the per-message path reads it again and says what is wrong
    finally:
        reader.close()
    fit: dict[tuple[str, int], float] = {}
    for t, dev in quality.items():
        if t in per:
            qb = per[t][1]
            fit.update(zip(((dev, s) for s in qb.t_ns.tolist()), qb.fit_error.tolist(), strict=True))
    jb = per[JOINT_TOPIC][1] if JOINT_TOPIC in per else None
    jt = np.asarray([] if jb is None else jb.t_ns, np.int64)
    jq = np.array([] if jb is None else jb.position)
    # every pose as pose_to_T accepts it (stamp > 0, finite, unit quaternion to 1e-2), else the per-message path
    # raises or rejects it as the node would
    mats: dict[int, np.ndarray] = {}
    for k, t in enumerate(topics):
        if t not in kind:
            continue
        pb = per[t][1]
        if not ((pb.t_ns > 0).all() and np.isfinite(pb.p).all() and np.isfinite(pb.q).all()
                and (np.abs(_norm(pb.q) - 1.0) <= 1e-2).all()):
            raise _NotBulk
        mats[k] = _matrices(pb.p, pb.q)
    within = np.zeros(len(raw.topic), np.int64)
    for idx, _ in per.values():
        within[idx] = np.arange(len(idx))
    kind_of = [kind.get(t, -1) for t in topics]
    bodies = [t.split("/")[2] for t in topics]
    stamps = {k: per[t][1].t_ns.tolist() for k, t in enumerate(topics) if k in mats}
    used: list[tuple[int, int, np.ndarray]] = []   # target samples in bag order: (topic, index in topic, link in use)
    for k, j in zip(raw.topic.tolist(), within.tolist(), strict=True):
        what = kind_of[k]
        if what == 0:
            if links.T_omc_base is not None:
                used.append((k, j, links.T_omc_base))
        elif what == 1:
            if links.T_base_ots is not None:        # the static chain's local_ready
                used.append((k, j, links.T_base_ots))
        elif what >= 2 and links.collecting:        # final links: a link body's sighting changes nothing any more
            (chain.observe_omc if what == 2 else chain.observe_ots)(bodies[k], stamps[k][j], mats[k][j])
    # mapping into base: inv(T_omc_base) @ T (global_T), T_base_ots @ T (the static local_T)
    mapped: dict[int, np.ndarray] = {}
    groups: dict[tuple[int, int], list[int]] = {}
    for n, (k, _, L) in enumerate(used):
        groups.setdefault((k, id(L)), []).append(n)
    for (k, _), ns in groups.items():
        L = used[ns[0]][2]
        A = inv_T(L) if kind_of[k] == 0 else L
        out = A @ mats[k][[used[n][1] for n in ns]]
        mapped.update(zip(ns, out, strict=True))
    samples = [("omc" if kind_of[k] == 0 else "ots", stamps[k][j], mats[k][j], mapped[n])
               for n, (k, j, _) in enumerate(used)]
    return samples, jt, jq, fit


def _sample_rows(bag: Path, layout, samples: list, jt, jq, fit: dict[tuple[str, int], float]
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The rows of :func:`bag_rows` from its samples ((device, stamp, pose in the device frame, pose in base), in
    bag order), the joint states and the target's fit error by (device, stamp)."""
    gt = GroundTruth(np.array(jt), np.array(jq), load_calibration(bag))
    Ttrue, ok = gt.T_base_tool(np.array([s[1] for s in samples], dtype=np.int64))
    rows: dict[str, list] = {"omc": [], "ots": []}
    R0 = np.where(ok[:, None, None], Ttrue[:, :3, :3], np.eye(3))          # the truth is NaN where invalid
    Rb = np.array([s[3][:3, :3] for s in samples]).reshape(-1, 3, 3)
    rvs = Rotation.from_matrix(Rb @ R0.transpose(0, 2, 1)).as_rotvec() if samples else np.zeros((0, 3))
    for (dev, t, Td, Tb), T0, k, rv in zip(samples, Ttrue, ok, rvs, strict=True):
        if not k:
            continue
        margin = margin_at(layout, Td[:3, 3])[0] if dev == "omc" else np.nan
        rows[dev].append((t * 1e-9, *(Tb[:3, 3] - T0[:3, 3]), fit.get((dev, t), -1.0), margin,
                          float(np.linalg.norm(Td[:3, 3])), *rv, *T0[:3, 3]))
    return np.array(rows["omc"]), np.array(rows["ots"])


def _segments(t: np.ndarray) -> list[np.ndarray]:
    cuts = np.flatnonzero((np.diff(t) < 0) | (np.diff(t) > 1.0)) + 1
    return np.split(np.arange(len(t)), cuts)


def regress(y: np.ndarray, fit: np.ndarray, margin: np.ndarray) -> np.ndarray:
    """Least squares y ~ a + k fit^2 + c 300/max(margin, 30); returns each coefficient as a signed std,
    sign(x) sqrt(|x|): a negative one (the data do not support that term) shows as a negative std."""
    A = np.column_stack([np.ones(len(y)), fit**2, 300.0 / np.maximum(margin, 30.0)])
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    return np.sign(coef) * np.sqrt(np.abs(coef))


def structure(e: np.ndarray, t: np.ndarray, lags: tuple[int, ...]) -> list[float]:
    """rms per-axis increment of e over each lag (in samples), within each bag."""
    out = []
    for L in lags:
        d = np.concatenate([e[s][L:] - e[s][:-L] for s in _segments(t) if len(s) > L])
        out.append(float(np.sqrt((d**2).mean())))
    return out


# distance bins [m] of the rotation error's structure function over space (:func:`structure_over_distance`)
DISTANCE_BINS = (0.0, 0.0025, 0.005, 0.01, 0.02, 0.035, 0.05, 0.075, 0.1, 0.15, 0.2, 0.3, 0.5)


def structure_over_distance(e: np.ndarray, x: np.ndarray, t: np.ndarray, bins=DISTANCE_BINS,
                            stride: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """(mean distance [m], rms per-axis increment of e) per distance bin: every pair of samples (each ``stride``-th
    sample) of the same bag, binned by the distance between their true positions ``x``. Why: the OMC's error is a
    field over the room; over time lags it mixes the tool's speed in (``FullpercParams.rot_bias_length``)."""
    bins = np.asarray(bins)
    sq, dist, cnt = np.zeros(len(bins) - 1), np.zeros(len(bins) - 1), np.zeros(len(bins) - 1)
    for seg in _segments(t):
        k = seg[::stride]
        i, j = np.triu_indices(len(k), 1)
        d = np.linalg.norm(x[k][i] - x[k][j], axis=1)
        b = np.digitize(d, bins) - 1
        ok = (b >= 0) & (b < len(cnt))
        np.add.at(sq, b[ok], ((e[k][i] - e[k][j]) ** 2).mean(1)[ok])
        np.add.at(dist, b[ok], d[ok])
        np.add.at(cnt, b[ok], 1)
    has = cnt > 0
    return dist[has] / cnt[has], np.sqrt(sq[has] / cnt[has])


def fit_gauss_markov(lags_s: np.ndarray, rms: np.ndarray, grid: tuple[float, float] = (0.05, 100.0)
                     ) -> tuple[float, float, float]:
    """(white std, systematic std, tau [s]) of D(L) = 2 w^2 + 2 s^2 (1 - exp(-L / tau)) fitted to the squared
    rms increments (grid over tau within ``grid``, linear least squares for w^2 and s^2 at each tau, the tau whose
    fit has both non-negative and the smallest relative residual). The same form over distance (``lags_s`` in
    metres) gives a correlation length instead of a time.

    When no tau of the grid gives a least-squares fit with both variances non-negative -- increments that grow
    faster than linearly with the lag to the last one, as a ``paper``-like room's position error can over a single
    session (``test_sensor_stats.py`` holds one such curve) -- each tau's fit is taken under that
    constraint instead (non-negative least squares), so a room's own recording still gives a model (there: tau at
    the grid's end, a bias that behaves as a random walk over a session) rather than zeros, which no filter can
    use (``omc_bias.sys_time`` must be > 0). Where the plain fit exists, as on every bag set the repository fits
    (``test_model_constants.py``), the result is that fit."""
    from scipy.optimize import nnls

    D = rms**2
    designs = [(tau, np.column_stack([2 * np.ones_like(lags_s), 2 * (1 - np.exp(-lags_s / tau))]))
               for tau in np.geomspace(grid[0], grid[1], 400)]

    def best_of(solve) -> tuple[float, float, float, float]:
        """(relative residual, w, s, tau) of the grid's best fit by ``solve`` (A -> coefficients, None: refused)."""
        best = (np.inf, 0.0, 0.0, 0.0)
        for tau, A in designs:
            coef = solve(A)
            if coef is not None:
                res = float(np.sum((A @ coef - D) ** 2 / D**2))
                if res < best[0]:
                    best = (res, float(np.sqrt(coef[0])), float(np.sqrt(coef[1])), float(tau))
        return best

    def plain(A):
        coef = np.linalg.lstsq(A, D, rcond=None)[0]
        return coef if np.all(coef >= 0) else None

    def constrained(A):
        coef = nnls(A, D)[0]
        return coef if coef[1] > 0 else None

    best = best_of(plain)
    if not np.isfinite(best[0]):
        best = best_of(constrained)
    return best[1], best[2], best[3]


def fit_two_gauss_markov(lags_s: np.ndarray, rms: np.ndarray) -> tuple[float, float, float, float, float]:
    """(white std, fast std, fast tau, slow std, slow tau [s]) of D(L) = 2 w^2 + 2 s1^2 (1 - exp(-L / tau1))
    + 2 s2^2 (1 - exp(-L / tau2)), tau1 < tau2, fitted to the squared rms increments (grid over both taus,
    non-negative least squares for the variances, relative residuals). The slow part is what a bias state can
    follow; the fast part reverts within about a second and is noise of the sample."""
    from scipy.optimize import nnls

    D = rms**2
    best = (np.inf, 0.0, 0.0, 0.0, 0.0, 0.0)
    for t1 in np.geomspace(0.05, 3.0, 60):
        for t2 in np.geomspace(2.0, 200.0, 80):
            if t2 <= t1:
                continue
            A = np.column_stack([2 * np.ones_like(lags_s), 2 * (1 - np.exp(-lags_s / t1)),
                                 2 * (1 - np.exp(-lags_s / t2))]) / D[:, None]
            coef, _ = nnls(A, np.ones_like(D))
            res = float(np.sum((A @ coef - 1.0) ** 2))
            if res < best[0]:
                w2, s1, s2 = np.sqrt(coef)
                best = (res, float(w2), float(s1), float(t1), float(s2), float(t2))
    return best[1:]


def fitted(g: np.ndarray, o: np.ndarray, diffs: list[tuple[np.ndarray, np.ndarray]] | None = None) -> dict[str, Any]:
    """Every statistic of one profile's rows (:func:`bag_rows` of its bags, concatenated): regressions as
    (floor, fit gain, margin term) -- per-axis std [m or rad] -- structure functions, Gauss-Markov fits, the
    median fit error, the Vega's per-axis rms by distance and its orientation rms; with ``diffs``
    (:func:`profile_differences`) the raw differences' semivariogram and its fit (``pos_variogram``, ``pos_gm_dist``:
    nugget, s_f, L). ``test/test_model_constants.py`` holds the constants of ``measurement_models`` and
    ``FullpercParams`` to these on the committed bags."""
    out: dict[str, Any] = {}
    if diffs is not None:
        out["pos_variogram"] = semivariogram(diffs)
        out["pos_gm_dist"] = fit_semivariogram(*out["pos_variogram"])
    fit = np.where(g[:, FIT] >= 0, g[:, FIT], np.nan)
    ok = np.isfinite(fit)
    g, fit = g[ok], fit[ok]
    e, r = g[:, EX:EZ + 1], g[:, RX:RZ + 1]
    out["n_omc"], out["n_ots"] = len(g), len(o)
    out["fit_median"] = float(np.median(fit))
    out["pos_total"] = regress((e**2).mean(1), fit, g[:, MARGIN])
    out["rot_total"] = regress((r**2).mean(1), fit, g[:, MARGIN])
    pair = np.diff(g[:, T]) < 0.02
    dw = (np.diff(e, axis=0)[pair] ** 2).mean(1) / 2
    fm = 0.5 * (fit[1:] + fit[:-1])[pair]
    mm = np.minimum(g[1:, MARGIN], g[:-1, MARGIN])[pair]
    out["pos_white"] = regress(dw, fm, mm)
    d = np.diff(e, axis=0)[pair]
    out["pos_white_mad"] = 1.4826 * np.median(np.abs(d - np.median(d, 0)), 0) / np.sqrt(2)
    lags = (1, 6, 12, 30, 60, 120, 240, 360, 600, 1200)
    out["lags_s"] = np.asarray(lags) / 120.0
    out["structure_pos"] = np.asarray(structure(e, g[:, T], lags))
    out["structure_rot"] = np.asarray(structure(r, g[:, T], lags))
    out["pos_gm"] = fit_gauss_markov(out["lags_s"], out["structure_pos"])
    out["rot_gm"] = fit_gauss_markov(out["lags_s"], out["structure_rot"])
    out["rot_gm2"] = fit_two_gauss_markov(out["lags_s"], out["structure_rot"])
    out["rot_dist_m"], out["structure_rot_dist"] = structure_over_distance(r, g[:, PX:PZ + 1], g[:, T])
    out["rot_gm_dist"] = fit_gauss_markov(out["rot_dist_m"], out["structure_rot_dist"], grid=(0.002, 2.0))
    eo, ro, dist = o[:, EX:EZ + 1], o[:, RX:RZ + 1], o[:, DIST]
    out["ots_by_distance"] = [(lo, hi, float(np.sqrt((eo[s] ** 2).mean())), int(s.sum()))
                              for lo, hi in ((0.9, 1.3), (1.3, 1.6), (1.6, 1.8), (1.8, 2.5))
                              if (s := (dist >= lo) & (dist < hi)).any()]
    out["ots_rot_rms"] = float(np.sqrt((ro**2).mean()))
    return out


def report(name: str, f: dict[str, Any]) -> None:
    """Print the statistics ``f`` (:func:`fitted`) of ``name``."""
    print(f"== {name}: {f['n_omc']} OMC samples, {f['n_ots']} OTS samples; median fit error "
          f"{f['fit_median'] * 1e3:.3f} mm")
    a, k, c = f["pos_total"]
    print(f"OMC position, total per axis:   floor {a * 1e3:.3f} mm, fit gain {k:.2f}, margin term {c * 1e3:.3f} mm")
    a, k, c = f["rot_total"]
    print(f"OMC rotation, total per axis:   floor {a * 1e3:.2f} mrad, fit gain {k:.1f} rad/m, margin term "
          f"{c * 1e3:.2f} mrad")
    a, k, c = f["pos_white"]
    print(f"OMC position, white per axis:   floor {a * 1e3:.3f} mm, fit gain {k:.2f}, margin term {c * 1e3:.3f} mm")
    print(f"OMC position, robust white per axis (MAD): {np.round(f['pos_white_mad'] * 1e3, 3)} mm")
    print("OMC structure function (lag s: pos mm / rot mrad per axis): "
          + ", ".join(f"{L:.2f}: {p * 1e3:.3f} / {q * 1e3:.2f}"
                      for L, p, q in zip(f["lags_s"], f["structure_pos"], f["structure_rot"], strict=True)))
    w, sy, tau = f["pos_gm"]
    print(f"OMC position as white + Gauss-Markov: white {w * 1e3:.3f} mm, systematic {sy * 1e3:.3f} mm, "
          f"tau {tau:.2f} s")
    w, sy, tau = f["rot_gm"]
    print(f"OMC rotation as white + Gauss-Markov: white {w * 1e3:.2f} mrad, systematic {sy * 1e3:.2f} mrad, "
          f"tau {tau:.2f} s")
    w, s1, t1, s2, t2 = f["rot_gm2"]
    print(f"OMC rotation as white + two Gauss-Markov: white {w * 1e3:.2f} mrad, fast {s1 * 1e3:.2f} mrad tau "
          f"{t1:.2f} s, slow {s2 * 1e3:.2f} mrad tau {t2:.1f} s (200 s: the grid's end, a random walk)")
    w, sy, L = f["rot_gm_dist"]
    print(f"OMC rotation over distance as white + Gauss-Markov: white {w * 1e3:.2f} mrad, systematic "
          f"{sy * 1e3:.2f} mrad, length {L * 1e3:.1f} mm")
    if "pos_gm_dist" in f:
        c0, sf, L = f["pos_gm_dist"]
        h, gam, _ = f["pos_variogram"]
        print("OMC - local chain position (raw) over distance, semivariogram (h mm: sqrt(gamma) mm): "
              + ", ".join(f"{d * 1e3:.0f}: {np.sqrt(v) * 1e3:.3f}" for d, v in zip(h, gam, strict=True)))
        print(f"  as nugget + Gauss-Markov: nugget {c0 * 1e3:.3f} mm, bias_field_std {sf * 1e3:.3f} mm, bias_length "
              f"{L:.3f} m" + (" (the grid's end: no level-off within these distances)" if _at_grid_end(L) else ""))
    for lo, hi, rms, n in f["ots_by_distance"]:
        print(f"OTS tool at {lo}-{hi} m: per-axis rms {rms * 1e3:.3f} mm (n={n})")
    print(f"OTS tool orientation: per-axis rms {f['ots_rot_rms'] * 1e3:.2f} mrad")


def pool_rows(parts: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """(OMC rows, OTS rows) of several :func:`bag_rows` / :func:`profile_rows` results, concatenated."""
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


def profile_rows(directory: Path, layout) -> tuple[np.ndarray, np.ndarray]:
    """:func:`bag_rows` of every bag directory below ``directory``, concatenated."""
    return pool_rows([bag_rows(b, layout) for b in sorted(p for p in Path(directory).iterdir() if p.is_dir())])


def profile_differences(directory: Path) -> list[tuple[np.ndarray, np.ndarray]]:
    """(e, x) of every bag directory below ``directory``: :func:`.bias_variogram.differences` of its
    :func:`bag_samples` (raw OMC - local chain, and the local chain's position)."""
    return [differences(bag_samples(b))[1:] for b in sorted(p for p in Path(directory).iterdir() if p.is_dir())]


def _at_grid_end(length: float) -> bool:
    return length >= 0.99 * LENGTH_GRID[1]


# the two-Gauss-Markov fit's slow time constant at or beyond this is the grid's end: a random walk
RANDOM_WALK_TAU_S = 100.0


def noise_model_from_stats(f: dict[str, Any]) -> tuple[dict[str, float], dict[str, float]]:
    """(``omc``, ``omc_bias``) sections of a noise-model file from :func:`fitted` statistics:

    * ``omc``: the white part's regression (floor, fit gain, margin term); the total's fit gain and margin term,
      and its floor beyond the white one (``sys_floor = sqrt(a_total^2 - a_white^2)``); the rotation's margin term
      and its floor beyond the white position floor over the lever (``rot_sys_floor``); ``marker_lever =
      k_fit / k_rot_fit`` (the built-in one when a gain is not positive) and the median fit error. A negative
      regression term counts as 0;
    * ``omc_bias``: the position structure function's Gauss-Markov fit (``sys_time``, ``sys_std``) and the
      slow part of the rotation's two-Gauss-Markov fit: a Gauss-Markov process (``rot_sys_time``,
      ``rot_sys_std``) with the correlation length of the rotation error over distance (``rot_bias_length``:
      how far the tool moves, once the Vega has lost it, before that part is forgotten), or, when its time
      constant is at the grid's end (>= :data:`RANDOM_WALK_TAU_S`), a random walk with the same short-lag
      increments: ``rot_bias_walk = 2 s^2 / tau``, ``rot_sys_time = 0`` and ``rot_bias_length = 0`` (nothing to
      forget: the slow error of such a room stays where it was learnt); with ``pos_gm_dist``, ``bias_field_std``
      and ``bias_field_length`` its s_f and L, and ``bias_length`` L too, or 0 when L is at the grid's end (no
      length determined: b is kept as learnt, CBKF's rule, and the field's s_f and L give the output covariance's
      growth with distance within the distances seen, ``fullperc_state.field_var``).
    """
    floor_w, k_w, m_w = np.maximum(f["pos_white"], 0.0)   # a negative term (signed std): the data show none
    floor_t, k_fit, m = np.maximum(f["pos_total"], 0.0)
    floor_r, k_rot, m_rot = np.maximum(f["rot_total"], 0.0)
    lever = k_fit / k_rot if k_fit > 0 and k_rot > 0 else OmcModelParams().marker_lever
    omc = {"white_std": floor_w, "white_fit_gain": k_w, "white_margin_std": m_w,
           "sys_floor": np.sqrt(max(floor_t**2 - floor_w**2, 0.0)), "fit_gain": k_fit, "margin_std": m,
           "marker_lever": lever, "rot_sys_floor": np.sqrt(max(floor_r**2 - (floor_w / lever) ** 2, 0.0)),
           "rot_margin_std": m_rot, "default_fit": f["fit_median"]}
    _, s, tau = f["pos_gm"]
    bias = {"sys_time": tau, "sys_std": s}
    _, _, _, s2, t2 = f["rot_gm2"]
    if t2 >= RANDOM_WALK_TAU_S:
        bias.update(rot_sys_time=0.0, rot_sys_std=0.0, rot_bias_walk=2.0 * s2**2 / t2, rot_bias_length=0.0)
    else:
        bias.update(rot_sys_time=t2, rot_sys_std=s2, rot_bias_length=f["rot_gm_dist"][2])
    if "pos_gm_dist" in f:
        _, sf, L = f["pos_gm_dist"]
        bias.update(bias_length=0.0 if _at_grid_end(L) else L, bias_field_std=sf, bias_field_length=L)
    return {k: float(v) for k, v in omc.items()}, {k: float(v) for k, v in bias.items()}


def write_noise_model(path: str | Path, f: dict[str, Any], source: str) -> str:
    """Write the noise-model file of statistics ``f`` (:func:`noise_model_from_stats`) to ``path``; returns it."""
    from fullperc_fusion.filters.noise_model_file import noise_model_yaml

    omc, bias = noise_model_from_stats(f)
    text = noise_model_yaml(omc, bias, f"{source}: {f['n_omc']} OMC samples against the arm's forward kinematics")
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(text)
    return text


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="fit_noise_model", description=__doc__.split("\n")[0])
    ap.add_argument("dirs", nargs="+", help="directories of bag directories (each bag with its calibration.yaml)")
    ap.add_argument("--write", default="", help="write the noise model of all directories pooled to this file")
    args = ap.parse_args(argv)
    layout = load_layout(default_layout_path())
    rows = [profile_rows(Path(d), layout) for d in args.dirs]
    diffs = [profile_differences(Path(d)) for d in args.dirs]
    stats = [fitted(g, o, df) for (g, o), df in zip(rows, diffs, strict=True)]
    for d, f in zip(args.dirs, stats, strict=True):
        report(d, f)
    if args.write:
        pooled = stats[0]
        if len(args.dirs) > 1:
            pooled = fitted(*pool_rows(rows), [d for df in diffs for d in df])
            report(" + ".join(args.dirs), pooled)
        write_noise_model(args.write, pooled, "raw-sensor statistics of " + ", ".join(args.dirs))
        print(f"wrote {args.write}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
