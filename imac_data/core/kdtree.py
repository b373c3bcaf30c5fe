"""Exact KD-trees over 3-D points: pykdtree, loaded single-threaded.

pykdtree sizes its OpenMP pool from ``OMP_NUM_THREADS`` once, when the library loads. We load it
with one thread and parallelise over blocks of queries on Python threads where that pays (its
queries release the GIL): spinning OpenMP pools made the contact streams several times slower on a
shared 2-core machine. It answers the same nearest neighbours as scipy's ``cKDTree``, with the same
``inf`` distance and index ``n`` past ``distance_upper_bound``, 2-3x faster to build and to query
(docs/building.md, "Contact: searches and glue"; docs/calibration.md, "Accuracy and time")."""

from __future__ import annotations

import os
import sys

import numpy as np

__all__ = ["LEAFSIZE", "kdtree"]

LEAFSIZE = 16  # points per leaf: the contact streams' queries were fastest at 16


def _kdtree_class():
    if "pykdtree.kdtree" not in sys.modules:
        old = os.environ.get("OMP_NUM_THREADS")
        os.environ["OMP_NUM_THREADS"] = "1"
        try:
            import pykdtree.kdtree  # noqa: F401
        finally:
            if old is None:
                os.environ.pop("OMP_NUM_THREADS", None)
            else:
                os.environ["OMP_NUM_THREADS"] = old
    return sys.modules["pykdtree.kdtree"].KDTree


class _NoPoints:
    """The tree of an empty cloud: nothing within any distance, as scipy's ``cKDTree`` answers (pykdtree refuses
    to build one)."""

    def query(self, query_pts, **_):
        n = len(query_pts)
        return np.full(n, np.inf), np.zeros(n, dtype=np.uint32)


def kdtree(points: np.ndarray, *, leafsize: int = LEAFSIZE):
    """A pykdtree ``KDTree`` over ``(N, 3)`` points, kept as float64 (``query`` takes any float points)."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    return _kdtree_class()(points, leafsize=int(leafsize)) if len(points) else _NoPoints()
