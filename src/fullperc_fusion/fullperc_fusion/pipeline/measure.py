"""An item's samples as the filters' :class:`~fullperc_fusion.filters.api.Measurement`\\ s in ``base``.

Two forms (:class:`~.ordered.TargetPipeline` builds the second only for a lane with a filter that declares
``models``, :class:`~fullperc_fusion.filters.api.Capabilities`):

* :func:`measurement` -- what every filter gets: the sample mapped into base, a device covariance rotated with it
  (C_base = J C J^T, J = diag(R_A, R_A), T_base = A T_dev; the links taken as exact) or the source's own fixed
  covariance (``noise_std``, :mod:`.sources`), else ``cov=None`` (the filter's fixed noise, as the paper does).
* :func:`model_measurements` -- the same samples with the covariances of :mod:`~fullperc_fusion.filters.
  measurement_models` (module docstring of :mod:`.ordered`, "Model covariances").

:class:`OmcQualities` keeps the OMC's TrackingQuality of each sample until the sample is fused.
"""

from __future__ import annotations

import numpy as np

from fullperc_common.transforms import T_to_pq, inv_T
from fullperc_fusion.filters.api import SOURCE_GLOBAL, SOURCE_LOCAL, Measurement
from fullperc_fusion.filters.measurement_models import local_covariance, omc_variances, rotate_diag_cov
from fullperc_fusion.margin.view_margin import margin_at
from fullperc_fusion.pipeline.frame_chain import FrameChain
from fullperc_fusion.pipeline.sources import model_cov_std
from fullperc_fusion.pipeline.synchronizer import SyncItem
from fullperc_fusion.pipeline.target import TargetConfig

QUALITY_KEEP_NS = 1_000_000_000   # OMC qualities older than this behind the fused sample are dropped
QUALITY_MAX = 512                 # a body whose poses never come (not tracked): only the newest are kept


class OmcQualities:
    """The TrackingQuality of OMC target samples by stamp (``fit_error`` [m], ``markers_used``), before or after
    their poses: looked up when the sample is fused, for the OMC model covariance. Input-side state: a rewind on
    arrival (arrival.py) fuses an item again with the same quality, so nothing here is rewound."""

    __slots__ = ("_by_t",)

    def __init__(self) -> None:
        self._by_t: dict[int, dict[str, float]] = {}

    def __len__(self) -> int:
        return len(self._by_t)

    def add(self, t_ns: int, quality: dict) -> None:
        """Keep ``quality`` for the sample at ``t_ns``; a malformed one only means the model's defaults (ignored)."""
        try:
            self._by_t[int(t_ns)] = {k: float(v) for k, v in dict(quality).items()}
        except (TypeError, ValueError):
            return
        if len(self._by_t) > QUALITY_MAX:
            for k in sorted(self._by_t)[:QUALITY_MAX // 2]:
                del self._by_t[k]

    def at(self, t_ns: int) -> dict[str, float]:
        """The quality of the sample at ``t_ns`` ({} without one; kept, the item may be fused again); the ones
        more than :data:`QUALITY_KEEP_NS` older are dropped."""
        qual = self._by_t.get(t_ns) or {}
        for k in [k for k in self._by_t if k < t_ns - QUALITY_KEEP_NS]:
            del self._by_t[k]
        return qual


def measurement(source: int, t_ns: int, T_base: np.ndarray, T_dev: np.ndarray,
                C_dev: np.ndarray | None, fixed: np.ndarray | None = None) -> Measurement:
    """The filter's measurement of one sample mapped into base; the covariance rotated by the chain's R_A.
    ``fixed``: the source's own diagonal covariance in base (``noise_std``, sources.py), used instead."""
    p, q = T_to_pq(T_base)
    C = fixed
    if C_dev is not None and fixed is None:
        RA = T_base[:3, :3] @ T_dev[:3, :3].T   # T_base = A T_dev -> R_A = R_base R_dev^T
        J = np.zeros((6, 6))
        J[0:3, 0:3] = J[3:6, 3:6] = RA
        C = J @ C_dev @ J.T
        C = 0.5 * (C + C.T)
    return Measurement(t_ns, source, p, q, C)


def model_measurements(config: TargetConfig, rot_stds: tuple[float, float], fixed_local: list[np.ndarray | None],
                       item: SyncItem, mg: Measurement | None, ml: Measurement | None, Tg: np.ndarray | None,
                       Tl: np.ndarray | None, eq: str, chain: FrameChain,
                       quality: dict[str, float]) -> list[Measurement]:
    """The item's measurements (``mg`` / ``ml`` from :func:`measurement`) with the model covariances.

    Global: a device covariance when one was pushed (already in base), else the OMC model (white part) from the
    sample's ``quality`` (:class:`OmcQualities`; defaults without) and the view margin at the body in the layout;
    ``extras`` carry the quality and ``sys_var``, the variance of the OMC's systematic position error here.
    Local: the device covariance or the Vega's distance model, mapped into base, plus the calibrated static
    link's covariance through the lever arm (``static`` chain with a T_base_ots that has one: calibrated, or the
    average that bridges until it is; else no link term).
    A source with ``noise_std`` or ``noise_model: std`` (sources.py) gets its diagonal instead of the model
    (orientation part: ``rot_stds``, :func:`~.target.rotation_stds`).
    """
    src, p = config.sources, config.params
    out = []
    if mg is not None:
        T_dev = item.glob.payload[0]
        C = mg.cov
        if C is None and src.glob.noise_model == "std":
            C = model_cov_std(src.glob, p.global_std, rot_stds[0])
        margin = None
        if C is None:
            lay = config.layout
            margin = margin_at(lay, T_dev[:3, 3])[0] if lay is not None else None
        # omc_systematic_var and omc_covariance's diagonal at once; rotate_diag_cov = rotate_cov of that diagonal
        vp, vr, sys_var = omc_variances(quality.get("fit_error"), margin, config.omc_model)
        if C is None:
            C = rotate_diag_cov(vp, vr, Tg[:3, :3] @ T_dev[:3, :3].T)   # R_A = R_base R_dev^T
        out.append(Measurement(mg.t_ns, SOURCE_GLOBAL, mg.p, mg.q, C, extras={**quality, "sys_var": sys_var[0]}))
    if ml is not None:
        T_dev, C_dev = item.local.payload[0], item.local.payload[1]
        spec = src.locals[item.source]
        if fixed_local[item.source] is not None or (spec.noise_model == "std" and C_dev is None):
            C = ml.cov if ml.cov is not None else model_cov_std(spec, p.local_std, rot_stds[1])
        else:
            A = Tl @ inv_T(T_dev)   # T_base_tool = A T_ots_tool: the whole chain in front of the tool
            est = chain.links.estimates.get("T_base_ots") if eq == "static" else None
            C = local_covariance(A, T_dev, None if est is None else est.cov, device_cov=C_dev)
        out.append(Measurement(ml.t_ns, SOURCE_LOCAL, ml.p, ml.q, C))
    return out
