"""The collection of one calibration: sightings in, a :class:`~.se3_stats.Calibration` out.

:class:`Collector` buffers the sightings of the bodies its links need over a window of sensor time, then checks
every body's count and stillness (:func:`~.static_check.check_static`) and estimates the links (:mod:`.links`).
The node's live calibration (:mod:`.run`, ``frame_chain``'s calibrate mode) and the ``calibrate`` executable feed
one.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from fullperc_fusion.calibration.links import link_T_base_ots, link_T_omc_base, link_T_rig_ots
from fullperc_fusion.calibration.poses import BadSample, pose_to_T
from fullperc_fusion.calibration.se3_stats import (
    LINK_NAMES,
    Calibration,
    CalibrationBodies,
    CalibrationError,
    CalibrationSettings,
    LinkEstimate,
)
from fullperc_fusion.calibration.static_check import check_static


class Collector:
    """Accumulates timestamped sightings for ``duration_s`` and turns them into a :class:`Calibration`.

    Feed every pose with :meth:`add` (device 'omc' or 'ots'); sightings of other bodies are ignored. The
    window starts at ``start_ns`` or the first accepted stamp and holds stamps in [start, start + duration];
    :attr:`complete` turns true once a stamp at or beyond its end arrives. :meth:`finish` checks counts and
    stillness of every body it needs, then estimates ``links`` (T_rig_ots brings T_omc_base with it).
    """

    def __init__(self, links: Sequence[str] = ("T_omc_base", "T_base_ots"),
                 bodies: CalibrationBodies | None = None, duration_s: float = 10.0,
                 settings: CalibrationSettings | None = None, start_ns: int | None = None) -> None:
        bad = [x for x in links if x not in LINK_NAMES]
        if bad or not links:
            raise ValueError(f"links {list(links)}: each must be one of {LINK_NAMES}")
        if not duration_s > 0:
            raise ValueError(f"duration_s must be > 0, got {duration_s}")
        self.links = tuple(x for x in LINK_NAMES if x in links or (x == "T_omc_base" and "T_rig_ots" in links))
        self.bodies = bodies or CalibrationBodies()
        self.settings = settings or CalibrationSettings()
        self.duration_ns = int(round(duration_s * 1e9))
        self.start_ns = start_ns
        self.last_ns: int | None = None
        b = self.bodies
        need = {"T_omc_base": [("omc", b.omc_base)], "T_base_ots": [("ots", b.ots_base)],
                "T_rig_ots": [("omc", b.omc_rig), ("ots", b.ots_base)]}
        self._buf: dict[tuple[str, str], list[tuple[int, np.ndarray]]] = {}
        for ln in self.links:
            for key in need[ln]:
                self._buf.setdefault(key, [])
        self.n_bad: dict[tuple[str, str], int] = {k: 0 for k in self._buf}

    @staticmethod
    def label(device: str, body: str) -> str:
        return f"OMC body '{body}'" if device == "omc" else f"OTS tool '{body}'"

    @property
    def complete(self) -> bool:
        return self.start_ns is not None and self.last_ns is not None and \
            self.last_ns >= self.start_ns + self.duration_ns

    def counts(self) -> dict[str, int]:
        return {f"{d}:{b}": len(v) for (d, b), v in self._buf.items()}

    def add(self, device: str, body: str, stamp_ns: int, position, quat_xyzw=None) -> bool:
        """One sighting (position [m] + quaternion x y z w, or a 4x4 as ``position`` with ``quat_xyzw`` None);
        True when it was collected (a needed body, valid pose, inside the window)."""
        key = (device, body)
        if key not in self._buf:
            return False
        stamp_ns = int(stamp_ns)
        self.last_ns = stamp_ns if self.last_ns is None else max(self.last_ns, stamp_ns)
        try:
            T = pose_to_T(position if quat_xyzw is None else (position, quat_xyzw))
        except BadSample:
            self.n_bad[key] += 1
            return False
        if self.start_ns is None:
            self.start_ns = stamp_ns
        if not self.start_ns <= stamp_ns <= self.start_ns + self.duration_ns:
            return False
        self._buf[key].append((stamp_ns, T))
        return True

    def samples(self, device: str, body: str) -> tuple[np.ndarray, np.ndarray]:
        """(stamps [ns] (N,), poses (N, 4, 4)) collected of one body, in stamp order."""
        v = sorted(self._buf[(device, body)], key=lambda x: x[0])
        return np.array([s for s, _ in v], dtype=np.int64), np.array([T for _, T in v]).reshape(-1, 4, 4)

    def finish(self, stamp_ns: int | None = None, source: str = "") -> Calibration:
        """The calibration, or :class:`CalibrationError` listing every body that was too sparse or moved."""
        s = self.settings
        problems = []
        data = {}
        for key in self._buf:
            lab = self.label(*key)
            t, Ts = self.samples(*key)
            data[key] = (t, Ts)
            if len(t) < s.min_samples:
                bad = f", {self.n_bad[key]} invalid poses dropped" if self.n_bad[key] else ""
                problems.append(f"too few sightings of {lab}: {len(t)} in {self.duration_ns / 1e9:g} s{bad}, "
                                f"need >= {s.min_samples}")
                continue
            try:
                check_static(lab, t, Ts, s.static, s.alpha)
            except CalibrationError as e:
                problems.append(str(e))
        if problems:
            raise CalibrationError("calibration refused: " + "; ".join(problems))
        b = self.bodies
        out: dict[str, LinkEstimate] = {}
        try:
            if "T_omc_base" in self.links:
                out["T_omc_base"] = link_T_omc_base(data[("omc", b.omc_base)][1], s, self.label("omc", b.omc_base))
            if "T_base_ots" in self.links:
                out["T_base_ots"] = link_T_base_ots(data[("ots", b.ots_base)][1], s, self.label("ots", b.ots_base))
            if "T_rig_ots" in self.links:
                (tr, Tr), (to, To) = data[("omc", b.omc_rig)], data[("ots", b.ots_base)]
                out["T_rig_ots"] = link_T_rig_ots(tr, Tr, to, To, out["T_omc_base"], s,
                                                  self.label("omc", b.omc_rig), self.label("ots", b.ots_base))
        except CalibrationError as e:
            raise CalibrationError(f"calibration refused: {e}") from e
        first = min(int(t[0]) for t, _ in data.values())
        last = max(int(t[-1]) for t, _ in data.values())
        return Calibration(out, int(stamp_ns) if stamp_ns is not None else last, (last - first) / 1e9, source)
