"""The Intel RealSense D455's stereo constants and depth-noise model: one home for the
reconstruction's wall test, the live map's weights and its coverage check."""

from __future__ import annotations

import numpy as np

BASELINE_M = 0.095  # stereo baseline
SUBPIXEL_PX = 0.08  # disparity RMS of block matching on an ideal target
# share of the noise variance common to pixels a few apart (the blobs a block matcher makes):
# averaging more points of one frame does not take it down
CORRELATED_SHARE = 0.5


def depth_rms_m(depth_m: np.ndarray | float, focal_px: float, factor: float = 1.0) -> np.ndarray:
    """The depth RMS at a depth, `factor` times the ideal target's: stereo matching errs in
    disparity, so it grows with depth squared (z^2 x subpixel / (f x baseline))."""
    return factor * np.square(depth_m) * SUBPIXEL_PX / (focal_px * BASELINE_M)
