"""Where does a replay lose the outcome: the frame, or the contact images rebuilt from it?

The early gate (``imac_model/experiments/ranking/gate.py``) replays the recorded actions of the
held-out training rollouts in a trained run and judges the generated frames. Every chunk after the
first starts from the model's own last frame, and its contact images are rebuilt from that frame's
depth. This diagnosis replays the same episodes (full replays, from chunk 1) in two ways:

* ``generated``: as the gate does;
* ``recorded-scene``: the same, except that each chunk's contact images are rebuilt from the
  *recorded* frame at its start, an oracle scene. The model still starts from its own frame.

* ``recorded:<view>``: the same as ``generated``, except that at every chunk boundary that view of
  the model's own frame (its RGB and depth) is replaced by the recorded one: which view's drift
  loses the outcome (``--boundaries 1``: at the first boundary only, t=H).

If ``recorded-scene`` draws the outcome and ``generated`` does not, the outcome is lost in the
contact images (the generated depth no longer holds the cube); if neither does, in the frames.
``--split training`` replays as many *training* rollouts instead (the ones just before the held-out
block): if the model draws their outcome and not the held-out ones', it has fitted its data and
not learned the rule (more or other data); if it draws neither, it has not fitted (capacity, steps).
Each way is sampled with several noise seeds, which also measures how much of the gate's spread
is the sampler's rather than the model's::

    python -m benchmarks.gate_diagnosis motion_contact_noise03_to240 --work runs/ranking_cpu --seeds 3 \\
        --json benchmarks/results/gate_diagnosis.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from imac_data import lerobot_compat as lr
from imac_data.metadata import dataset_info
from imac_model.data.batch import unit_frames
from imac_model.evaluate.closed_loop import episode_starts, judged_frames, rollout_episode
from imac_model.evaluate.policies import recorded_actions_policy
from imac_model.evaluate.success import dataset_success_labels, verdict_scores
from imac_model.experiments.ranking.gate import cube_summary, measure_cube, reseeded, start_at_chunk
from imac_model.experiments.ranking.judge import LiftJudge
from imac_model.experiments.ranking.plan import TRAIN_REPO, RankingPlan
from imac_model.models.checkpoint import list_checkpoints, load_world_model
from imac_model.pipelines.online_controls import OnlineControls
from imac_model.pipelines.sampling import open_chunks

WAYS = ("generated", "recorded-scene")
SPLITS = ("held-out", "training")


def _recorded_view(way: str, views: tuple[str, ...]) -> int | None:
    """The view index a ``recorded:<view>`` way restores, None for the other ways."""
    if not way.startswith("recorded:"):
        if way not in WAYS:
            raise ValueError(f"way must be one of {WAYS} or recorded:<view>, got {way!r}")
        return None
    view = way.split(":", 1)[1]
    if view not in views:
        raise ValueError(f"way {way!r}: the model's views are {list(views)}")
    return views.index(view)


def _oracles(way: str, chunks, items: list, spec, boundaries: tuple[int, ...] | None = None):
    """``(scene, intervene)`` for ``rollout_episode``: what ``way`` takes from the recording of the
    replayed chunks ``items`` (a ``recorded:<view>`` way: at the chunk ``boundaries`` n, default all)."""
    def recorded(n: int) -> torch.Tensor:  # the recorded frame at chunk n's start, (3, 2h, V w)
        return unit_frames(chunks[items[n]]["reference"])

    v, w = _recorded_view(way, spec.views), spec.view_width
    if v is None:
        return (recorded if way == "recorded-scene" else None), None

    def intervene(reference: torch.Tensor, n: int) -> torch.Tensor:  # view v of the mosaic: columns v w to (v+1) w
        if boundaries is not None and n not in boundaries:
            return reference
        out = reference.clone()
        out[..., v * w:(v + 1) * w] = recorded(n)[..., v * w:(v + 1) * w].to(out)
        return out
    return None, intervene


def replayed_episodes(plan: RankingPlan, split: str) -> list[int]:
    """The held-out training rollouts, or as many training ones: those just before them."""
    held = plan.held_out_episodes()
    if split == "held-out":
        return held
    if split != "training":
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
    return list(range(max(0, held[0] - len(held)), held[0]))


def _share(x: np.ndarray) -> float | None:
    return round(float(x.mean()), 4) if x.size else None  # None: no episode of that outcome


def diagnose(plan: RankingPlan, run: str, seeds: int = 3, ways: tuple[str, ...] = WAYS, from_chunk: int = 0,
             guidance: float | None = None, split: str = "held-out",
             boundaries: tuple[int, ...] | None = None) -> dict:
    """Replays of the held-out training rollouts (``split``: or as many training ones) in ``<work>/runs/<run>`` (latest checkpoint, EMA
    weights), each way and noise seed judged by the lift judge against MuJoCo's labels; from the
    recorded frame of chunk ``from_chunk`` (0: full replays, as the gate's verdict); sampled with
    classifier-free ``guidance`` (default: the run's own, ``conditioning.guidance``)."""
    torch.set_num_threads(1)
    t0 = time.time()
    checkpoint = list_checkpoints(plan.work / "runs" / run)[-1]
    model, spec = load_world_model(checkpoint, weights="ema", device=plan.device, guidance=guidance)
    labels = dataset_success_labels(lr.LeRobotDataset(TRAIN_REPO, root=plan.train_dataset))
    episodes = [e for e in replayed_episodes(plan, split) if labels.get(e) is not None]
    chunks = open_chunks(spec, TRAIN_REPO, str(plan.train_dataset), episodes=episodes)
    online = OnlineControls.from_dataset(plan.train_dataset, spec, info=dataset_info(chunks.lerobot.meta))
    judge = LiftJudge()
    starts = episode_starts(chunks, episodes, seed=plan.seed, horizon_chunks=plan.chunks)
    truth = [labels[st.episode] for st in starts]
    judged = {w: np.zeros((seeds, len(starts)), dtype=bool) for w in ways}
    cubes: dict[str, dict] = {w: {} for w in ways}  # full replays: the cube at each chunk's end, per view
    for way in ways:
        for s in range(seeds):
            for j, start in enumerate(starts):
                items = chunks.episode_chunks(start.episode)[from_chunk:]
                scene, intervene = _oracles(way, chunks, items, spec, boundaries)
                start = start_at_chunk(start, chunks, from_chunk) if from_chunk else start
                start = reseeded(start, s)
                records = list(rollout_episode(model, online, recorded_actions_policy(start.recorded_actions), start,
                                               steps=plan.steps, scene=scene, intervene=intervene))
                if from_chunk == 0:
                    measure_cube(chunks, start, records, spec, cubes[way])
                last = [(f, q) for r in records for f, q in zip(r.frames.unbind(0), r.configurations.unbind(0))][-4:]
                judged[way][s, j] = judge.judge([judged_frames(start.episode, last, spec.views, start.task, online)])[0]
            score = verdict_scores(judged[way][s].tolist(), truth)["balanced_accuracy"]
            print(f"[diagnosis] {run} {split} {way} seed {s}: balanced accuracy {score:.2f}", flush=True)
    result = {"work": plan.work.name, "run": run, "checkpoint": checkpoint.name, "split": split, "from_chunk": from_chunk,
              "boundaries": None if boundaries is None else list(boundaries),
              "guidance": spec.conditioning.guidance, "episodes": [st.episode for st in starts], "labels": truth,
              "sampler_steps": plan.steps, "seeds": seeds, "wall_s": round(time.time() - t0, 1)}
    for way in ways:
        scores = [verdict_scores(judged[way][s].tolist(), truth)["balanced_accuracy"] for s in range(seeds)]
        # an episode whose verdict differs between seeds is decided by the sampler, not the model
        flips = int((judged[way].min(axis=0) != judged[way].max(axis=0)).sum())
        lifted = judged[way].mean(axis=0)  # per episode: the share of seeds judged lifted
        result[way] = {"balanced_accuracy": [round(x, 4) for x in scores], "mean": round(float(np.mean(scores)), 4),
                       "episodes_that_flip": flips, "judged_lifted": judged[way].astype(int).tolist(),
                       "lifted_share_of_successes": _share(lifted[np.array(truth)]),
                       "lifted_share_of_failures": _share(lifted[~np.array(truth)]),
                       "cube_at_chunk_end": {v: cube_summary(c) for v, c in cubes[way].items()} or None}
    return result


def _key(entry: dict) -> tuple:
    """What a JSON entry is a measurement of: one entry per key (entries older than a field lack it)."""
    return (entry.get("work", "ranking_cpu"), entry["run"], entry["from_chunk"], entry["guidance"], entry.get("split", "held-out"),
            None if entry.get("boundaries") is None else tuple(entry["boundaries"]),
            tuple(sorted(w for w in entry if w in WAYS or w.startswith("recorded:"))))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run", help="a trained run of the work directory (runs/<run>), e.g. motion_contact")
    p.add_argument("--work", default="runs/ranking_cpu", help="the ranking benchmark's work directory")
    p.add_argument("--seeds", type=int, default=3, help="noise seeds per way (the first is the gate's)")
    p.add_argument("--ways", nargs="+", default=list(WAYS), help=f"{', '.join(WAYS)} or recorded:<view>")
    p.add_argument("--from-chunk", type=int, default=0, help="start from the recorded frame of chunk K, counted from 0 (0: full replays; 1: t=H)")
    p.add_argument("--guidance", type=float, help="classifier-free guidance (a run trained with conditioning.dropout)")
    p.add_argument("--split", choices=SPLITS, default="held-out",
                   help="replay the held-out rollouts (the gate's) or as many training ones")
    p.add_argument("--boundaries", type=int, nargs="+",
                   help="recorded:<view> ways: restore the view at these chunk boundaries only (1: t=H; default all)")
    p.add_argument("--json", help="write the figures here (a list: this run's entry is replaced or added)")
    args = p.parse_args(argv)
    plan = RankingPlan.load(Path(args.work) / "plan.json")
    result = diagnose(plan, args.run, args.seeds, tuple(args.ways), args.from_chunk, args.guidance, args.split,
                      None if args.boundaries is None else tuple(args.boundaries))
    for way in args.ways:
        r = result[way]
        print(f"{args.run} {args.split} (guidance {result['guidance']:g}) {way:15s} balanced accuracy {' '.join(f'{x:.2f}' for x in r['balanced_accuracy'])} "
              f"(mean {r['mean']:.2f}); judged lifted in {r['lifted_share_of_successes']} of the successes' "
              f"replays, {r['lifted_share_of_failures']} of the failures'; {r['episodes_that_flip']} of "
              f"{len(result['episodes'])} episodes flip between seeds")
        for view, c in (r["cube_at_chunk_end"] or {}).items():
            print(f"  the cube in {view} at each chunk's end: kept {c['kept']}, centre off {c['offset_px']} px (median)")
    if args.json:
        path = Path(args.json)
        entries = [e for e in (json.loads(path.read_text()) if path.is_file() else [])
                   if _key(e) != _key(result)]
        path.write_text(json.dumps(entries + [result], indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
