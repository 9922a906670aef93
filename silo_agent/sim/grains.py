"""Grain types: the angle of repose shapes the piles, the bulk density turns volume into tonnes.

Angles of repose from base/choices.REPOSE_DEG (the reconstruction's fill uses the same).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from silo_agent.base.choices import REPOSE_DEG


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
    "wheat": Grain("wheat", REPOSE_DEG["wheat"], 0.77, (196, 160, 96)),
    "corn": Grain("corn", REPOSE_DEG["corn"], 0.72, (226, 178, 52)),
    "soybeans": Grain("soybeans", REPOSE_DEG["soybeans"], 0.77, (210, 190, 130)),
    "rice": Grain("rice", REPOSE_DEG["rice"], 0.58, (200, 170, 110)),
}


def grain(name: str) -> Grain:
    """The named grain, or a ValueError listing the known ones."""
    try:
        return GRAINS[name]
    except KeyError:
        raise ValueError(f"unknown grain {name!r}; known: {', '.join(GRAINS)}") from None
