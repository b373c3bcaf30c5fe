"""What fusing the certified tiles' passes into compiled loops would give: a measurement, not the build's code.

    pip install numba   # not a dependency of the project
    python -m benchmarks.contact_fused [--size 480x640] [--rounds 2] [--json PATH]

``certified_distances`` (imac_data/core/contact/nearest.py) runs each tile level as about 35 torch
passes over the unresolved points (docs/building.md, "Contact: searches and glue";
``benchmarks.contact_profile`` measures them). Here the same algorithm runs as two numba loops a level:
one finds every point's tile and the tile's representative (the point nearest its centre, ties to the
lowest index, as in ``_tile_representatives``), one tests each member's certified bound
``|p - n_r| - max(d(r) - |p - r|, 0) <= max(abs, rel * lower)`` and writes its value or keeps it for
the next level. The KD-tree searches are the same calls. On the chunks of ``benchmarks.contact_profile``
(one thread, the build's defaults, percentile caps) the two versions alternate ``--rounds`` times; the
report gives CPU-ms a frame for each and how far the fused images are from today's (distances, and colour
pixels that differ: a float32 norm rounded otherwise can move a member between accepting its bound and an
exact search, both within the tolerance).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np
import torch

import imac_data.core.contact.images as images
from benchmarks.contact_profile import chunks

try:
    from numba import njit
except ImportError as e:  # pragma: no cover - the project does not depend on numba
    raise SystemExit("benchmarks.contact_fused needs numba: pip install numba") from e


@njit(nogil=True, cache=True)
def _tiles(subset, group, pix, H, W, s, G):
    """Each member's representative (its position in ``subset``), the slot of every representative,
    and the representatives' point indices in slot order."""
    th, tw = (H + s - 1) // s, (W + s - 1) // s
    per = th * tw
    n = subset.shape[0]
    best = np.full(G * per, np.iinfo(np.int64).max, np.int64)
    tile = np.empty(n, np.int64)
    for i in range(n):
        p = subset[i]
        y, x = pix[p] // W, pix[p] % W
        ty, tx = y // s, x // s
        t = group[p] * per + ty * tw + tx
        key = ((2 * (y - ty * s) - (s - 1)) ** 2 + (2 * (x - tx * s) - (s - 1)) ** 2) * (n + 1) + i
        tile[i] = t
        if key < best[t]:
            best[t] = key
    rep = np.empty(n, np.int64)
    slot = np.full(n, -1, np.int64)
    count = 0
    for i in range(n):
        r = best[tile[i]] % (n + 1)
        rep[i] = r
        if slot[r] < 0:
            slot[r] = count
            count += 1
    reps = np.empty(count, np.int64)
    for i in range(n):
        if slot[i] >= 0:
            reps[slot[i]] = subset[i]
    return rep, slot, reps


@njit(nogil=True, cache=True)
def _accept(subset, points, rep, slot, d_rep, n_rep, tol_abs, tol_rel, out):
    """Write every member whose certified bound holds into ``out``; return the others."""
    n = subset.shape[0]
    rest = np.empty(n, np.int64)
    m = 0
    for i in range(n):
        p, r, j = subset[i], subset[rep[i]], slot[rep[i]]
        d = d_rep[j]
        if math.isinf(d):
            out[p] = d
            continue
        gap = np.float32(math.sqrt((points[p, 0] - points[r, 0]) ** 2 + (points[p, 1] - points[r, 1]) ** 2
                                   + (points[p, 2] - points[r, 2]) ** 2))
        upper = np.float32(math.sqrt((points[p, 0] - n_rep[j, 0]) ** 2 + (points[p, 1] - n_rep[j, 1]) ** 2
                                     + (points[p, 2] - n_rep[j, 2]) ** 2))
        lower = max(d - gap, np.float32(0.0))
        if upper - lower <= max(tol_abs, tol_rel * lower):
            out[p] = upper
        else:
            rest[m] = p
            m += 1
    return rest[:m]


def fused_certified_distances(pyramid, query, tolerance, max_distance):
    """``certified_distances`` with each level as the two loops above (percentile caps only)."""
    if max_distance is not None:
        raise ValueError("the fused experiment covers percentile caps only (max_distance None)")
    tol_abs, tol_rel = np.float32(tolerance[0]), np.float32(tolerance[1])
    points = pyramid.points
    pts, group, pix = points.numpy(), pyramid.group.numpy(), pyramid.pix.numpy()
    out = np.full(len(pts), np.nan, np.float32)
    todo = np.arange(len(pts), dtype=np.int64)
    for level, size in enumerate(pyramid.sizes):
        if not len(todo):
            break
        cached = getattr(pyramid, "_fused_level0", None)  # the s2g scene serves every step of a chunk
        rep, slot, reps = cached if level == 0 and cached is not None else \
            _tiles(todo, group, pix, pyramid.H, pyramid.W, size, pyramid.num_groups)
        if level == 0:
            pyramid._fused_level0 = (rep, slot, reps)
        d, near = query(points[torch.from_numpy(reps)], None)
        todo = _accept(todo, pts, rep, slot, d.numpy().astype(np.float32),
                       np.ascontiguousarray(near.numpy(), dtype=np.float32), tol_abs, tol_rel, out)
    if len(todo):
        out[todo] = query(points[torch.from_numpy(todo)], None)[0].numpy()
    return torch.from_numpy(out)


def _contact(inputs, fused: bool):
    images.certified_distances = fused_certified_distances if fused else _TORCH
    try:
        return [images.contact_chunk(*c, workers=1, parallel=1) for c in inputs]
    finally:
        images.certified_distances = _TORCH


_TORCH = images.certified_distances


def run(size: str = "480x640", rounds: int = 2, max_steps: int = 120) -> dict:
    height, width = (int(x) for x in size.split("x"))
    torch.set_num_threads(1)
    inputs = chunks(height, width, max_steps)
    frames = sum(c[4].shape[0] for c in inputs)
    ours, fused = _contact(inputs, False), _contact(inputs, True)  # also compiles the loops
    worst, differ, pixels = 0.0, 0, 0
    for a, b in zip(ours, fused):
        for k in ("r2s", "s2g"):
            x, y = getattr(a, k), getattr(b, k)
            if not torch.equal(torch.isnan(x), torch.isnan(y)):
                raise AssertionError(f"{k}: the fused loops painted other pixels")
            m = torch.isfinite(x)
            worst = max(worst, float((x[m] - y[m]).abs().max()) if m.any() else 0.0)
            differ += int((getattr(a, k + "_rgb") != getattr(b, k + "_rgb")).any(-1).sum())
            pixels += x.numel()
    times: dict[str, list[float]] = {"torch": [], "fused": []}
    for _ in range(rounds):
        for name in times:
            cpu = time.process_time()
            _contact(inputs, name == "fused")
            times[name].append(1e3 * (time.process_time() - cpu) / frames)
    med = {k: float(np.median(v)) for k, v in times.items()}
    return {"size": size, "future_frames": frames, "cpu_ms_per_frame": times, "median": med,
            "ratio_fused_to_torch": med["fused"] / med["torch"], "max_abs_difference_m": worst,
            "colour_pixels_differing": differ, "colour_pixels": pixels}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", default="480x640")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    r = run(args.size, args.rounds)
    print(f"contact, {r['size']}, one thread, {r['future_frames']} future frames, CPU-ms a frame by round: "
          f"torch {r['cpu_ms_per_frame']['torch']}, fused {r['cpu_ms_per_frame']['fused']}; "
          f"fused / torch {r['ratio_fused_to_torch']:.2f} (medians); distances within {r['max_abs_difference_m']:.1e} m, "
          f"{r['colour_pixels_differing']} of {r['colour_pixels']} colour pixels differ")
    if args.json:
        args.json.write_text(json.dumps(r, indent=2) + "\n")


if __name__ == "__main__":
    main()
