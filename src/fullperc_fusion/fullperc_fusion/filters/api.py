"""The filter seam: what every fusion filter implements, and the measurement it is fed (issue 18, fusion-v2).

A filter is anything that satisfies :class:`Filter` -- ``predict(t_ns)`` to move its state to a stamp and
``update(*measurements)`` to fuse one or more :class:`Measurement` taken at or before that stamp -- and is
registered by name in :mod:`filter_registry`. ``TargetPipeline`` drives every filter through exactly these
calls; nothing else of a filter is used but :attr:`Filter.kind` and :meth:`Filter.reset`.

Measurement contract (SI units, integer-nanosecond stamps, everything in ``base``):

* ``p`` position [m], ``q`` orientation quaternion x y z w (optional; the paper's filters fuse position only).
* ``cov`` the 6x6 pose covariance in ROS order [x y z, rx ry rz]: the position block in ``base`` axes [m^2];
  the rotation part is a small rotation vector [rad] about the axes of ``base`` (the parent frame of the pose),
  i.e. R_true = exp([dtheta]x) R_est -- the convention of geometry_msgs/PoseWithCovariance, whose rotation
  entries are "about the fixed X, Y, Z axes" of header.frame_id. ``None``: the filter's fixed noise applies.
* ``cov`` must be finite, symmetric (to 1e-9 of its largest entry) and positive definite, all six dimensions --
  "unknown orientation" is a large rotation variance, not a zero one. :func:`check_covariance` is the one check;
  the pipeline runs it at the input so a bad covariance is rejected and counted like any other bad sample, and
  :class:`Measurement` runs it again so a direct caller cannot feed one either (:class:`BadMeasurement`).
* ``extras`` free-form per-source quality numbers (e.g. OMC fit error, marker count) for filters that model
  them; the paper's filters ignore them.

The paper's KF / BKF / CKF / CBKF (:mod:`filters`) use the position block only: their R for a measurement is
``cov[:3, :3]``, or ``FilterParams.global_std**2 I`` / ``local_std**2 I`` when ``cov`` is None, which is what
they did before the seam existed, so default results are bit-identical.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum
from typing import Protocol, runtime_checkable

import numpy as np
from scipy.linalg.lapack import dpotrf as _dpotrf


class Role(IntEnum):
    """What a measurement source is to the filters: THE global one (drift-free room frame; the filters carry one
    bias state for it) or a local one. The one definition of the three encodings that name a role:

    * ``int(role)`` -- the synchronizer stream index (``pipeline.synchronizer.GLOBAL`` / ``LOCAL``);
    * :attr:`bit` = 1 << index -- :attr:`Measurement.source` and :attr:`Step.sources` (:data:`SOURCE_GLOBAL`,
      :data:`SOURCE_LOCAL`), on the wire fullperc_msgs/FusionStatus ``SOURCE_GLOBAL`` = 1 / ``SOURCE_LOCAL`` = 2;
    * :attr:`label` -- the text: a source's ``role:`` in the params (``pipeline.sources``), the synchronizer's
      stream names and the keys of ``fusion_health``'s per-source state.
    """

    GLOBAL = 0
    LOCAL = 1

    @property
    def bit(self) -> int:
        return 1 << int(self)

    @property
    def label(self) -> str:
        return self.name.lower()


SOURCE_GLOBAL = Role.GLOBAL.bit   # 1: the bit values of fullperc_msgs/FusionStatus
SOURCE_LOCAL = Role.LOCAL.bit     # 2
ROLE_LABELS = tuple(r.label for r in Role)   # ("global", "local"), in stream order

SYMMETRY_RTOL = 1e-9   # |C - C^T| allowed, relative to the largest |C_ij|


class BadMeasurement(ValueError):
    """A measurement that must not be fused; the message says why (used as the rejection reason)."""


def check_covariance(cov) -> np.ndarray:
    """The covariance as a (6, 6) float array, or BadMeasurement naming what is wrong with it."""
    try:
        C = np.array(cov, dtype=float)
    except (TypeError, ValueError) as e:
        raise BadMeasurement(f"covariance is not a numeric array ({e})") from None
    if C.shape != (6, 6):
        if C.size == 36:
            C = C.reshape(6, 6)   # the row-major 36-vector of geometry_msgs/PoseWithCovariance
        else:
            raise BadMeasurement(f"covariance must be 6x6 (or 36 values), got shape {C.shape}")
    # ndarray methods: the same reductions as np.all / np.max without their Python dispatch (~1.5 us each; this
    # runs for every model measurement of a per-sample replay)
    if not np.isfinite(C).all():
        raise BadMeasurement("non-finite covariance")
    scale = float(np.abs(C).max())
    if float(np.abs(C - C.T).max()) > SYMMETRY_RTOL * scale:
        raise BadMeasurement("covariance not symmetric")
    # LAPACK's Cholesky itself (np.linalg.cholesky's ~5 us of wrapper less): info > 0 = not positive definite
    if _dpotrf(0.5 * (C + C.T), lower=1, clean=0)[1] != 0:
        raise BadMeasurement("covariance not positive definite")
    return C


def predict_interval(t_ns: int, state_ns: int | None, pending_ns: int | None,
                     max_gap_s: float) -> tuple[int, float | None]:
    """``(t, dt)`` of ``predict(t_ns)``, the time rule every filter shares (:class:`Filter`).

    ``dt`` [s] from the state's stamp ``state_ns`` to ``t``, or None when there is nothing to predict from -- no
    state yet, a (re-)initialisation pending at ``pending_ns``, or a gap longer than ``max_gap_s`` -- and the
    caller records ``t`` as its pending stamp. ValueError when ``t`` is before the filter's time (the pending stamp
    if there is one, else the state's).
    """
    t = int(t_ns)
    now = pending_ns if pending_ns is not None else state_ns
    if now is None:
        return t, None
    if t < now:
        raise ValueError(f"time went backwards by {(now - t) * 1e-9:.6f} s (filter at {now}, sample at {t})")
    if pending_ns is not None:
        return t, None
    dt = (t - state_ns) * 1e-9
    return t, (None if dt > max_gap_s else dt)


@dataclass
class Step:
    """Result of one filter update (one synchronizer item), in ``base``, SI units."""

    t_ns: int
    p: np.ndarray
    v: np.ndarray
    b: np.ndarray                  # zeros for kinds without a bias state
    P: np.ndarray                  # full state covariance after the step (its [0:3, 0:3] is the position block)
    sources: int                   # SOURCE_GLOBAL | SOURCE_LOCAL bits used
    innovation: np.ndarray = field(default_factory=lambda: np.zeros(3))  # global rows if any, else local
    nis: float = 0.0               # NIS of the whole (stacked) update, dof = rows of H
    nis_global: float = 0.0        # NIS of the global rows alone (the hop test)
    log_lik: float = 0.0           # log N(y; 0, S) of the whole update, before a hop raises S (fullperc, when asked:
                                   #   its ``likelihood`` flag; the model weights of motion: auto, fullperc_imm.py)
    hop: bool = False
    reset: bool = False            # this sample (re-)initialised the state; no update was made
    m: np.ndarray | None = None    # diagonal of M (biased kinds)
    q: np.ndarray | None = None    # fused orientation x y z w, for filters that estimate it (fullperc); else None
    pose_cov: np.ndarray | None = None   # its 6x6 pose covariance [x y z, rx ry rz] (module docstring), with q

    @property
    def pos_cov(self) -> np.ndarray:
        return self.P[0:3, 0:3]


@dataclass(slots=True)
class Measurement:
    """One sample for a filter, in ``base``; see the module docstring for units and the covariance convention."""

    t_ns: int                          # acquisition stamp [ns]
    source: int                        # SOURCE_GLOBAL or SOURCE_LOCAL
    p: np.ndarray                      # (3,) position [m]
    q: np.ndarray | None = None        # (4,) orientation x y z w
    cov: np.ndarray | None = None      # (6, 6) pose covariance [m^2, rad^2], or None: the filter's fixed noise
    extras: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.source not in (SOURCE_GLOBAL, SOURCE_LOCAL):
            raise BadMeasurement(f"source must be SOURCE_GLOBAL (1) or SOURCE_LOCAL (2), got {self.source!r}")
        if self.t_ns is None:
            raise BadMeasurement("every sample needs its stamp")
        self.t_ns = int(self.t_ns)
        p = np.asarray(self.p, dtype=float).reshape(3)
        if not np.isfinite(p).all():
            raise BadMeasurement("non-finite measurement")
        self.p = p
        if self.q is not None:
            self.q = np.asarray(self.q, dtype=float).reshape(4)
        if self.cov is not None:
            self.cov = check_covariance(self.cov)


def measurements_from_samples(z_global=None, t_global=None, z_local=None, t_local=None,
                              cov_global=None, cov_local=None) -> list[Measurement]:
    """The measurements of one synchronised item, global first (the row order of the stacked update)."""
    if z_global is None and z_local is None:
        raise ValueError("step needs a global or a local sample")
    if z_global is not None and t_global is None or z_local is not None and t_local is None:
        raise ValueError("every sample needs its stamp")
    ms = []
    if z_global is not None:
        ms.append(Measurement(t_global, SOURCE_GLOBAL, z_global, cov=cov_global))
    if z_local is not None:
        ms.append(Measurement(t_local, SOURCE_LOCAL, z_local, cov=cov_local))
    return ms


def split_update(kind: str, measurements) -> tuple[Measurement | None, Measurement | None]:
    """``(global, local)`` of one update's measurements: at most one of each source, at least one in all."""
    mg = ml = None
    for m in measurements:
        if m.source == SOURCE_GLOBAL and mg is None:
            mg = m
        elif m.source == SOURCE_LOCAL and ml is None:
            ml = m
        else:
            raise ValueError(f"filter {kind} takes at most one global and one local measurement per update")
    if mg is None and ml is None:
        raise ValueError("update needs a global or a local measurement")
    return mg, ml


@dataclass(frozen=True)
class Capabilities:
    """What a filter supports, declared in its registry entry (:class:`~.registry.FilterSpec`), never guessed from
    its attributes: the pipeline, the evaluator and the node configuration read these flags, nothing else.

    * ``models``: for every sample without a device covariance the pipeline computes the model covariance of
      :mod:`~.measurement_models` (OMC quality and view margin, Vega distance, calibrated link) and passes it in
      :attr:`Measurement.cov`, and tells the filter the local chain's frame (``express_in(T_frame, local)``, which
      such a filter must have); filters without it get ``cov=None`` and use their fixed noise.
    * ``orientation``: its :class:`Step` carries a fused orientation (``q``, ``pose_cov``); the pipeline outputs it
      instead of copying a source's.
    * ``snapshot``: ``snapshot()`` returns the whole state as a value and ``restore(snap)`` puts it back (rewind and
      replay on arrival). Every registered filter must have it; the flag states it for checks and documentation.
    * ``batch``: :func:`~.paper_batch.run_closed_form` replays it in one loop on arrays (offline evaluation).
    """

    models: bool = False
    orientation: bool = False
    snapshot: bool = True
    batch: bool = False


@runtime_checkable
class Filter(Protocol):
    """What the pipeline needs of a filter. Register an implementation in :mod:`~.registry`.

    What it supports beyond this (model covariances, orientation, batch replay) its registry entry declares in
    :class:`Capabilities`.

    * ``predict(t_ns)``: move the state to ``t_ns`` (non-decreasing; ValueError when time goes backwards).
      On a filter that has no state yet, or after a gap it does not bridge, it only records the stamp.
    * ``update(*measurements)``: fuse the measurements -- one, or a synchronised pair, global first -- in one
      step at the filter's time (each stamp <= it; an older one is a lagged measurement). It predicts to the
      newest stamp first if that is ahead. Returns the :class:`Step`, or None when the filter has
      nothing to say about these measurements (``omc`` given a local sample only). Raises ValueError
      (BadMeasurement included) for input it refuses, without fusing it.
    * ``reset()``: forget the state.
    * ``snapshot()`` / ``restore(snap)``: the whole state as a value, and back (rewind and replay on arrival).
    """

    kind: str

    def reset(self) -> None: ...

    def predict(self, t_ns: int) -> None: ...

    def update(self, *measurements: Measurement) -> Step | None: ...

    def snapshot(self) -> object: ...

    def restore(self, snap: object) -> None: ...


class StepCompat:
    """``step(z_global, t_global, z_local, t_local)`` -- the pre-seam call -- as predict + update."""

    def step(self, z_global=None, t_global: int | None = None, z_local=None, t_local: int | None = None,
             cov_global=None, cov_local=None) -> Step | None:
        ms = measurements_from_samples(z_global, t_global, z_local, t_local, cov_global, cov_local)
        self.predict(max(m.t_ns for m in ms))   # type: ignore[attr-defined]
        return self.update(*ms)                  # type: ignore[attr-defined]
