"""The early gate of the CPU preset: does ``motion+contact`` draw the outcome yet?

After each ``plan.gate_every`` CPU-minutes of training, the recorded actions of the held-out
*training* rollouts are replayed in the world model (the evaluation episodes are used once, at
the end) and the lift judge reads the generated frames against MuJoCo's labels. The score is the
balanced accuracy (the mean recall of successes and failures), so a model that paints the
training prior, the lift, everywhere scores 0.5 whatever the mix of outcomes.

Each replay also starts again from the recorded frame of every later chunk (teacher-forced to
that chunk, free after it): if the model fails from chunk 0 but not from the last chunk, the
outcome is lost by drift across chunks; if it fails from the last chunk too, one chunk of it
does not carry the cube. ``runs/<mode>/gates.json`` keeps every gate; the report shows them."""

from __future__ import annotations

import dataclasses
import json
import os
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from imac_data import lerobot_compat as lr
from imac_data.metadata import dataset_info
from imac_model.data import mosaic
from imac_model.data.batch import unit_frames
from imac_model.evaluate.closed_loop import Start, episode_starts, judged_frames, rollout_episode
from imac_model.evaluate.pictures import label
from imac_model.evaluate.policies import recorded_actions_policy
from imac_model.evaluate.success import dataset_success_labels, verdict_scores
from imac_model.experiments.ranking.judge import LiftJudge
from imac_model.experiments.ranking.perception import RED_THRESHOLD, redness
from imac_model.experiments.ranking.plan import GATED_MODE, TRAIN_REPO, RankingPlan
from imac_model.experiments.ranking.policies import WORKSPACE
from imac_model.models.checkpoint import list_checkpoints, load_world_model
from imac_model.pipelines.online_controls import OnlineControls
from imac_model.pipelines.sampling import open_chunks
from imac_model.training.archive import GATES
from imac_model.training.log import read_log

SEED_STRIDE = 100_003  # seed s of a replay: its start's seed + s * SEED_STRIDE


def gate_minutes(plan: RankingPlan) -> list[float]:
    """The CPU-minutes of training after which the gated mode is measured: every
    ``gate_every``, and at the end of its budget."""
    if not plan.gate_every:
        return []
    points = list(np.arange(plan.gate_every, plan.cpu_minutes, plan.gate_every).round(6))
    return [float(m) for m in points] + [float(plan.cpu_minutes)]


def reseeded(start: Start, seed: int) -> Start:
    """Replay ``seed`` (0, 1, ...) of a closed-loop start: seed 0 keeps
    the start's own noise (the single-seed gate's), seed s adds ``s * SEED_STRIDE``. Every measure that pools
    seeds (the gate, the evaluation replays, the diagnosis) draws them this way, so their replays match."""
    return dataclasses.replace(start, seed=start.seed + SEED_STRIDE * int(seed))


def gates_path(plan: RankingPlan, mode: str = GATED_MODE) -> Path:
    return plan.run_dir(mode) / GATES


def read_gates(plan: RankingPlan, mode: str = GATED_MODE) -> list[dict]:
    path = gates_path(plan, mode)
    return json.loads(path.read_text()) if path.is_file() else []


def gate_verdict(plan: RankingPlan, gates: list[dict]) -> str:
    """``passed`` once a full replay (from chunk 0) reached ``gate_min`` balanced accuracy; ``stop``
    when it has not by ``gate_by`` CPU-minutes (or by the end of the budget, if sooner); else
    ``continue``."""
    if any(g["from_chunk"]["0"]["balanced_accuracy"] >= plan.gate_min for g in gates):
        return "passed"
    deadline = min(plan.gate_by, plan.cpu_minutes)
    return "stop" if any(g["budget_minutes"] >= deadline - 1e-6 for g in gates) else "continue"


def start_at_chunk(start, chunks, k: int):
    """``start`` moved to the recorded frame of its ``k``-th chunk: that frame, its state, the
    actions from there, the chunks that remain."""
    item = chunks[chunks.episode_chunks(start.episode)[k]]
    H = chunks.layout.chunk
    ref = item["reference"]
    return dataclasses.replace(start, frame=start.frame + k * H, chunks=start.chunks - k,
                               reference=unit_frames(ref),
                               state=item["state"].float(), recorded_actions=start.recorded_actions[k * H:])


def cube_in_view(frames: torch.Tensor, spec, view: str) -> list[list[float]]:
    """The cube in ``view`` of each of ``frames (T, 3, 2h, V w)``: ``[pixels, row, col]``, its red
    pixels and their centroid (None without any)."""
    v = spec.views.index(view)
    rgb, _ = mosaic.split(frames, len(spec.views))
    red = (redness(rgb[:, v].clamp(0, 1)) > RED_THRESHOLD).float()
    n = red.sum(dim=(-2, -1))
    rows, cols = torch.arange(red.shape[-2]).float(), torch.arange(red.shape[-1]).float()
    cy = (red.sum(-1) * rows).sum(-1) / n
    cx = (red.sum(-2) * cols).sum(-1) / n
    return [[int(a), round(float(b), 2), round(float(c), 2)] if a > 0 else [0, None, None] for a, b, c in zip(n, cy, cx)]


def cube_summary(cube: dict[str, list[list[list[float]]]], share: float = 0.5) -> dict[str, list]:
    """Per chunk, over the full replays whose recording shows the cube at the chunk's last frame:
    ``kept``, the share whose generated view shows at least ``share`` of its pixels; ``offset_px``,
    the median distance (pixels) between the generated and recorded cubes' centroids, where both show."""
    kept, offset = [], []
    for n in range(max((len(r) for r in cube["recorded"]), default=0)):
        pairs = [(g[n], r[n]) for g, r in zip(cube["generated"], cube["recorded"]) if len(r) > n and r[n][0] > 0]
        kept.append(round(sum(g[0] >= share * r[0] for g, r in pairs) / len(pairs), 4) if pairs else None)
        d = [float(np.hypot(g[1] - r[1], g[2] - r[2])) for g, r in pairs if g[0] > 0]
        offset.append(round(float(np.median(d)), 2) if d else None)
    return {"kept": kept, "offset_px": offset}


def cube_by_view(gate: dict) -> dict[str, dict]:
    """A gate's ``cube_at_chunk_end`` per view (gates written before views were measured have the
    workspace view's alone)."""
    c = gate["cube_at_chunk_end"]
    return {WORKSPACE: c} if "kept" in c else c


def _strip(recorded: torch.Tensor, generated: torch.Tensor, spec, times: list[int],
           captions: tuple[str, str]) -> np.ndarray:
    """Two rows (recorded, generated) of the workspace view at ``times``, each row's first cell
    captioned; (H, W, 3) uint8."""
    v = spec.views.index(WORKSPACE) if WORKSPACE in spec.views else 0
    rows = []
    for name, frames, caption in (("recorded", recorded, captions[0]), ("generated", generated, captions[1])):
        rgb, _ = mosaic.split(frames, len(spec.views))
        cells = [(rgb[t, v].clamp(0, 1) * 255).round().byte().permute(1, 2, 0).numpy() for t in times]
        cells = [cv2.resize(c, (c.shape[1] * 2, c.shape[0] * 2), interpolation=cv2.INTER_NEAREST) for c in cells]
        cells = [label(c, f"{name} t={t + 1}" if i else caption) for i, (c, t) in enumerate(zip(cells, times))]
        rows.append(np.concatenate(cells, axis=1))
    return np.concatenate(rows, axis=0)


def measure_cube(chunks, start, records, spec, cube: dict, *, picture: bool = False, judged: bool = False,
                 outcome: bool = False):
    """Append a full replay's cube at each chunk's end (recorded, generated), in every view, to
    ``cube[view]``; its picture strip when ``picture`` (captioned with ``outcome`` and how it was ``judged``)."""
    items = chunks.episode_chunks(start.episode)[:len(records)]
    recorded = unit_frames(torch.cat([chunks[i]["future"] for i in items]))
    generated = torch.cat([r.frames for r in records])
    H = spec.chunk
    ends = [H * (n + 1) - 1 for n in range(len(records))]
    for view in spec.views:  # the wrist view too: it carries the grasp (docs/ranking.md)
        for name, frames in (("recorded", recorded), ("generated", generated)):
            cube.setdefault(view, {"recorded": [], "generated": []})[name].append(cube_in_view(frames[ends], spec, view))
    if not picture:
        return None
    captions = (f"ep {start.episode}: {'success' if outcome else 'failure'}",
                f"judged {'lifted' if judged else 'not lifted'}")
    return _strip(recorded, generated, spec, [H // 2 - 1] + ends, captions)


def measure_gate(plan: RankingPlan, budget_minutes: float, mode: str = GATED_MODE, pictures: int = 4) -> dict:
    """The gate on ``mode``'s latest checkpoint (EMA weights), trained to ``budget_minutes`` (one of
    :func:`gate_minutes`), appended to ``runs/<mode>/gates.json`` with a picture ``gate_<step>.png``
    beside it (up to ``pictures`` full replays, half of each outcome)."""
    torch.set_num_threads(1)
    t0, c0 = time.time(), time.process_time()
    run_dir = plan.run_dir(mode)
    checkpoint = list_checkpoints(run_dir)[-1]
    model, spec = load_world_model(checkpoint, weights="ema", device=plan.device)
    log = read_log(run_dir)
    trained = next(r for r in reversed(log) if "step" in r)  # the CPU trainer logs CPU seconds, the GPU one wall
    labels = dataset_success_labels(lr.LeRobotDataset(TRAIN_REPO, root=plan.train_dataset))
    episodes = [e for e in plan.held_out_episodes() if labels.get(e) is not None]
    chunks = open_chunks(spec, TRAIN_REPO, str(plan.train_dataset), episodes=episodes)
    online = OnlineControls.from_dataset(plan.train_dataset, spec, info=dataset_info(chunks.lerobot.meta))
    judge = LiftJudge()
    verdicts: dict[int, list[tuple[bool, bool]]] = {k: [] for k in range(plan.chunks)}  # (judged, label)
    cube: dict[str, dict] = {}  # per view, per full replay: the cube at each chunk's last frame
    shown = {True: 0, False: 0}
    strips = []
    for seed in range(plan.gate_seeds):
        for start in episode_starts(chunks, episodes, seed=plan.seed, horizon_chunks=plan.chunks):
            start = reseeded(start, seed)
            for k in range(min(plan.chunks, len(chunks.episode_chunks(start.episode)))):
                s = start_at_chunk(start, chunks, k)
                records = list(rollout_episode(model, online, recorded_actions_policy(s.recorded_actions), s,
                                               steps=plan.steps))
                last = [(f, q) for r in records for f, q in zip(r.frames.unbind(0), r.configurations.unbind(0))][-4:]
                outcome = labels[start.episode]
                judged = bool(judge.judge([judged_frames(s.episode, last, spec.views, s.task, online)])[0])
                verdicts[k].append((judged, outcome))
                if k == 0 and seed == 0:
                    strip = measure_cube(chunks, start, records, spec, cube, judged=judged, outcome=outcome,
                                         picture=shown[outcome] < pictures // 2)
                    if strip is not None:
                        shown[outcome] += 1
                        strips.append(strip)
    truth = [labels[e] for e in episodes]
    from_chunk = {}
    for k, v in verdicts.items():
        if v:  # pooled over the seeds, and each seed's own (the replays of one seed are consecutive)
            n = len(v) // plan.gate_seeds
            from_chunk[str(k)] = {**verdict_scores(*zip(*v)), "balanced_accuracy_per_seed": [
                verdict_scores(*zip(*v[i * n:(i + 1) * n]))["balanced_accuracy"] for i in range(plan.gate_seeds)]}
    gate = {"budget_minutes": float(budget_minutes),
            "cpu_minutes": round(trained["cpu_s"] / 60, 2) if "cpu_s" in trained else None, "step": int(trained["step"]),
            "checkpoint": checkpoint.name, "episodes": episodes, "labels": truth, "sampler_steps": plan.steps,
            "seeds": plan.gate_seeds,
            "from_chunk": from_chunk, "cube": cube,
            "cube_at_chunk_end": {view: cube_summary(c) for view, c in cube.items()}, "wall_s": round(time.time() - t0, 1), "cpu_s": round(time.process_time() - c0, 1)}
    gates = [g for g in read_gates(plan, mode) if g["budget_minutes"] != budget_minutes] + [gate]
    path = gates_path(plan, mode)
    if strips:
        width = max(s.shape[1] for s in strips)
        img = np.concatenate([np.pad(s, ((0, 0), (0, width - s.shape[1]), (0, 0))) for s in strips], axis=0)
        cv2.imwrite(str(path.with_name(f"gate_{gate['step']:06d}.png")), cv2.cvtColor(img, cv2.COLOR_RGB2BGR),
                    [cv2.IMWRITE_PNG_COMPRESSION, 9])
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(sorted(gates, key=lambda g: g["budget_minutes"]), indent=1))
    os.replace(tmp, path)
    return gate


__all__ = ["GATED_MODE", "gate_minutes", "gate_verdict", "measure_gate", "read_gates", "reseeded"]
