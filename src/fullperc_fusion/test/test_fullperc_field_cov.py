"""The OMC's position error field in ``fullperc``'s output covariance (``bias_field_std`` s_f, ``bias_field_length``
L_f; :func:`fullperc_state.field_var`): with ``bias_length`` 0 (b kept as learnt) the published position covariance
adds 2 s_f^2 (1 - exp(-d / L_f)) per axis once the local source has lost the target, d the distance from where it
last saw it -- and nothing else changes:

* the rule itself: 0 while the local source sees the target (up to ``local_lost_s``), with the decay of b on, with
  s_f or L_f 0, before any local sample; the variogram's form at the current distance (back near the anchor, back
  near 0: the field is a function of where the target is);
* both forms on a stream where the Vega loses a moving tool: every estimate (p, v, b, q, innovation, NIS) and the
  filter's own state bit for bit those of s_f = 0, the output's P and pose_cov larger by exactly that variance on the
  position diagonal where lost and equal elsewhere; the IMM of ``motion: auto`` likewise.

test_fullperc_fast.py holds the fast form to the reference with the default parameters (the term acting).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from fullperc_common.testing import load_by_path
from fullperc_fusion.filters.fullperc import FullpercFilter
from fullperc_fusion.filters.fullperc_imm import FullpercImm
from fullperc_fusion.filters.fullperc_params import FullpercParams
from fullperc_fusion.filters.fullperc_reference import FullpercReference
from fullperc_fusion.filters.fullperc_state import field_var
from fullperc_fusion.filters.registry import make_filter

MS = 1_000_000
S = 1_000_000_000
_bd = load_by_path(Path(__file__).with_name("test_fullperc_bias_decay.py"), "_bias_decay_helpers")


def test_the_rule():
    pr = FullpercParams()
    assert (pr.bias_length, pr.bias_field_std, pr.bias_field_length) == (0.0, 0.341e-3, 0.296)   # spec's fit
    a, t_l = [0.0, 0.0, 0.5], 10 * S
    lost = t_l + int(pr.local_lost_s * S) + 1
    for d in (0.01, 0.1, 1.0, 10.0):
        want = 2.0 * pr.bias_field_std**2 * (1.0 - math.exp(-d / pr.bias_field_length))
        assert field_var(lost, t_l, [d, 0.0, 0.5], a, pr) == pytest.approx(want, rel=1e-12)
    assert field_var(lost, t_l, [10.0, 0.0, 0.5], a, pr) == pytest.approx(2 * pr.bias_field_std**2, rel=1e-6)
    assert field_var(lost, t_l, a, a, pr) == 0.0                         # back where it was learnt
    assert field_var(t_l + int(pr.local_lost_s * S), t_l, [1.0, 0.0, 0.5], a, pr) == 0.0   # not lost yet
    assert field_var(lost, None, [1.0, 0.0, 0.5], None, pr) == 0.0      # no local sample ever
    for off in (dict(bias_length=0.3), dict(bias_field_std=0.0), dict(bias_field_length=0.0)):
        assert field_var(lost, t_l, [1.0, 0.0, 0.5], a, FullpercParams(**off)) == 0.0, off
    with pytest.raises(ValueError, match="bias_field_length"):
        FullpercParams(bias_field_length=-1.0).validate()


def test_the_sill_is_at_least_what_the_learnt_bias_shows():
    """The sill is max(s_f^2, |b|^2 / 3): a learnt b of millimetres (a ``paper`` room) sets it, one smaller than the
    room's s_f leaves s_f^2; without b, s_f^2; switched off (s_f 0) it stays off whatever b is."""
    pr = FullpercParams()
    a, t_l = [0.0, 0.0, 0.5], 10 * S
    lost = t_l + int(pr.local_lost_s * S) + 1
    shape = 2.0 * (1.0 - math.exp(-0.1 / pr.bias_field_length))
    big, small = [3e-3, -2e-3, 1e-3], [1e-4, 0.0, -1e-4]
    assert field_var(lost, t_l, [0.1, 0.0, 0.5], a, pr, big) == pytest.approx(shape * 14e-6 / 3, rel=1e-12)
    assert field_var(lost, t_l, [0.1, 0.0, 0.5], a, pr, small) == pytest.approx(shape * pr.bias_field_std**2, rel=1e-12)
    assert field_var(lost, t_l, [0.1, 0.0, 0.5], a, pr) == pytest.approx(shape * pr.bias_field_std**2, rel=1e-12)
    assert field_var(lost, t_l, [0.1, 0.0, 0.5], a, FullpercParams(bias_field_std=0.0), big) == 0.0
    assert field_var(t_l, t_l, [0.1, 0.0, 0.5], a, pr, big) == 0.0   # the local source still sees it


@pytest.mark.parametrize("form", [FullpercReference, FullpercFilter])
def test_both_forms_add_the_sill_of_their_learnt_bias(form):
    """On the outage stream with s_f far below the learnt b, the output's added variance is the rule's with the
    filter's own b, anchor and stamp: each form passes its b."""
    items = _bd._outage_stream(7, 1200)
    pr = FullpercParams(bias_field_std=1e-6, bias_field_length=0.2)
    on, off = form(pr), form(FullpercParams(bias_field_std=0.0))
    x, y = _run(on, items)[-1], _run(off, items)[-1]
    st = on.s if form is FullpercReference else on.state
    assert float(st.b @ st.b) / 3 > 100 * pr.bias_field_std**2   # the learnt b sets the sill here
    want = field_var(x.t_ns, st.t_local_ns, st.p, st.rot_anchor, pr, st.b)
    assert want > 0.0 and x.P[0, 0] - y.P[0, 0] == pytest.approx(want, rel=1e-9)


def _run(f, items):
    out = []
    for ms in items:
        f.predict(max(m.t_ns for m in ms))
        out.append(f.update(*ms))
    return out


@pytest.mark.parametrize("form", [FullpercReference, FullpercFilter])
def test_only_the_output_covariance_changes_by_the_field_variance(form):
    items = _bd._outage_stream(7, 1200)
    on_pr, off_pr = FullpercParams(bias_field_std=1e-3, bias_field_length=0.2), FullpercParams(bias_field_std=0.0)
    on, off = form(on_pr), form(off_pr)
    a, b = _run(on, items), _run(off, items)
    grew = 0
    for ms, x, y in zip(items, a, b, strict=True):
        for k in ("p", "v", "b", "q", "innovation"):
            assert np.array_equal(getattr(x, k), getattr(y, k)), k
        assert (x.nis, x.nis_global, x.hop) == (y.nis, y.nis_global, y.hop)
        fv = np.diag(x.P)[0:3] - np.diag(y.P)[0:3]
        np.testing.assert_allclose(fv, fv[0], rtol=0, atol=1e-18)
        dP, dC = x.P - y.P, x.pose_cov - y.pose_cov
        dP[0:3, 0:3] -= fv[0] * np.eye(3)
        dC[0:3, 0:3] -= fv[0] * np.eye(3)
        assert np.abs(dP).max() <= 1e-18 and np.abs(dC).max() <= 1e-18
        if len(ms) == 2:
            assert fv[0] == 0.0   # the local source sees the tool: nothing added
        grew += fv[0] > 0.0
    assert grew > 200
    # the filter's own state is untouched: it goes on exactly as without the term
    sa = on.s if form is FullpercReference else on.state
    sb = off.s if form is FullpercReference else off.state
    assert np.array_equal(sa.P, sb.P) and np.array_equal(sa.p, sb.p) and np.array_equal(sa.b, sb.b)


def test_the_imm_of_motion_auto_outputs_the_term_and_the_same_estimates():
    items = _bd._outage_stream(3, 900)
    on = make_filter("fullperc", FullpercParams(motion="auto", bias_field_std=1e-3, bias_field_length=0.2))
    off = make_filter("fullperc", FullpercParams(motion="auto", bias_field_std=0.0))
    assert isinstance(on, FullpercImm)
    grew = 0
    for x, y in zip(_run(on, items), _run(off, items), strict=True):
        assert np.array_equal(x.p, y.p) and np.array_equal(x.q, y.q)
        d = x.pose_cov[0, 0] - y.pose_cov[0, 0]
        assert d >= -1e-18 and abs(x.pose_cov[3, 3] - y.pose_cov[3, 3]) <= 1e-18
        grew += d > 1e-12
    assert grew > 150
