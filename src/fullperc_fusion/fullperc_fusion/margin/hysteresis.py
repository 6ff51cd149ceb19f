"""Hysteresis for the BVV / GVV / PVV label of one target, so a label changes once per real boundary crossing.

Why: the label of a fused pose that moves along or across a region boundary flickers with the estimate's noise
(issue 14 item 9: 5 changes in 57 ms). Two mechanisms, each disabled by 0:

* **margin band** ``margin_band_deg`` [deg], for the GVV / PVV boundary (the margin varies continuously with the
  position between the jumps at which a camera pair becomes valid or invalid): a target labelled GVV stays GVV
  while ``margin >= threshold - band``; a target labelled PVV becomes GVV only at ``margin >= threshold + band``;
  otherwise (first label, or coming from BVV) the plain ``margin >= threshold``. The BVV test (inside the OTS
  volume with its line of sight) is a yes/no and has no band.
* **minimum dwell** ``min_dwell_s`` [s], for every boundary (the margin also *jumps* across the threshold, and
  the OTS volume is a yes/no): after a label change the label is held for at least ``min_dwell_s`` of pose
  stamps (the first label of a target is not a change and starts no hold). A change the labels ask for during
  the hold is made with the first pose at or after the end of the hold whose label (after the band) still
  differs. So the label follows the plain model with no delay except within ``min_dwell_s`` of its previous
  change: a real crossing is delayed by at most ``min_dwell_s`` (measured in pose stamps); noise that settles
  within ``min_dwell_s`` of a change causes that one change only; a target resting *on* a boundary changes label
  at most once per ``min_dwell_s``.

Time is the pose stamp [ns] (acquisition time), so a replayed bag gives the labels the live node gave. A stamp
earlier than the last change (a replay restarted) ends the hold.

Consistency of the published Region: :meth:`RegionFilter.update` returns the label together with the
:class:`~fullperc_fusion.margin.view_margin.PointLabel` that supports it and the threshold in force, so that in every
message BVV <=> the evidence is inside the OTS volume with line of sight, GVV <=> margin_deg >= threshold_deg,
PVV <=> margin_deg < threshold_deg. With the band the threshold in force is ``threshold -/+ band`` (above);
while a change is held back the evidence is that of the newest pose that had the held label (at most
``min_dwell_s`` old), not the current pose's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from fullperc_fusion.margin.view_margin import BVV, GVV, PVV, UNKNOWN, PointLabel


@dataclass(frozen=True)
class HysteresisParams:
    margin_band_deg: float = 1.0   # [deg] band around the GVV threshold; 0 = none
    min_dwell_s: float = 0.2       # [s] a label is held this long after a change; 0 = none

    def validate(self) -> HysteresisParams:
        for name in ("margin_band_deg", "min_dwell_s"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) or v < 0:
                raise ValueError(f"hysteresis parameter {name} must be finite and >= 0, got {v!r}")
        return self


@dataclass(frozen=True)
class Filtered:
    """The label to publish, the evidence it rests on and the threshold in force for it."""

    label: int
    evidence: PointLabel      # margin, pairs, cameras, OTS volume flags supporting ``label``
    threshold_deg: float      # GVV threshold in force (threshold -/+ band, see the module docstring)
    raw_label: int            # the plain model's label of the current pose (no hysteresis)
    changed: bool             # ``label`` differs from the previous update's
    held: bool                # the plain label (after the band) differs and the dwell holds it back


def _candidate(p: PointLabel, current: int, threshold_deg: float, band: float) -> tuple[int, float]:
    """Label of ``p`` with the band applied relative to the ``current`` label, and the threshold used."""
    thr = threshold_deg - band if current == GVV else threshold_deg + band if current == PVV else threshold_deg
    if p.label == BVV:
        return BVV, thr
    return (GVV if p.margin_deg >= thr else PVV), thr


class RegionFilter:
    """Hysteresis of one target's label; feed every labelled pose in stamp order."""

    def __init__(self, params: HysteresisParams | None = None) -> None:
        self.params = (params or HysteresisParams()).validate()
        self.label = UNKNOWN
        self._since_ns: int | None = None        # stamp of the last change
        self._evidence: tuple[PointLabel, float] | None = None   # newest pose that had ``label``
        self.raw_changes = 0                      # changes of the plain model's label
        self.changes = 0                          # changes of the published label (the first label is none)
        self._raw_prev = UNKNOWN

    def update(self, t_ns: int, p: PointLabel, threshold_deg: float) -> Filtered:
        prm = self.params
        if p.label != self._raw_prev:
            if self._raw_prev != UNKNOWN:
                self.raw_changes += 1
            self._raw_prev = p.label
        cand, thr = _candidate(p, self.label, threshold_deg, prm.margin_band_deg)
        if cand == self.label:
            self._evidence = (p, thr)
            return Filtered(self.label, p, thr, p.label, False, False)
        if self.label == UNKNOWN:            # the first label: nothing to hold, no hold started
            self.label = cand
            self._evidence = (p, thr)
            return Filtered(cand, p, thr, p.label, True, False)
        dwell_ns = int(round(prm.min_dwell_s * 1e9))
        if self._since_ns is None or t_ns < self._since_ns or t_ns - self._since_ns >= dwell_ns:
            self.label = cand
            self._since_ns = int(t_ns)
            self._evidence = (p, thr)
            self.changes += 1
            return Filtered(cand, p, thr, p.label, True, False)
        ev, ev_thr = self._evidence
        return Filtered(self.label, ev, ev_thr, p.label, False, True)

    def reset(self) -> None:
        """Forget the label (e.g. after the layout changed): the next pose is labelled without hysteresis."""
        self.label = UNKNOWN
        self._since_ns = None
        self._evidence = None
