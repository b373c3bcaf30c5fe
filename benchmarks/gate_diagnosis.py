"""Where does a replay lose the outcome: the frame, or the contact images rebuilt from it?

The early gate (``imac_model/experiments/ranking/gate.py``) replays the recorded actions of the
held-out training rollouts in a trained run and judges the generated frames. Every chunk after the
first starts from the model's own last frame, and its contact images are rebuilt from that frame's
depth. This diagnosis replays the same episodes (full replays, from chunk 1) in two ways:

* ``generated``: as the gate does;
* ``recorded-scene``: the same, except that each chunk's contact images are rebuilt from the
  *recorded* frame at its start, an oracle scene. The model still starts from its own frame.

If ``recorded-scene`` draws the outcome and ``generated`` does not, the outcome is lost in the
contact images (the generated depth no longer holds the cube); if neither does, in the frames.
Each way is sampled with several noise seeds, which also measures how much of the gate's spread
is the sampler's rather than the model's::

    python -m benchmarks.gate_diagnosis motion_contact_noise03_to240 --work runs/ranking_cpu --seeds 3 \\
        --json benchmarks/results/gate_diagnosis.json
"""

from __future__ import annotations

import argparse
import dataclasses
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
from imac_model.experiments.ranking.gate import SEED_STRIDE, _from_chunk
from imac_model.experiments.ranking.judge import LiftJudge
from imac_model.experiments.ranking.plan import TRAIN_REPO, RankingPlan
from imac_model.models.checkpoint import list_checkpoints, load_world_model
from imac_model.pipelines.online_controls import OnlineControls
from imac_model.pipelines.sampling import open_chunks

WAYS = ("generated", "recorded-scene")


def _share(x: np.ndarray) -> float | None:
    return round(float(x.mean()), 4) if x.size else None  # None: no episode of that outcome


def diagnose(plan: RankingPlan, run: str, seeds: int = 3, ways: tuple[str, ...] = WAYS, from_chunk: int = 0,
             guidance: float | None = None) -> dict:
    """Replays of the held-out training rollouts in ``<work>/runs/<run>`` (latest checkpoint, EMA
    weights), each way and noise seed judged by the lift judge against MuJoCo's labels; from the
    recorded frame of chunk ``from_chunk`` (0: full replays, as the gate's verdict); sampled with
    classifier-free ``guidance`` (default: the run's own, ``conditioning.guidance``)."""
    torch.set_num_threads(1)
    t0 = time.time()
    checkpoint = list_checkpoints(plan.work / "runs" / run)[-1]
    model, spec = load_world_model(checkpoint, weights="ema", device=plan.device, guidance=guidance)
    labels = dataset_success_labels(lr.LeRobotDataset(TRAIN_REPO, root=plan.train_dataset))
    episodes = [e for e in plan.held_out_episodes() if labels.get(e) is not None]
    chunks = open_chunks(spec, TRAIN_REPO, str(plan.train_dataset), episodes=episodes)
    online = OnlineControls.from_dataset(plan.train_dataset, spec, info=dataset_info(chunks.lerobot.meta))
    judge = LiftJudge()
    starts = episode_starts(chunks, episodes, seed=plan.seed, horizon_chunks=plan.chunks)
    truth = [labels[st.episode] for st in starts]
    judged = {w: np.zeros((seeds, len(starts)), dtype=bool) for w in ways}
    for way in ways:
        for s in range(seeds):
            for j, start in enumerate(starts):
                items = chunks.episode_chunks(start.episode)[from_chunk:]
                scene = (lambda n, items=items: unit_frames(chunks[items[n]]["reference"])) if way == "recorded-scene" else None
                start = _from_chunk(start, chunks, from_chunk) if from_chunk else start
                start = dataclasses.replace(start, seed=start.seed + SEED_STRIDE * s)  # seed 0 is the single-seed gate's
                records = list(rollout_episode(model, online, recorded_actions_policy(start.recorded_actions), start,
                                               steps=plan.steps, scene=scene))
                last = [(f, q) for r in records for f, q in zip(r.frames.unbind(0), r.configurations.unbind(0))][-4:]
                judged[way][s, j] = judge.judge([judged_frames(start.episode, last, spec.views, start.task, online)])[0]
            score = verdict_scores(judged[way][s].tolist(), truth)["balanced_accuracy"]
            print(f"[diagnosis] {run} {way} seed {s}: balanced accuracy {score:.2f}", flush=True)
    result = {"run": run, "checkpoint": checkpoint.name, "from_chunk": from_chunk,
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
                       "lifted_share_of_failures": _share(lifted[~np.array(truth)])}
    return result


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run", help="a trained run of the work directory (runs/<run>), e.g. motion_contact")
    p.add_argument("--work", default="runs/ranking_cpu", help="the ranking benchmark's work directory")
    p.add_argument("--seeds", type=int, default=3, help="noise seeds per way (the first is the gate's)")
    p.add_argument("--ways", nargs="+", choices=WAYS, default=list(WAYS))
    p.add_argument("--from-chunk", type=int, default=0, help="start from the recorded frame of chunk K, counted from 0 (0: full replays; 1: t=H)")
    p.add_argument("--guidance", type=float, help="classifier-free guidance (a run trained with conditioning.dropout)")
    p.add_argument("--json", help="write the figures here (a list: this run's entry is replaced or added)")
    args = p.parse_args(argv)
    plan = RankingPlan.load(Path(args.work) / "plan.json")
    result = diagnose(plan, args.run, args.seeds, tuple(args.ways), args.from_chunk, args.guidance)
    for way in args.ways:
        r = result[way]
        print(f"{args.run} (guidance {result['guidance']:g}) {way:15s} balanced accuracy {' '.join(f'{x:.2f}' for x in r['balanced_accuracy'])} "
              f"(mean {r['mean']:.2f}); judged lifted in {r['lifted_share_of_successes']} of the successes' "
              f"replays, {r['lifted_share_of_failures']} of the failures'; {r['episodes_that_flip']} of "
              f"{len(result['episodes'])} episodes flip between seeds")
    if args.json:
        path = Path(args.json)
        entries = [e for e in (json.loads(path.read_text()) if path.is_file() else [])
                   if (e["run"], e["from_chunk"], e["guidance"]) != (args.run, args.from_chunk, result["guidance"])]
        path.write_text(json.dumps(entries + [result], indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
