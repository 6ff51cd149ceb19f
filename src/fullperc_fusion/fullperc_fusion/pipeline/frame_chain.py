"""Frame chain of the paper's eq. (1) and (2): every measurement of a target expressed in ``base``.

Notation as in ``fullperc_common.transforms``: ``T_a_b`` maps points from frame b into frame a.

* Global (OMC) measurement:   T_base_tool = inv(T_omc_base) · T_omc_tool
* Local (OTS) measurement, eq. (1):
      T_base_tool = inv(T_omc_base) · T_omc_rig · T_rig_ots · T_ots_tool
  where ``rig`` is the OMC body rigidly attached to the OTS (the paper's {Robot}); or eq. (2), when the
  OTS sees the base marker in the same frame:  T_base_tool = inv(T_ots_base) · T_ots_tool.

Static links are not measured live, because every live factor adds its own noise and hops to the
measurement: the base marker is fixed, so T_omc_base is the average of the OMC's base observations at
initialization; T_rig_ots (eq. 1; hand-eye calibration in the paper) is given or estimated from
simultaneous observations of the base marker by both systems; with a stationary OTS (a Vega on a
stand), the whole local prefix collapses to one static T_base_ots. Averages of rotations use
``mean_T`` (the chordal L2 mean), never a component-wise average of matrix entries or quaternions.

The bodies must be stationary while the links are being estimated (the paper's initialization:
"both positioning systems could see the target and the marker representing the global coordinate
system"); :class:`StaticLinks` can be re-estimated on request (``fusion_node``'s ``~/initialize``).

How the static links are estimated: :mod:`fullperc_fusion.calibration.static_links`.

Local chain modes (``local_chain``):
  * ``static``  (default) T_base_ots fixed: given, or from eq. (2) averages (OTS sees base), or eq. (1)
                averages with a given T_rig_ots. Right for an OTS on a stand.
  * ``tracked`` eq. (1) with the live OMC pose of the rig (nearest in time) and a static T_rig_ots.
                Right for an OTS on a moving arm.
  * ``direct``  eq. (2) live whenever the OTS saw the base marker in the same frame, else ``static``.
"""

from __future__ import annotations

import bisect
from collections import deque

import numpy as np

from fullperc_common.transforms import inv_T
from fullperc_fusion.calibration.poses import BadSample, pose_to_T
from fullperc_fusion.calibration.static_links import (
    LOCAL_CHAINS,
    STATIC_LINK_MODES,
    ChainConfig,
    StaticLinks,
    links_needed,
)

__all__ = ["LOCAL_CHAINS", "STATIC_LINK_MODES", "BadSample", "ChainConfig", "FrameChain", "StaticLinks",
           "links_needed", "pose_to_T"]


class _Recent:
    """Last few stamped poses of one body, for nearest-in-time lookup."""

    def __init__(self, maxlen: int = 256) -> None:
        self.t: deque[int] = deque(maxlen=maxlen)
        self.T: deque[np.ndarray] = deque(maxlen=maxlen)

    def add(self, t_ns: int, T: np.ndarray) -> None:
        if self.t and t_ns < self.t[-1]:
            ts = list(self.t)
            i = bisect.bisect_right(ts, t_ns)
            if i == 0 and len(self.t) == self.t.maxlen:
                return  # older than everything kept
            Ts = list(self.T)
            ts.insert(i, t_ns)
            Ts.insert(i, T)
            self.t.clear()
            self.T.clear()
            self.t.extend(ts)
            self.T.extend(Ts)
            return
        self.t.append(t_ns)
        self.T.append(T)

    def nearest(self, t_ns: int, max_age_ns: int) -> np.ndarray | None:
        if not self.t:
            return None
        ts = self.t   # bisect on the deque itself: copying 256 stamps to a list per lookup cost more than the rest
        i = bisect.bisect_left(ts, t_ns)
        best = None
        for j in (i - 1, i):
            if 0 <= j < len(ts) and abs(ts[j] - t_ns) <= max_age_ns and (
                    best is None or abs(ts[j] - t_ns) < abs(ts[best] - t_ns)):
                best = j
        return None if best is None else self.T[best]


class FrameChain:
    """Turns raw device poses of one target into global and local measurements in ``base``.

    Feed every device pose through :meth:`observe_omc` / :meth:`observe_ots` (they collect the
    initialization averages and the live rig / base poses the chain needs), then call
    :meth:`global_T` / :meth:`local_T` for target samples. Both return None with a reason in
    :attr:`why_not` when the measurement cannot be formed yet.
    """

    def __init__(self, cfg: ChainConfig) -> None:
        self.cfg = cfg
        self.links = StaticLinks(cfg)
        self._rig = _Recent()
        self._ots_base = _Recent()
        self.why_not = ""
        self._inv_src: np.ndarray | None = None   # the T_omc_base whose inverse is cached (kept: no id reuse)
        self._inv: np.ndarray | None = None

    def _inv_omc_base(self, T_omc_base: np.ndarray) -> np.ndarray:
        """inv(T_omc_base), computed once per link estimate instead of once per sample (issue 16: per-sample
        cost). Links are replaced, never modified in place (StaticLinks sets new arrays; arrival.py's link views
        rely on the same), so the identity of the array names its value."""
        if T_omc_base is not self._inv_src:
            self._inv_src, self._inv = T_omc_base, inv_T(T_omc_base)
        return self._inv

    def reinitialize(self, mode: str | None = None) -> None:
        """Re-estimate the static links (``mode``: average | calibrate, default the configured one)."""
        self.links.start(mode)

    def observe_omc(self, body: str, t_ns: int, T: np.ndarray) -> None:
        if body == self.cfg.omc_base:
            self.links.add("omc_base", T, t_ns)
        if body == self.cfg.omc_rig:
            self.links.add("omc_rig", T, t_ns)
            self._rig.add(t_ns, T)

    def observe_ots(self, tool: str, t_ns: int, T: np.ndarray) -> None:
        if tool == self.cfg.ots_base:
            self.links.add("ots_base", T, t_ns)
            self._ots_base.add(t_ns, T)

    def global_T(self, T_omc_tool: np.ndarray) -> np.ndarray | None:
        """inv(T_omc_base) · T_omc_tool, or None before T_omc_base is known."""
        if self.links.T_omc_base is None:
            self.why_not = "global link T_omc_base not initialised yet"
            return None
        return self._inv_omc_base(self.links.T_omc_base) @ T_omc_tool

    def local_T(self, t_ns: int, T_ots_tool: np.ndarray) -> tuple[np.ndarray | None, str]:
        """Local measurement in base and the equation used ('eq1', 'eq2', 'static'), or (None, '')."""
        L = self.links
        mode = self.cfg.local_chain
        if mode == "direct":
            T_ots_base = self._ots_base.nearest(t_ns, 0)  # same OTS frame: identical stamp
            if T_ots_base is not None:
                return inv_T(T_ots_base) @ T_ots_tool, "eq2"
        if mode == "tracked":
            if L.T_omc_base is None or L.T_rig_ots is None:
                self.why_not = "local link T_rig_ots not initialised yet"
                return None, ""
            T_omc_rig = self._rig.nearest(t_ns, self.cfg.rig_max_age_ns)
            if T_omc_rig is None:
                self.why_not = f"no OMC pose of '{self.cfg.omc_rig}' within {self.cfg.rig_max_age_ns / 1e6:g} ms"
                return None, ""
            return self._inv_omc_base(L.T_omc_base) @ T_omc_rig @ L.T_rig_ots @ T_ots_tool, "eq1"
        if L.T_base_ots is None:
            self.why_not = "local link T_base_ots not initialised yet"
            return None, ""
        return L.T_base_ots @ T_ots_tool, "static"
