"""What an incomplete OMC calibration leaves of the real lenses: a focal-length and a radial-distortion residual.

The paper attributes its OMC error to "incomplete calibration, leading to distortions akin to those encountered in
camera imaging". A wand calibration estimates each camera's focal length and lens distortion from the wand samples
it saw; where the wand never went (under the table top, the image edges), those estimates are extrapolated, and
the errors are *common to all cameras*: the cameras are one lens type and one calibration procedure fits them the
same way. The simulator models what is left as a distortion of the image points, in normalised image coordinates
(x, y) = (X/Z, Y/Z) of each camera:

    (x, y)_real = (x, y)_believed * (1 + focal_scale) * (1 + k1 * (x^2 + y^2))

``focal_scale``: the real focal length is longer than the calibrated one by this share (the calibration cannot
tell a focal-length error from the camera's distance along its axis without wand samples near the image edges);
``k1``: the radial distortion the calibrated model does not remove (negative: barrel). The system back-projects
with its believed model, so each ray bends away from the marker by an angle that grows towards the image edge.

Because the residual is the same in every camera, the rays of all cameras that see a marker bend consistently: the
triangulated point moves smoothly with its position (a distortion of the reconstructed volume: raises the MAE of
the OMC chain in ``base`` without big frame-to-frame hops), and the hop when the set of seeing cameras changes
stays small; the per-camera extrinsic error (``omc.miscalibration``) supplies the hops. Both are zero for an
ideal system (``build_scene(..., miscalibration=False)``).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True)
class LensResidual:
    """Image-point residual of the believed lens model, common to all cameras (see the module docstring)."""

    focal_scale: float = 0.0  # real / believed focal length - 1
    k1: float = 0.0  # residual radial distortion coefficient in normalised image coordinates

    def distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where the real lens images a point the believed model puts at normalised (x, y)."""
        f = (1.0 + self.focal_scale) * (1.0 + self.k1 * (x * x + y * y))
        return x * f, y * f

    @property
    def is_zero(self) -> bool:
        return self.focal_scale == 0.0 and self.k1 == 0.0

    @classmethod
    def from_config(cls, section: Mapping[str, Any] | None) -> LensResidual | None:
        """From scene.yaml's ``omc.lens_residual`` (absent or all zero: None, the exact pinhole of earlier
        releases). Raises ValueError naming the field when a value is not a number or is implausible (|x| >= 0.1:
        a lens that far off would not pass any calibration)."""
        if not section:
            return None
        vals = {}
        for key in ("focal_scale", "k1"):
            try:
                vals[key] = float(section.get(key, 0.0))
            except (TypeError, ValueError) as e:
                raise ValueError(f"scene field 'omc.lens_residual.{key}': not a number: {section.get(key)!r}") from e
            if not abs(vals[key]) < 0.1:
                raise ValueError(f"scene field 'omc.lens_residual.{key}': {vals[key]} is not a residual (|x| < 0.1)")
        res = cls(**vals)
        return None if res.is_zero else res
