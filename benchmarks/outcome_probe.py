"""Can the outcome be read from what a chunk's world model is shown? A discriminative probe.

The gate asks the world model to draw whether the cube is lifted, from a recorded frame and one
chunk's conditioning. This asks a small CNN classifier the same question directly: from the
chunk's inputs (the reference frame, RGB and depth of both views, and its control images or its
actions), predict MuJoCo's label of the episode. It learns from one bit per rollout where the
world model learns from every pixel of its frames, so it bounds from below what the inputs hold;
it shows where in an episode the outcome becomes readable, and which views and streams carry it.

Every rollout of the GPU preset's pack (torch alone) is scored out of fold: the episodes are split
into folds, and each fold is predicted by a probe trained on the others. ``future`` is the answer as
recorded (the chunk's own last frame), the probe's ceiling. ``--target offset`` regresses the
rollout's planned grasp offset (cm) instead of its label: a number per rollout, not a bit, and the
geometry that decides the grasp (docs/ranking.md, "What the view must show")::

    python -m benchmarks.outcome_probe --work runs/ranking_side --inputs reference motion+contact --chunks 2 1 \
        --target offset [--views cam_workspace] --json benchmarks/results/outcome_probe.json

``--test evaluation`` trains each probe on every training rollout instead and tests it on the
evaluation episodes, the policies the benchmark ranks: does the training data teach the outcomes
those policies meet ("Training data that covers the policies" in docs/ranking.md)?
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn

from imac_data import lerobot_compat as lr
from imac_model.data.chunks import ChunkDataset, open_metadata
from imac_model.data.pack import Pack, pack_arrays
from imac_model.evaluate.success import dataset_success_labels, verdict_scores
from imac_model.experiments.ranking.plan import EVAL_REPO, TRAIN_REPO, RankingPlan
from imac_model.training.dataset_source import model_spec

# what each probe sees besides the chunk's reference frame (its RGB and depth rows, both views)
INPUTS = {
    "reference": (),
    "actions": ("actions",),
    "motion+contact": ("control.motion", "control.contact_s2g", "control.contact_r2s"),
    "motion+contact+scene-warp": ("control.motion", "control.contact_s2g", "control.contact_r2s",
                                  "control.scene_warp"),
    "future": ("future",),
    # what a full replay is given from its first frame: every chunk's actions, or their motion images
    "episode-actions": ("episode.actions",),
    "episode-motion": ("episode.control.motion",),
}


class Probe(nn.Module):
    """Three stride-2 convolutions over the stacked images, max-pooled over the image (a grasp is
    decided by where things are relative to each other, not where in the view), beside a linear
    read of the actions, to one logit (or ``outputs`` regressed values)."""

    def __init__(self, channels: int, actions: int = 0, width: int = 32, outputs: int = 1):
        super().__init__()
        c = width
        self.images = nn.Sequential(
            nn.Conv2d(channels, c, 3, stride=2, padding=1), nn.GroupNorm(8, c), nn.SiLU(),
            nn.Conv2d(c, 2 * c, 3, stride=2, padding=1), nn.GroupNorm(8, 2 * c), nn.SiLU(),
            nn.Conv2d(2 * c, 2 * c, 3, stride=2, padding=1), nn.SiLU(), nn.AdaptiveMaxPool2d(1), nn.Flatten(),
            nn.Dropout(0.3))
        self.actions = nn.Linear(actions, 64) if actions else None
        self.head = nn.Linear(2 * c + (64 if actions else 0), outputs)

    def forward(self, images: torch.Tensor, actions: torch.Tensor | None = None) -> torch.Tensor:
        x = self.images(images)
        if self.actions is not None:
            x = torch.cat([x, torch.relu(self.actions(actions))], dim=1)
        return self.head(x)


def probe_inputs(pack: Pack, index: torch.Tensor, what: str, views: list[str] | None = None,
                 chunks: int = 4) -> tuple[torch.Tensor, torch.Tensor | None]:
    """``(n, C, H/2, W)`` float images (the mosaic's two rows stacked in channels, each control's
    frames in channels; only ``views``' columns where given) and ``(n, A)`` actions or None.
    ``episode-`` inputs take an episode's ``chunks`` chunks from its first (``index``)."""
    t = pack.tensors

    def rows(mosaic: torch.Tensor) -> torch.Tensor:  # (n, 3, 2h, w) -> (n, 6, h, w)
        n, c, h2, w = mosaic.shape
        return mosaic.reshape(n, c, 2, h2 // 2, w).reshape(n, 2 * c, h2 // 2, w)

    images, actions = [rows(t["reference"][index])], None
    for key in INPUTS[what]:
        if key.startswith("episode."):  # the episode's chunks are consecutive in the pack
            index, key = index[:, None] + torch.arange(chunks), key[len("episode."):]
        if key == "actions":
            actions = t["actions"][index].flatten(1)
        elif key == "future":
            images.append(rows(t["future"][index][:, -1]))
        else:
            images.append(t[key][index].reshape(len(index), -1, *t[key].shape[-2:]))
    images = torch.cat(images, dim=1)
    if views:  # the mosaic's columns are the spec's views, in order
        w = images.shape[-1] // len(pack.spec.views)
        images = torch.cat([images[..., w * pack.spec.views.index(v):w * (pack.spec.views.index(v) + 1)]
                            for v in views], dim=-1)
    return images.float() / 255.0, actions


def fit_predict(train: tuple, target: torch.Tensor, test: tuple, *, steps: int, seed: int) -> torch.Tensor:
    """Out-of-fold predictions of a probe trained ``steps`` steps (batch 32, AdamW): logits for a
    boolean ``target`` (classes weighted), else ``(n, k)`` regressed values (standardised inside)."""
    torch.manual_seed(seed)
    images, actions = train
    scale = None
    if actions is not None:  # the actions standardised on the training folds
        mean, std = actions.mean(0), actions.std(0).clamp_min(1e-3)
        scale = lambda a: (a - mean) / std  # noqa: E731
    boolean = target.dtype == torch.bool
    y = target.float()[:, None] if boolean else target.float()
    if not boolean:
        y_mean, y_std = y.mean(0), y.std(0).clamp_min(1e-6)
        y = (y - y_mean) / y_std
    model = Probe(images.shape[1], 0 if actions is None else actions.shape[1], outputs=y.shape[1])
    opt = torch.optim.AdamW(model.parameters(), lr=1e-3, weight_decay=0.05)
    if boolean:
        positive = y.mean().clamp(0.05, 0.95)
        weights = torch.where(target, 0.5 / positive, 0.5 / (1 - positive))[:, None]
    g = torch.Generator().manual_seed(seed)
    model.train()
    for _ in range(steps):
        b = torch.randint(len(y), (32,), generator=g)
        out = model(images[b], None if actions is None else scale(actions[b]))
        if boolean:
            loss = nn.functional.binary_cross_entropy_with_logits(out, y[b], weight=weights[b])
        else:
            loss = nn.functional.mse_loss(out, y[b])
        opt.zero_grad()
        loss.backward()
        opt.step()
    model.eval()
    with torch.no_grad():
        out = model(test[0], None if test[1] is None else scale(test[1]))
    return out[:, 0] if boolean else out * y_std + y_mean


def grasp_offsets(plan: RankingPlan) -> dict[int, list[float]]:
    """Each scripted training rollout's planned grasp offset (x, y) in cm, from the simulate stage's records
    (a plan's ``training_policies`` plan none)."""
    rows = [r for part in sorted((plan.work / "sim" / "train").glob("part_*"))
            for r in json.loads((part / "outcomes.json").read_text())]
    return {int(r["index"]): [100.0 * v for v in r["offset"]] for r in rows if r["offset"] is not None}


def offset_knn(offsets: dict[int, list[float]], labels: dict[int, bool | None], k: int) -> float:
    """Balanced accuracy of the majority label of each rollout's ``k`` nearest planned offsets
    (leave one out): what knowing the grasp offset exactly, and nothing else, tells of the outcome."""
    episodes = [e for e in offsets if labels.get(e) is not None]
    x = np.array([offsets[e] for e in episodes])
    y = np.array([labels[e] for e in episodes])
    d = np.linalg.norm(x[:, None] - x[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    predicted = y[np.argsort(d, axis=1)[:, :k]].mean(axis=1) > 0.5
    return float(verdict_scores(predicted.tolist(), y.tolist())["balanced_accuracy"])


def regression_scores(predicted: torch.Tensor, truth: torch.Tensor) -> dict:
    """Per axis (x, y): out-of-fold R^2 and mean absolute error (cm)."""
    sse, sst = ((predicted - truth) ** 2).sum(0), ((truth - truth.mean(0)) ** 2).sum(0)
    mae = (predicted - truth).abs().mean(0)
    return {"n": len(truth), **{f"r2_{a}": round(float(1 - sse[k] / sst[k]), 3) for k, a in enumerate("xy")},
            **{f"mae_cm_{a}": round(float(mae[k]), 2) for k, a in enumerate("xy")}}


def evaluation_pack(plan: RankingPlan) -> Pack:
    """The evaluation episodes' chunks as an in-memory pack, decoded with the training pack's layout
    (the recorded control streams; the derived scene warp is not among them)."""
    run = plan.run_config("motion+contact")
    spec, layout = model_spec(run, open_metadata(run.data))
    ds = ChunkDataset(EVAL_REPO, layout, root=plan.eval_dataset, cache="memory")
    ds.preload(num_workers=1, progress=True)
    items = [ds[i] for i in range(len(ds))]
    return Pack.from_arrays(pack_arrays(items, [True] * len(items), spec))


def measure_on_evaluation(plan: RankingPlan, inputs: list[str], chunks: list[int], steps: int, seeds: list[int],
                          views: list[str] | None = None, save=lambda result: None) -> dict:
    """Probes trained on every labelled training rollout (one per seed), tested on the evaluation
    episodes (the policies the benchmark ranks): balanced accuracy per seed, and each policy's
    MuJoCo rate against the share the probes call a success, over the seeds."""
    torch.set_num_threads(1)
    pack, evaluation = Pack(plan.pack), evaluation_pack(plan)
    labels = dataset_success_labels(lr.LeRobotDataset(TRAIN_REPO, root=plan.train_dataset))
    eval_labels = dataset_success_labels(lr.LeRobotDataset(EVAL_REPO, root=plan.eval_dataset))
    per_policy = plan.groups * plan.real_per_group
    result = {"work": plan.work.name, "target": "success", "test": "evaluation",
              "training_offsets": plan.training_offsets, "steps": steps, "seeds": seeds,
              "views": views or list(pack.spec.views), "probes": {}}

    def at(p: Pack, known: dict, c: int) -> torch.Tensor:  # the chunks at position c of labelled episodes
        episode = p.tensors["episode_index"]
        position = torch.arange(len(episode)) - p.first_chunk
        return torch.tensor([i for i in range(len(episode))
                             if int(position[i]) == c and known.get(int(episode[i])) is not None])

    for c in chunks:
        train, test = at(pack, labels, c), at(evaluation, eval_labels, c)
        y = torch.tensor([labels[int(pack.tensors["episode_index"][i])] for i in train])
        truth = [eval_labels[int(evaluation.tensors["episode_index"][i])] for i in test]
        policy = [plan.names[int(evaluation.tensors["episode_index"][i]) // per_policy] for i in test]
        for what in inputs:
            t0 = time.process_time()
            train_inputs = probe_inputs(pack, train, what, views, plan.chunks)
            test_inputs = probe_inputs(evaluation, test, what, views, plan.chunks)
            verdicts = [(fit_predict(train_inputs, y, test_inputs, steps=steps, seed=s) > 0).tolist() for s in seeds]
            per_seed = [verdict_scores(v, truth)["balanced_accuracy"] for v in verdicts]
            row = {"n": len(truth), "balanced_accuracy": round(float(np.mean(per_seed)), 3),
                   "balanced_accuracy_per_seed": [round(float(b), 3) for b in per_seed],
                   "policies": {name: {"mujoco": round(float(np.mean([t for t, q in zip(truth, policy) if q == name])), 3),
                                       "probe": round(float(np.mean([v[k] for v in verdicts for k, q in enumerate(policy)
                                                                     if q == name])), 3)}
                                for name in plan.names if name in policy},
                   "cpu_s": round(time.process_time() - t0, 1)}
            result["probes"].setdefault(what, {})[str(c)] = row
            print(json.dumps({"inputs": what, "chunk": c + 1, "t": 8 * c, **row}), flush=True)
            save(result)
    return result


def measure(plan: RankingPlan, inputs: list[str], chunks: list[int], folds: int, steps: int, seed: int,
            views: list[str] | None = None, target: str = "success", save=lambda result: None) -> dict:
    """Every (chunk, inputs) probe, out of fold; ``save`` is called with the result after each."""
    torch.set_num_threads(1)
    pack = Pack(plan.pack)
    labels = dataset_success_labels(lr.LeRobotDataset(TRAIN_REPO, root=plan.train_dataset))
    offsets = grasp_offsets(plan)
    episode = pack.tensors["episode_index"]
    position = torch.arange(len(episode)) - pack.first_chunk
    known = sorted({int(e) for e in episode if labels.get(int(e)) is not None})
    order = np.random.default_rng(seed).permutation(known)
    fold_of = {int(e): i % folds for i, e in enumerate(order)}
    result = {"work": plan.work.name, "target": target, "episodes": len(known),
              "successes": sum(labels[e] for e in known), "folds": folds, "steps": steps, "seed": seed,
              "views": views or list(pack.spec.views),
              "offset_knn": {str(k): round(offset_knn(offsets, labels, k), 3) for k in (5, 9, 15)}, "probes": {}}
    print(json.dumps({"offset_knn": result["offset_knn"]}), flush=True)
    for c in chunks:
        index = torch.tensor([i for i in range(len(episode)) if int(position[i]) == c and int(episode[i]) in fold_of
                              and (target != "offset" or int(episode[i]) in offsets)])  # a policy's rollouts plan none
        if target == "offset":
            y = torch.tensor([offsets[int(episode[i])] for i in index])
        else:
            y = torch.tensor([labels[int(episode[i])] for i in index])
        fold = torch.tensor([fold_of[int(episode[i])] for i in index])
        for what in inputs:
            if what.startswith("episode-") and c != 0:
                continue
            t0 = time.process_time()
            images, actions = probe_inputs(pack, index, what, views, plan.chunks)
            predicted = torch.empty(y.shape)
            for f in range(folds):
                tr, te = fold != f, fold == f
                predicted[te] = fit_predict((images[tr], None if actions is None else actions[tr]), y[tr],
                                            (images[te], None if actions is None else actions[te]),
                                            steps=steps, seed=seed + f)
            if target == "offset":
                row = regression_scores(predicted, y)
            else:
                scores = verdict_scores((predicted > 0).tolist(), y.tolist())
                row = {k: scores[k] for k in ("n", "balanced_accuracy", "accuracy", "majority_baseline", "confusion")}
            row["cpu_s"] = round(time.process_time() - t0, 1)
            result["probes"].setdefault(what, {})[str(c)] = row
            print(json.dumps({"inputs": what, "views": result["views"], "chunk": c + 1, "t": 8 * c, **row}), flush=True)
            save(result)
    return result


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.outcome_probe", description=__doc__.split("\n\n")[0])
    p.add_argument("--work", default="runs/ranking_gpu2", help="the ranking benchmark's work directory (its pack)")
    p.add_argument("--inputs", nargs="+", default=list(INPUTS), choices=list(INPUTS))
    p.add_argument("--chunks", nargs="+", type=int, default=[1, 2, 3, 4], help="chunk positions, from 1")
    p.add_argument("--views", nargs="+", help="only these views of the pack (default: all)")
    p.add_argument("--folds", type=int, default=6)
    p.add_argument("--steps", type=int, default=300, help="training steps of each probe (batch 32)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--seeds", type=int, default=3, help="with --test evaluation: probes trained, each its own seed")
    p.add_argument("--target", choices=("success", "offset"), default="success",
                   help="success: MuJoCo's label (balanced accuracy); offset: the planned grasp offset (x, y) in cm (R^2)")
    p.add_argument("--test", choices=("folds", "evaluation"), default="folds",
                   help="folds: out of fold over the training rollouts; evaluation: trained on them all, tested on "
                        "the evaluation episodes (the ranked policies; label only)")
    p.add_argument("--json", help="append the figures to this file (kept up to date after every probe)")
    args = p.parse_args(argv)
    path = Path(args.json) if args.json else None
    before = json.loads(path.read_text()) if path is not None and path.is_file() else []

    def save(result: dict) -> None:
        if path is not None:
            path.write_text(json.dumps([*before, result], indent=1) + "\n")

    plan, chunks = RankingPlan.load(Path(args.work) / "plan.json"), [c - 1 for c in args.chunks]
    if args.test == "evaluation":
        if args.target != "success":
            p.error("--test evaluation probes the label alone (--target success)")
        measure_on_evaluation(plan, args.inputs, chunks, args.steps, list(range(args.seed, args.seed + args.seeds)),
                              args.views, save)
    else:
        measure(plan, args.inputs, chunks, args.folds, args.steps, args.seed, args.views, args.target, save)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
