"""The calibration's refusals: each message names the camera or scan and says why."""

from __future__ import annotations


class CalibrationError(Exception):
    """Calibration impossible or refused; the message says which camera and why."""


class SerialMismatch(CalibrationError):
    """The scan's cameras and the config's are not the same set of serials."""


class ScanMismatch(CalibrationError):
    """Calibration scans to be pooled are not of the same cameras or the same site."""
