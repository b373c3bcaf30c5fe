"""Does the workspace camera show the lift? The cube's size and its lift in pixels at the world
model's view size, from MuJoCo's own cube pose projected with the rig's calibration.

For each start the benchmark's closed-loop lift policy runs in MuJoCo (the ranking views); the
cube's eight corners are projected into ``cam_workspace`` at rest (after its 3 cm drop, at the
first chunk boundary) and at the end. The span is the larger side of the corners' bounding box;
the lift is how far the projected centre moved. The issue's bar: at least 6 px and, for a
successful lift, at least 10 px. ``offset_px_per_cm`` is how far the resting cube's image moves when
it moves 1 cm along world x and y: the training rollouts' lift is decided by the grasp's y offset
(docs/ranking.md, "What the view must show"). ``--front`` measures the camera's pose before
2026-11-28 instead; ``--picture`` draws two training rollouts (a near miss and a success) in both poses::

    python -m benchmarks.workspace_view --starts 12 --json benchmarks/results/workspace_view.json
    python -m benchmarks.workspace_view --starts 0 --picture docs/workspace_view.png
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageDraw

from imac_data.core.cameras import project
from imac_data.sources.sim import rig
from imac_model.evaluate.simulator import SimRunConfig, SimRunner
from imac_model.experiments.ranking import policies
from imac_model.experiments.ranking.plan import EVAL_SEED0, TRAIN_SEED0
from imac_model.experiments.ranking.policies import training_policy

CAMERA = next(iter(rig.WORKSPACE_CAMERA.values()))
FRONT_POSE = {"pos": (0.1, 0.1, 0.18), "target": (0.1, 0.5, 0.07), "fovy": 34.0}  # in front, looking along +y
PICTURED = {7: "near miss, 3.3 cm off in y", 21: "success, 0.5 cm off"}  # training rollouts of the "disc" offsets (policies.training_policy)
TIMES = (0, 8, 12, 16, 32)
HALF = 0.02  # the cube's half side (m)


def cube_corners(env) -> np.ndarray:
    body = env.layout.object_bodies["box"]
    R, p = env.data.xmat[body].reshape(3, 3), env.data.xpos[body]
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float)
    return p + (signs * HALF) @ R.T


def pixels(runner: SimRunner, corners: np.ndarray, hw: tuple[int, int]) -> tuple[float, np.ndarray]:
    cam = runner.cameras[CAMERA].rescaled(width=hw[1], height=hw[0])
    uv, _ = project(torch.as_tensor(corners), torch.as_tensor(cam.K), torch.as_tensor(cam.T_world_cam))
    uv = uv.numpy()
    return float(max(np.ptp(uv[:, 0]), np.ptp(uv[:, 1]))), uv.mean(axis=0)


def measure(starts: int, view_size: tuple[int, int]) -> dict:
    config = SimRunConfig(views=policies.VIEWS, view_height=view_size[0], view_width=view_size[1])
    rows = []
    with SimRunner(config) as runner:
        for i in range(starts):
            seen = {}

            def at_rest(env, chunk, seen=seen):
                if chunk == 1:
                    seen["rest"] = cube_corners(env)

            episode = runner.run_episode(policies.closed_loop(), EVAL_SEED0 + i, intervene=at_rest)
            span, centre0 = pixels(runner, seen["rest"], view_size)
            _, centre1 = pixels(runner, cube_corners(runner.env), view_size)
            per_cm = {axis: round(float(np.linalg.norm(pixels(runner, seen["rest"] + 0.01 * np.eye(3)[k], view_size)[1]
                                                       - centre0)), 2) for k, axis in enumerate("xy")}
            rows.append({"seed": EVAL_SEED0 + i, "success": episode.success, "span_px": round(span, 2),
                         "lift_px": round(float(np.linalg.norm(centre1 - centre0)), 2), "offset_px_per_cm": per_cm})
    ok = [r for r in rows if r["success"]]
    return {"camera": CAMERA, "pose": rig.WORKSPACE_POSE, "view_size": list(view_size), "episodes": rows,
            "offset_px_per_cm": {a: float(np.mean([r["offset_px_per_cm"][a] for r in rows])) for a in "xy"},
            "span_px": {"min": min(r["span_px"] for r in rows), "mean": float(np.mean([r["span_px"] for r in rows]))},
            "lift_px_successful": ({"min": min(r["lift_px"] for r in ok), "mean": float(np.mean([r["lift_px"] for r in ok]))}
                                   if ok else None)}


def picture(path: str) -> None:
    """The workspace camera at the render size in both poses, for the :data:`PICTURED` rollouts."""
    rows, labels = [], []
    strips = {}
    for name, pose in (("front (before)", FRONT_POSE), ("side (now)", rig.WORKSPACE_POSE)):
        rig.WORKSPACE_POSE, kept = pose, rig.WORKSPACE_POSE  # read when the runner builds its model
        with SimRunner(SimRunConfig(views=policies.VIEWS)) as runner:
            for i in PICTURED:
                images = runner.run_episode(training_policy(i), TRAIN_SEED0 + i).images[CAMERA]
                strips[(i, name)] = np.concatenate([images[t] for t in TIMES], axis=1)
        rig.WORKSPACE_POSE = kept
    for i, outcome in PICTURED.items():
        for name in ("front (before)", "side (now)"):
            rows.append(strips[(i, name)])
            labels.append((name, outcome))
    grid = np.concatenate(rows, axis=0)
    h, w = grid.shape[0] // len(rows), grid.shape[1] // len(TIMES)
    image = Image.new("RGB", (170 + grid.shape[1], 16 + grid.shape[0]), "white")
    image.paste(Image.fromarray(grid), (170, 16))
    draw = ImageDraw.Draw(image)
    for k, t in enumerate(TIMES):
        draw.text((170 + k * w + w // 2 - 14, 2), f"t={t}", fill=(0, 0, 0))
    for r, (name, outcome) in enumerate(labels):
        draw.text((4, 16 + r * h + h // 2 - 14), f"{name}\n{outcome}", fill=(0, 0, 0))
    image.save(path)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--starts", type=int, default=12)
    p.add_argument("--view-size", type=int, nargs=2, default=(48, 64))
    p.add_argument("--front", action="store_true", help="measure the camera's pose before 2026-11-28")
    p.add_argument("--json")
    p.add_argument("--picture", help="write the two poses' picture here (PNG)")
    args = p.parse_args()
    if args.picture:  # both poses, before --front changes the rig's
        picture(args.picture)
    if args.front:
        rig.WORKSPACE_POSE = FRONT_POSE
    if args.starts:
        result = measure(args.starts, tuple(args.view_size))
        print(json.dumps({k: v for k, v in result.items() if k != "episodes"}, indent=1))
        if args.json:
            Path(args.json).write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
