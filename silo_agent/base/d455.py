"""The Intel RealSense D455's stereo constants and depth-noise model: one home for the
reconstruction's wall test, the live map's weights and its coverage check."""

from __future__ import annotations

import numpy as np

# A depth image's size: at most the D455's largest depth stream, 1280x720 (a config's width of
# 1,000,000 passed and the simulator's `scan` never ended); at least 16: simulated cameras may
# render below any D455 stream (212x120 keeps a test's sim run fast)
MIN_IMAGE_PX = 16
MAX_WIDTH_PX = 1280
MAX_HEIGHT_PX = 720

BASELINE_M = 0.095  # stereo baseline
SUBPIXEL_PX = 0.08  # disparity RMS of block matching on an ideal target
# share of the noise variance common to pixels a few apart (the blobs a block matcher makes):
# averaging more points of one frame does not take it down
CORRELATED_SHARE = 0.5
CORRELATION_PX = 4.0  # ... in blobs of about this Gaussian sigma, in pixels


def depth_rms_m(depth_m: np.ndarray | float, focal_px: float, factor: float = 1.0) -> np.ndarray:
    """The depth RMS at a depth, `factor` times the ideal target's: stereo matching errs in
    disparity, so it grows with depth squared (z^2 x subpixel / (f x baseline))."""
    return factor * np.square(depth_m) * SUBPIXEL_PX / (focal_px * BASELINE_M)


def blob_area_px() -> float:
    """The correlated part's integral scale in pixels: a mean over A pixels keeps a share
    blob_area / A of its variance (4 pi sigma^2 for Gaussian-smoothed white noise)."""
    return 4 * np.pi * CORRELATION_PX**2
