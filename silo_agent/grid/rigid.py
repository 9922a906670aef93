"""Small rigid-body geometry of camera poses (4x4 camera->silo transforms, silo frame)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

UP = np.array([0.0, 0.0, 1.0])


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotation taking direction `a` to direction `b`."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    axis = np.cross(a, b)
    s, c = np.linalg.norm(axis), float(np.dot(a, b))
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        helper = np.array([1.0, 0, 0]) if abs(a[0]) < 0.9 else np.array([0, 1.0, 0])
        axis = np.cross(a, helper)
        s = np.linalg.norm(axis)
    k = axis / s
    cross = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    angle = np.arctan2(s, c)
    return np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross


def pose_change(before: np.ndarray, after: np.ndarray) -> tuple[float, float]:
    """(degrees turned, metres moved) of a camera between two camera->silo transforms."""
    relative = after[:3, :3] @ before[:3, :3].T
    cosine = np.clip((np.trace(relative) - 1) / 2, -1.0, 1.0)
    return float(np.degrees(np.arccos(cosine))), float(np.linalg.norm(after[:3, 3] - before[:3, 3]))


def about(rotation: np.ndarray, pivot: np.ndarray, shift: np.ndarray | None = None) -> np.ndarray:
    """4x4 silo-frame transform: rotate about `pivot`, then translate by `shift`."""
    out = np.eye(4)
    out[:3, :3] = rotation
    out[:3, 3] = pivot - rotation @ pivot + (0 if shift is None else shift)
    return out


def rotation_between_axis(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues: rotation by `angle` (rad) about unit `axis`."""
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def planar_procrustes(moved: Sequence[np.ndarray], reference: Sequence[np.ndarray]) -> np.ndarray:
    """The rotation about z and x/y shift (4x4) that best puts the `moved` camera poses back on
    the `reference` ones (centres and 1 m ahead of them): the rig's yaw and plan position,
    which neither a floor nor gravity can observe, stay where the configuration had them."""

    def marks(poses: Sequence[np.ndarray]) -> np.ndarray:
        out = []
        for pose in poses:
            ahead = pose[:3, 2].copy()
            ahead[2] = 0.0
            norm = np.linalg.norm(ahead)
            out.append(pose[:2, 3])
            if norm > 1e-6:
                out.append(pose[:2, 3] + ahead[:2] / norm)
        return np.array(out)

    src, dst = marks(moved), marks(reference)
    sc, dc = src.mean(axis=0), dst.mean(axis=0)
    h = (src - sc).T @ (dst - dc)
    angle = np.arctan2(h[0, 1] - h[1, 0], h[0, 0] + h[1, 1])
    c, s = np.cos(angle), np.sin(angle)
    out = np.eye(4)
    out[:2, :2] = [[c, -s], [s, c]]
    out[:2, 3] = dc - out[:2, :2] @ sc
    return out
