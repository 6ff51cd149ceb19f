"""fk_many places only the frame asked for (forwardKinematics + updateFramePlacement, issue 38 item 5): the very
matrices of framesForwardKinematics row by row (fk / fk_tool), over the joint range and a tool offset."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from fullperc_drivers.diana_kinematics import DianaKinematics


def test_fk_many_is_frames_forward_kinematics_bit_for_bit():
    off = np.eye(4)
    off[:3, :3] = Rotation.from_euler("xyz", [0.3, 0.1, -0.7]).as_matrix()
    off[:3, 3] = [0.02, 0.01, 0.12]
    for kin in (DianaKinematics(), DianaKinematics(tool_offset=off)):
        rng = np.random.default_rng(5)
        lo, hi = kin.joint_limits
        Q = np.vstack([rng.uniform(lo, hi, size=(400, 7)), np.zeros((1, 7)), lo[None], hi[None]])
        flange, tool = kin.fk_many(Q), kin.fk_many(Q, tool=True)
        assert flange.tobytes() == np.stack([kin.fk(q) for q in Q]).tobytes()
        assert tool.tobytes() == np.stack([kin.fk_tool(q) for q in Q]).tobytes()
        # fk after fk_many (which leaves the other frames as they were) is still framesForwardKinematics'
        assert kin.fk(Q[3]).tobytes() == flange[3].tobytes()
