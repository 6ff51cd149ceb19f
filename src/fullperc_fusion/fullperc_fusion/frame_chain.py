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
from dataclasses import dataclass

import numpy as np

from fullperc_common.transforms import inv_T, make_T, mean_T

LOCAL_CHAINS = ("static", "tracked", "direct")


class BadSample(ValueError):
    """A pose that cannot be used (non-finite, non-unit quaternion, not a rotation)."""


def pose_to_T(pose, unit_tol: float = 1e-2) -> np.ndarray:
    """A validated 4x4 transform from a 4x4 array or a (p, q_xyzw) pair; raises :class:`BadSample`.

    Quaternions within ``unit_tol`` of unit norm are renormalised (drivers round to float32);
    anything further off is rejected rather than silently normalised, since it signals a corrupt
    sample, not rounding.
    """
    if isinstance(pose, tuple | list) and len(pose) == 2:
        p = np.asarray(pose[0], dtype=float)
        q = np.asarray(pose[1], dtype=float)
        if p.shape != (3,) or q.shape != (4,):
            raise BadSample(f"pose has shapes {p.shape}, {q.shape}; expected (3,), (4,)")
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
            raise BadSample("non-finite pose (NaN/inf)")
        n = float(np.linalg.norm(q))
        if abs(n - 1.0) > unit_tol:
            raise BadSample(f"non-unit quaternion (norm {n:.4g})")
        return make_T(p, q / n)
    T = np.asarray(pose, dtype=float)
    if T.shape != (4, 4):
        raise BadSample(f"transform has shape {T.shape}; expected (4, 4)")
    if not np.all(np.isfinite(T)):
        raise BadSample("non-finite pose (NaN/inf)")
    R = T[:3, :3]
    if np.max(np.abs(R.T @ R - np.eye(3))) > unit_tol or np.linalg.det(R) < 0:
        raise BadSample("rotation block is not a rotation")
    if np.any(T[3] != [0.0, 0.0, 0.0, 1.0]):
        raise BadSample("last row of transform is not [0 0 0 1]")
    return T


@dataclass
class ChainConfig:
    """Which device bodies make up one target's chain (names as on the driver topics)."""

    omc_target: str = "tool"        # OMC rigid body of the target -> global measurement
    ots_target: str = "tool"        # OTS tool of the target -> local measurement
    omc_base: str = "base"          # OMC body of the global reference marker
    omc_rig: str = "ots_rig"        # OMC body rigidly attached to the OTS (paper's {Robot})
    ots_base: str = "base"          # OTS tool on the global reference marker (eq. 2)
    local_chain: str = "static"     # static | tracked | direct (module docstring)
    init_samples: int = 30          # samples of each body averaged per static link
    T_rig_ots: np.ndarray | None = None   # given hand-eye calibration (eq. 1), else estimated
    T_base_ots: np.ndarray | None = None  # given calibration of a stationary OTS, else estimated
    rig_max_age_ns: int = 20_000_000      # tracked mode: rig pose must be this close in time

    def __post_init__(self) -> None:
        if self.local_chain not in LOCAL_CHAINS:
            raise ValueError(f"local_chain '{self.local_chain}' is not one of {LOCAL_CHAINS}")
        if int(self.init_samples) < 1:
            raise ValueError(f"init_samples must be >= 1, got {self.init_samples}")
        for name in ("T_rig_ots", "T_base_ots"):
            v = getattr(self, name)
            if v is not None:
                setattr(self, name, pose_to_T(v))


class StaticLinks:
    """Collects stationary observations and averages them into the chain's static links.

    ``T_omc_base`` is needed by the global path and is ready after ``init_samples`` OMC base
    samples; the local link (``T_base_ots`` and, for ``tracked``, ``T_rig_ots``) becomes ready
    independently, so global fusion starts even while the OTS cannot see the base marker yet.
    While a re-estimation is running the previous links stay in use.
    """

    def __init__(self, cfg: ChainConfig) -> None:
        self.cfg = cfg
        self.T_omc_base: np.ndarray | None = None
        self.T_base_ots: np.ndarray | None = cfg.T_base_ots
        self.T_rig_ots: np.ndarray | None = cfg.T_rig_ots
        self.generation = 0  # bumps each time a link is (re-)estimated
        self._collect: dict[str, list[np.ndarray]] | None = None
        self.start()

    def start(self) -> None:
        """(Re-)start collecting; previous links remain valid until the new ones are computed."""
        self._collect = {"omc_base": [], "omc_rig": [], "ots_base": []}
        self._need_global = True
        self._need_local = self.cfg.T_base_ots is None or self.cfg.local_chain == "tracked"
        if self.cfg.local_chain == "tracked" and self.cfg.T_rig_ots is not None:
            self._need_local = False

    @property
    def collecting(self) -> bool:
        return self._need_global or self._need_local

    @property
    def global_ready(self) -> bool:
        return self.T_omc_base is not None

    @property
    def local_ready(self) -> bool:
        if self.cfg.local_chain == "tracked":
            return self.T_omc_base is not None and self.T_rig_ots is not None
        return self.T_base_ots is not None

    def progress(self) -> dict[str, int]:
        c = self._collect or {}
        return {k: len(v) for k, v in c.items()}

    def add(self, which: str, T: np.ndarray) -> bool:
        """Feed one observation ('omc_base', 'omc_rig' or 'ots_base'); True when a link was updated."""
        if not self.collecting or self._collect is None:
            return False
        n = int(self.cfg.init_samples)
        buf = self._collect[which]
        if len(buf) < n:
            buf.append(T)
        return self._try_finish(n)

    def _try_finish(self, n: int) -> bool:
        c = self._collect
        assert c is not None
        changed = False
        if self._need_global and len(c["omc_base"]) >= n:
            self.T_omc_base = mean_T(c["omc_base"])
            self._need_global = False
            changed = True
        if self._need_local and not self._need_global:
            T_omc_base = self.T_omc_base
            assert T_omc_base is not None
            given_rig = self.cfg.T_rig_ots
            if self.cfg.local_chain == "tracked":
                # T_rig_ots = inv(T_omc_rig) T_omc_base inv(T_ots_base): both systems see the base marker.
                if len(c["omc_rig"]) >= n and len(c["ots_base"]) >= n:
                    T_base_ots = mean_T([inv_T(T) for T in c["ots_base"]])
                    self.T_rig_ots = inv_T(mean_T(c["omc_rig"])) @ T_omc_base @ T_base_ots
                    self.T_base_ots = T_base_ots
                    self._need_local = False
                    changed = True
            elif len(c["ots_base"]) >= n:
                # eq. (2) averaged: the OTS sees the base marker directly.
                self.T_base_ots = mean_T([inv_T(T) for T in c["ots_base"]])
                self._need_local = False
                changed = True
            elif given_rig is not None and len(c["omc_rig"]) >= n:
                # eq. (1) averaged with the hand-eye calibration T_rig_ots.
                self.T_base_ots = inv_T(T_omc_base) @ mean_T(c["omc_rig"]) @ given_rig
                self._need_local = False
                changed = True
        if changed:
            self.generation += 1
        return changed


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
        ts = list(self.t)
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

    def reinitialize(self) -> None:
        self.links.start()

    def observe_omc(self, body: str, t_ns: int, T: np.ndarray) -> None:
        if body == self.cfg.omc_base:
            self.links.add("omc_base", T)
        if body == self.cfg.omc_rig:
            self.links.add("omc_rig", T)
            self._rig.add(t_ns, T)

    def observe_ots(self, tool: str, t_ns: int, T: np.ndarray) -> None:
        if tool == self.cfg.ots_base:
            self.links.add("ots_base", T)
            self._ots_base.add(t_ns, T)

    def global_T(self, T_omc_tool: np.ndarray) -> np.ndarray | None:
        """inv(T_omc_base) · T_omc_tool, or None before T_omc_base is known."""
        if self.links.T_omc_base is None:
            self.why_not = "global link T_omc_base not initialised yet"
            return None
        return inv_T(self.links.T_omc_base) @ T_omc_tool

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
            return inv_T(L.T_omc_base) @ T_omc_rig @ L.T_rig_ots @ T_ots_tool, "eq1"
        if L.T_base_ots is None:
            self.why_not = "local link T_base_ots not initialised yet"
            return None, ""
        return L.T_base_ots @ T_ots_tool, "static"
