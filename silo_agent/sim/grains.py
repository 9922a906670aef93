"""Grain types: the angle of repose shapes the piles, the bulk density turns volume into tonnes.

Values from design.md (wheat 25-27 deg, rice 30-40 deg: the middle of the range is used).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Grain:
    name: str
    repose_deg: float
    density_t_m3: float
    rgb: tuple[int, int, int]  # base colour for the shaded colour image

    @property
    def slope(self) -> float:
        """Rise per metre of a free-standing pile flank."""
        return float(np.tan(np.radians(self.repose_deg)))


GRAINS: dict[str, Grain] = {
    "wheat": Grain("wheat", 26.0, 0.77, (196, 160, 96)),
    "corn": Grain("corn", 23.0, 0.72, (226, 178, 52)),
    "soybeans": Grain("soybeans", 25.0, 0.77, (210, 190, 130)),
    "rice": Grain("rice", 35.0, 0.58, (200, 170, 110)),
}


def grain(name: str) -> Grain:
    """The named grain, or a ValueError listing the known ones."""
    try:
        return GRAINS[name]
    except KeyError:
        raise ValueError(f"unknown grain {name!r}; known: {', '.join(GRAINS)}") from None
