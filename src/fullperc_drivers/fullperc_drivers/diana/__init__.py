"""Agile Robots Diana 7 arm state: vendor DianaApi (ctypes) and simulator-stream backends.

Both backends produce :class:`JointSample` (SI units, host-clock stamp); the node turns them into
``/diana/joint_states`` and, through :mod:`fullperc_drivers.diana_kinematics`, the flange/tool poses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class JointSample:
    stamp_ns: int  # acquisition time on the host clock
    q: np.ndarray  # (7,) rad
    dq: np.ndarray | None = None  # (7,) rad/s, when the backend has it
    sequence: int = -1
    vendor_tcp: np.ndarray | None = None  # (6,) x y z [m] + rotation vector [rad] from the controller, if read
