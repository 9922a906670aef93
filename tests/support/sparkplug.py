"""What a Sparkplug host sends, encoded by pysparkplug (an independent implementation)."""

from __future__ import annotations

import time

import pysparkplug as ps


def rebirth_request() -> bytes:
    """NCMD `Node Control/Rebirth` = true, as a host sends it."""
    ncmd = ps.NCmd(
        timestamp=int(time.time() * 1000),
        metrics=(
            ps.Metric(
                timestamp=None,
                name="Node Control/Rebirth",
                datatype=ps.DataType.BOOLEAN,
                value=True,
            ),
        ),
    )
    return ncmd.encode(include_dtypes=True)
