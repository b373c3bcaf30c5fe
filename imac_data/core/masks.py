"""Robot masks: their outlines, their agreement, and the ground truth read off a simulator's
segmentation. Arrays in, arrays out."""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

__all__ = ["outline", "mask_iou", "ground_truth_robot_mask"]


def outline(mask: np.ndarray, thickness: int = 1) -> np.ndarray:
    """Boundary pixels of a boolean mask ``(H, W)`` (inside the mask, ``thickness`` px wide)."""
    m = np.ascontiguousarray(mask, dtype=np.uint8)
    k = 2 * thickness + 1
    eroded = cv2.erode(m, np.ones((k, k), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0)
    return (m > 0) & (eroded == 0)


def mask_iou(pred: np.ndarray, truth: np.ndarray) -> float:
    """Intersection over union of two boolean masks; NaN when both are empty."""
    union = np.logical_or(pred, truth).sum()
    if union == 0:
        return float("nan")
    return float(np.logical_and(pred, truth).sum() / union)


def ground_truth_robot_mask(segmentation: np.ndarray, labels: dict[int, tuple[str, str]],
                            robot_links: Sequence[str]) -> np.ndarray:
    """Robot pixels of a geom-id segmentation (``-1`` = none): geoms whose body is a robot
    link (our MJCF->URDF export keeps MuJoCo body names as link names)."""
    links = set(robot_links)
    ids = [int(g) for g, (_, body) in labels.items() if body in links]
    seg = np.asarray(segmentation).astype(np.int64)
    if not ids:
        return np.zeros(seg.shape, dtype=bool)
    lut = np.zeros(max(max(ids), int(seg.max(initial=-1))) + 2, dtype=bool)
    lut[np.array(ids) + 1] = True
    return lut[np.clip(seg, -1, None) + 1]
