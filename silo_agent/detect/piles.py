"""The per-pile result both detectors produce, and stable pile ids between scans."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

__all__ = ["ModelError", "Pile", "match_ids"]


class ModelError(Exception):
    """A detection model silo-agent cannot use; the message names the file and the problem."""


@dataclass(frozen=True)
class Pile:
    """One pile in the silo frame, whichever detector found it."""

    id: int
    detector: str  # "geometric" | "onnx"
    centroid: tuple[float, float]  # volume-weighted (x, y), silo frame
    peak: tuple[float, float]  # (x, y) of the highest point
    peak_height_m: float  # above the floor (site floor_z)
    footprint_m2: float
    volume_m3: float
    confidence: float | None = None  # the model's score (onnx only)

    def to_json(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "detector": self.detector,
            "centroid": {"x": self.centroid[0], "y": self.centroid[1]},
            "peak": {"x": self.peak[0], "y": self.peak[1]},
            "peak_height_m": self.peak_height_m,
            "footprint_m2": self.footprint_m2,
            "volume_m3": self.volume_m3,
            "confidence": self.confidence,
        }

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> Pile:
        """A pile of an earlier result.json, to carry its id over to the next scan."""
        return cls(
            id=int(data["id"]),
            detector=str(data["detector"]),
            centroid=(float(data["centroid"]["x"]), float(data["centroid"]["y"])),
            peak=(float(data["peak"]["x"]), float(data["peak"]["y"])),
            peak_height_m=float(data["peak_height_m"]),
            footprint_m2=float(data["footprint_m2"]),
            volume_m3=float(data["volume_m3"]),
            confidence=data.get("confidence"),
        )


def match_ids(previous: Sequence[Pile], new: Sequence[Pile], max_distance_m: float) -> list[Pile]:
    """`new` with ids carried over from `previous` where a pile stayed in place.

    Piles of the same detector are paired by centroid distance (Hungarian assignment, so two
    piles never claim one id); pairs farther apart than `max_distance_m` do not count. Unmatched
    piles get fresh ids above every previous one, in `new`'s order.
    """
    ids = [0] * len(new)
    if previous and new:
        from scipy.optimize import linear_sum_assignment  # 0.1 s to import: only when matching

        old_xy = np.array([p.centroid for p in previous], dtype=float)
        new_xy = np.array([p.centroid for p in new], dtype=float)
        distance = np.linalg.norm(new_xy[:, None, :] - old_xy[None, :, :], axis=2)
        same = np.array([[n.detector == o.detector for o in previous] for n in new])
        allowed = same & (distance <= max_distance_m)
        cost = np.where(allowed, distance, max_distance_m * 1e3 + 1.0)
        rows, cols = linear_sum_assignment(cost)
        for r, c in zip(rows.tolist(), cols.tolist(), strict=True):
            if allowed[r, c]:
                ids[r] = previous[c].id
    next_id = max((p.id for p in previous), default=0) + 1
    out = []
    for pile, pile_id in zip(new, ids, strict=True):
        if pile_id == 0:
            pile_id, next_id = next_id, next_id + 1
        out.append(replace(pile, id=pile_id))
    return out
