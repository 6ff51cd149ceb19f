"""KF / BKF / CKF / CBKF in closed form per axis: the same filter as :class:`~.paper_family.FusionFilter`, ~5x cheaper.

The filter is separable per axis while no covariance couples two axes (:mod:`.paper_kernel`, which derives it and
holds the per-axis arithmetic, shared with the batched replay :mod:`.paper_batch`). This module is the per-sample
filter around that kernel: the :class:`~.api.Filter` protocol, the decision when the closed form applies, the
fall-back to the general form, and the :class:`~.api.Step` it returns.

When the closed form is used (decided per update, checked exactly, no tolerance):

* every measurement's R is diagonal: no covariance (fixed noise ``global_std^2 I`` / ``local_std^2 I``), or a
  covariance whose position block ``cov[:3, :3]`` has all six off-diagonal entries exactly 0 -- isotropic or
  anisotropic (a different variance per axis is still separable);
* and the state covariance has no cross-axis entry (always true unless an earlier update used a correlated R).

Otherwise (a correlated position block, e.g. a device covariance rotated into ``base``) the step falls back to
the general :class:`~.paper_family.FusionFilter`, the reference, and stays there while the state covariance couples
axes; it returns to the closed form as soon as the cross-axis entries are exactly 0 again (a reset). Results
agree with the general form to rounding (test_fast_filter.py: 1e-12 relative over thousands of random steps).

The :class:`AxisStep` it returns builds the full covariance only when asked: the pipeline reads the position
variances alone, and assembling the 9x9 array is a tenth of a closed-form step.
"""

from __future__ import annotations

import numpy as np

from fullperc_fusion.filters.api import (
    SOURCE_GLOBAL,
    SOURCE_LOCAL,
    Measurement,
    Step,
    StepCompat,
    predict_interval,
    split_update,
)
from fullperc_fusion.filters.paper_family import FILTER_KINDS, FilterParams, FusionFilter
from fullperc_fusion.filters.paper_kernel import axis_form, init_axes, initial_axes, predict_axes, update_axes

__all__ = ["AxisStep", "ClosedFormFilter", "separable_cov"]


def separable_cov(cov: np.ndarray | None) -> bool:
    """True when a measurement covariance keeps the axes independent: None, or a diagonal position block."""
    if cov is None:
        return True
    return cov[0, 1] == 0.0 and cov[0, 2] == 0.0 and cov[1, 2] == 0.0 and \
        cov[1, 0] == 0.0 and cov[2, 0] == 0.0 and cov[2, 1] == 0.0


class AxisStep(Step):
    """A :class:`Step` whose full covariance ``P`` is assembled from the per-axis blocks on first access: the
    pipeline reads only ``pos_cov`` (diagonal here), and building the 9x9 array is a tenth of a closed-form step.
    ``P`` behaves as on a Step (an ndarray, the covariance after this step; assigning replaces it)."""

    @property  # type: ignore[override]
    def P(self) -> np.ndarray:
        P = self.__dict__["_P"]
        if not isinstance(P, np.ndarray):
            P = self.__dict__["_P"] = P.full()
        return P

    @P.setter
    def P(self, value) -> None:
        self.__dict__["_P"] = value

    @property
    def pos_cov(self) -> np.ndarray:
        P = self.__dict__["_P"]
        return P[0:3, 0:3] if isinstance(P, np.ndarray) else np.diag(P.pos_var())


class _AxisCov:
    """The per-axis covariance blocks of one step (a snapshot: the filter replaces, never mutates, the blocks)."""

    __slots__ = ("blocks", "gather", "n")

    def __init__(self, blocks, gather: np.ndarray, n: int) -> None:
        self.blocks, self.gather, self.n = blocks, gather, n

    def full(self) -> np.ndarray:
        c0, c1, c2 = self.blocks
        return np.array(c0 + c1 + c2 + [0.0])[self.gather].reshape(self.n, self.n)

    def pos_var(self) -> list[float]:
        return [c[0] for c in self.blocks]


class ClosedFormFilter(StepCompat):
    """Drop-in for ``FusionFilter(kind, params)`` (same Filter protocol, attributes and Step fields).

    State in closed form: ``_X`` and ``_C`` in :mod:`.paper_kernel`'s layout, stepped by its functions with
    ``_form`` (the kind and its parameters). ``_ref`` is the general filter, which holds the state instead while the
    closed form does not apply.
    """

    def __init__(self, kind: str = "cbkf", params: FilterParams | None = None) -> None:
        if kind not in FILTER_KINDS:
            raise ValueError(f"filter kind '{kind}' is not one of {FILTER_KINDS}")
        self._ref = FusionFilter(kind, params)
        self.kind = kind
        self.params = self._ref.params
        self.has_bias = self._ref.has_bias
        self.biased = self._ref.biased
        self.n = self._ref.n
        self._form = axis_form(kind, self.params)
        k = 3 if self.has_bias else 2
        # gather index of the n x n general covariance from the 18 per-axis entries (+ one 0.0, index 18)
        sym = {(0, 0): 0, (0, 1): 1, (0, 2): 2, (1, 1): 3, (1, 2): 4, (2, 2): 5}
        self._gather = np.array([6 * (r % 3) + sym[min(r // 3, c // 3), max(r // 3, c // 3)] if r % 3 == c % 3 else 18
                                 for r in range(self.n) for c in range(self.n)])
        self._k = k
        self.reset()

    # ---- state ----------------------------------------------------------------------------------
    def reset(self) -> None:
        self._ref.reset()
        self._general = False
        self._X, self._C = initial_axes(self._form)
        self.t_ns: int | None = None
        self._pending_ns: int | None = None

    def snapshot(self) -> tuple:
        """The whole filter state, for rewind-and-replay (arrival.py): a few list copies, no deepcopy. The inner
        per-axis covariance lists are replaced, never mutated, by every step, so copying the outer lists suffices."""
        if self._general:
            return (True, self._ref.snapshot(), self.t_ns, self._pending_ns)
        return (False, self._X[:], self._C[:], self.t_ns, self._pending_ns)

    def restore(self, snap: tuple) -> None:
        """Back to a :meth:`snapshot` (it stays valid: it can be restored again)."""
        if snap[0]:
            self._general = True
            self._ref.restore(snap[1])
            self.t_ns, self._pending_ns = snap[2], snap[3]
        else:
            self._general = False
            self._X, self._C = snap[1][:], snap[2][:]
            self.t_ns, self._pending_ns = snap[3], snap[4]

    @property
    def initialized(self) -> bool:
        return (self._ref.t_ns if self._general else self.t_ns) is not None

    @property
    def time_ns(self) -> int | None:
        if self._general:
            return self._ref.time_ns
        return self._pending_ns if self._pending_ns is not None else self.t_ns

    @property
    def closed_form(self) -> bool:
        """True while the state is held in closed form (False: the general filter holds it)."""
        return not self._general

    @property
    def x(self) -> np.ndarray:
        return self._ref.x.copy() if self._general else np.array(self._X)

    @property
    def P(self) -> np.ndarray:
        return self._ref.P.copy() if self._general else self._full_P()

    @property
    def bias(self) -> np.ndarray:
        if self._general:
            return self._ref.bias
        return np.array(self._X[6:9]) if self.has_bias else np.zeros(3)

    def _full_P(self) -> np.ndarray:
        c0, c1, c2 = self._C
        return np.array(c0 + c1 + c2 + [0.0])[self._gather].reshape(self.n, self.n)

    def _cov_snapshot(self) -> _AxisCov:
        return _AxisCov(tuple(self._C), self._gather, self.n)

    def _to_general(self) -> None:
        r = self._ref
        r.x, r.P, r.t_ns, r._pending_ns = np.array(self._X), self._full_P(), self.t_ns, self._pending_ns
        self._general = True

    def _try_closed_form(self) -> None:
        """Back to the closed form when the general state covariance has no cross-axis entry left."""
        r = self._ref
        P = r.P
        k = self._k
        Pa = [P[a::3, a::3] for a in range(3)]
        off = P.copy()
        for a in range(3):
            off[a::3, a::3] = 0.0
        self.t_ns, self._pending_ns = r.t_ns, r._pending_ns
        if np.any(off != 0.0):
            return
        self._X = [float(v) for v in r.x]
        self._C = [[float(Pa[a][0, 0]), float(Pa[a][0, 1]), float(Pa[a][0, 2]) if k == 3 else 0.0,
                    float(Pa[a][1, 1]), float(Pa[a][1, 2]) if k == 3 else 0.0,
                    float(Pa[a][2, 2]) if k == 3 else 0.0] for a in range(3)]
        self._general = False

    # ---- predict (eq. 9-10) ---------------------------------------------------------------------
    def predict(self, t_ns: int) -> None:
        if self._general:
            try:
                self._ref.predict(t_ns)
            finally:
                self.t_ns, self._pending_ns = self._ref.t_ns, self._ref._pending_ns
            return
        t, dt = predict_interval(t_ns, self.t_ns, self._pending_ns, self.params.max_gap_s)
        if dt is None:
            self._pending_ns = t
            return
        predict_axes(self._form, self._X, self._C, dt)
        self.t_ns = t

    # ---- update (eq. 11-14) ---------------------------------------------------------------------
    def update(self, *measurements: Measurement) -> Step:
        mg, ml = split_update(self.kind, measurements)
        if self._general or not all(separable_cov(m.cov) for m in measurements):
            if not self._general:
                self._to_general()
            try:
                return self._ref.update(*measurements)
            finally:
                self._try_closed_form()
        t_new = max(m.t_ns for m in measurements)
        if self.time_ns is None or t_new > self.time_ns:
            self.predict(t_new)
        t = self.time_ns
        zg = None if mg is None else mg.p.tolist()
        zl = None if ml is None else ml.p.tolist()
        src = (SOURCE_GLOBAL if mg is not None else 0) | (SOURCE_LOCAL if ml is not None else 0)
        if self._pending_ns is not None:   # (re-)initialisation (paper_kernel.init_axes)
            dt = (t - self.t_ns) * 1e-9 if self.t_ns is not None else None
            self._X, self._C = init_axes(self._form, self._X, self._C, dt, zg, zl)
            self.t_ns, self._pending_ns = int(t), None
            return AxisStep(self.t_ns, np.array(self._X[0:3]), np.zeros(3), self.bias, self._cov_snapshot(), src,
                            reset=True)
        form = self._form
        tg = tl = rg = rl = None
        if mg is not None:
            tg, c = mg.t_ns, mg.cov
            rg = form.global_var if c is None else (float(c[0, 0]), float(c[1, 1]), float(c[2, 2]))
        if ml is not None:
            tl, c = ml.t_ns, ml.cov
            rl = form.local_var if c is None else (float(c[0, 0]), float(c[1, 1]), float(c[2, 2]))
        try:
            X, C, hop, nis, nis_g, innov, m = update_axes(form, self._X, self._C, t, tg, zg, rg, tl, zl, rl)
        except FloatingPointError:
            self.reset()
            raise FloatingPointError("filter produced a non-finite state; it was reset") from None
        self._X, self._C, self.t_ns = X, C, t
        xs = np.array(X)
        return AxisStep(t, xs[0:3], xs[3:6], xs[6:9] if self.has_bias else np.zeros(3), self._cov_snapshot(), src,
                        innovation=np.array(innov), nis=nis, nis_global=nis_g, hop=hop,
                        m=None if m is None else np.array(m))
