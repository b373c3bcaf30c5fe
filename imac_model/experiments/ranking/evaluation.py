"""The benchmark's measuring steps, each run in its own process by :mod:`.benchmark`:

* :func:`run_judges`: train the learned classifier on the training rollouts; both judges'
  accuracy on the real evaluation episodes;
* :func:`evaluate_policy`: one policy closed loop in one mode's world model from the evaluation
  starts; :func:`replays`: the recorded actions replayed (the judges' accuracy on generated
  frames and the error per chunk); each in a process of its own, cached;
* :func:`evaluate_mode`: a mode's outcomes from those (``none``: one policy, once, after checking
  that two policies get bit-identical frames), and the mode's action sensitivity."""

from __future__ import annotations

import dataclasses
import json
import os
import time
from pathlib import Path

import numpy as np
import torch

from imac_data import lerobot_compat as lr
from imac_data.core.contact.images import JET_LUT
from imac_data.layout import image_key
from imac_data.metadata import dataset_info
from imac_model.data import mosaic
from imac_model.data.batch import unit_frames
from imac_model.data.depth import decode_depth
from imac_model.evaluate import open_loop
from imac_model.evaluate.closed_loop import (
    ClosedLoopConfig,
    episode_starts,
    judged_frames,
    rollout_episode,
    run_closed_loop,
)
from imac_model.evaluate.policies import load_policy, recorded_actions_policy
from imac_model.evaluate.success import (
    SuccessClassifier,
    SuccessClassifierConfig,
    dataset_success_labels,
    episode_frames,
    evaluate_judge,
    train_success_classifier,
)
from imac_model.experiments.ranking.freeze import freeze_models
from imac_model.experiments.ranking.gate import reseeded
from imac_model.experiments.ranking.judge import LiftJudge
from imac_model.experiments.ranking.perception import RED_THRESHOLD, interior, redness, without_cube
from imac_model.experiments.ranking.plan import EVAL_REPO, GATED_MODE, TRAIN_REPO, RankingPlan, run_mode, slug
from imac_model.experiments.ranking.policies import WORKSPACE
from imac_model.models.checkpoint import load_world_model
from imac_model.pipelines.online_controls import OnlineControls
from imac_model.pipelines.sampling import open_chunks
from imac_model.schedulers import flow

# the second action sequence of the sensitivity samples: the right arm's waist and shoulder
SENSITIVITY_OFFSETS = {7: 0.3, 8: -0.25}
CONTACT_NEAR = 0.9  # JET level 1 - d / cap of a scene pixel the future gripper touches (a tenth of the cap)
def cameras(plan: RankingPlan) -> tuple[str, ...]:
    """The RGB keys the learned classifier sees: the benchmark's views."""
    return tuple(image_key(v) for v in plan.views)


JUDGE_COLUMNS = {"lift_geometry": "success", "classifier": "success_classifier"}  # judge -> its column in the rows


def _write(path: Path, data: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(data, indent=1))
    os.replace(tmp, path)



def run_judges(plan: RankingPlan) -> None:
    """-> ``judges/classifier/`` and ``judges/real.json``."""
    torch.set_num_threads(1)
    t0, c0 = time.time(), time.process_time()
    train = lr.LeRobotDataset(TRAIN_REPO, root=plan.train_dataset)
    outcomes = set(dataset_success_labels(train).values()) - {None}
    classifier = training = None
    if outcomes == {True, False}:
        classifier, training = train_success_classifier(train, SuccessClassifierConfig(cameras=cameras(plan),
                                                                                        seed=plan.seed))
        classifier.save(plan.work / "judges" / "classifier")
    else:  # e.g. the toy run's two chunks end before any lift: no classifier, said so in the report
        training = {"skipped": f"the training rollouts have only {sorted(outcomes)} outcomes"}
    evaluation = lr.LeRobotDataset(EVAL_REPO, root=plan.eval_dataset)
    labels = dataset_success_labels(evaluation)
    episodes = sorted(labels)
    lift = LiftJudge()
    frames = episode_frames(evaluation, episodes, cameras(plan), 4, geometry=True)
    judges = [(name, j) for name, j in (("lift_geometry", lift), ("classifier", classifier)) if j is not None]
    real = {name: evaluate_judge(j, frames, [labels[e] for e in episodes]) for name, j in judges}
    # the same frames with the cube painted out: a judge of the cube, not of the arm, falls to chance
    masked = [dataclasses.replace(f, frames={c: without_cube(x) for c, x in f.frames.items()}) for f in frames]
    cube_masked = {name: evaluate_judge(j, masked, [labels[e] for e in episodes]) for name, j in judges}
    _write(plan.work / "judges" / "real.json", {
        "classifier_training": training, "real": real, "cube_masked": cube_masked,
        "heights": {int(f.episode_index): [None if np.isnan(h) else round(float(h), 4) for h in lift.heights(f)]
                    for f in frames},
        "labels": {int(e): bool(v) for e, v in labels.items()},
        "wall_s": round(time.time() - t0, 1), "cpu_s": round(time.process_time() - c0, 1)})


def recorded_episodes(plan: RankingPlan, labels: dict[int, bool]) -> list[int]:
    """Evaluation episodes to replay in the world model: half successes where possible, taken
    round-robin over the policies in a fixed shuffled order."""
    rng = np.random.default_rng(plan.seed)
    order = [int(e) for e in rng.permutation(sorted(labels))]
    want = {True: (plan.recorded + 1) // 2, False: plan.recorded // 2}
    picked = []
    for outcome in (True, False):
        picked += [e for e in order if labels[e] is outcome][:want[outcome]]
    rest = [e for e in order if e not in picked]
    return sorted(picked + rest[:plan.recorded - len(picked)])


def replay_recorded(plan: RankingPlan, model, chunks, online, episodes: list[int], labels: dict[int, bool],
                    steps: int, judge, classifier, seeds: int = 1) -> dict:
    """Real evaluation episodes replayed in the world model (their recorded actions, closed
    loop), each with ``seeds`` noise seeds (:func:`~imac_model.experiments.ranking.gate.reseeded`, as the gate
    draws them): both judges on the generated frames against MuJoCo's labels, pooled over the seeds and per seed,
    and the RGB error of every chunk against the recording (the mosaic's RGB row, [0, 1])."""
    t0, c0 = time.time(), time.process_time()
    spec = model.spec
    rows, mse = [], []
    starts = episode_starts(chunks, episodes, seed=plan.seed, horizon_chunks=plan.chunks)
    for seed, start in ((s, reseeded(st, s)) for s in range(seeds) for st in starts):
        records = list(rollout_episode(model, online, recorded_actions_policy(start.recorded_actions), start,
                                       steps=steps))
        items = chunks.episode_chunks(start.episode)
        errors, moving, by_view, depth = [], [], [], []
        for n, record in enumerate(records):
            item = chunks[items[n]]
            recorded, reference = unit_frames(item["future"]), unit_frames(item["reference"])
            h = spec.view_height
            errors.append(float(((record.frames[:, :, :h] - recorded[:, :, :h]) ** 2).mean()))
            moving.append(_moving_error(record.frames[:, :, :h], recorded[:, :, :h], reference[:, :h]))
            by_view.append(_view_errors(record.frames, recorded, spec))
            depth.append(_depth_figures(record.frames, recorded, online, spec))
        mse.append(errors)
        contact = (_chunk_two_contact(records, chunks, items, spec)
                   if len(records) > 1 and "contact_s2g" in records[1].controls else None)  # modes with contact
        last = [(f, q) for r in records for f, q in zip(r.frames.unbind(0), r.configurations.unbind(0))][-4:]
        seen = judged_frames(start.episode, last, spec.views, start.task, online)
        row = {"episode": start.episode, "seed": seed, "label": labels[start.episode],
               "lift_geometry": bool(judge.judge([seen])[0]),
               "mse_per_chunk": errors, "mse_moving_per_chunk": moving, "mse_per_chunk_by_view": by_view,
               "depth_per_chunk": depth, "chunk2_cube_contact": contact}
        if classifier is not None:
            row["classifier"] = bool(classifier.judge([seen])[0])
        rows.append(row)
    judges = [j for j in JUDGE_COLUMNS if all(j in r for r in rows)]
    return {"episodes": episodes, "labels": [labels[e] for e in episodes], "seeds": seeds, "rows": rows,
            "accuracy": {j: float(np.mean([r[j] == r["label"] for r in rows])) for j in judges},
            "accuracy_per_seed": {j: [float(np.mean([r[j] == r["label"] for r in rows if r["seed"] == s]))
                                      for s in range(seeds)] for j in judges},
            "mse_per_chunk": np.mean(mse, axis=0).tolist(),
            "mse_moving_per_chunk": np.nanmean([r["mse_moving_per_chunk"] for r in rows], axis=0).tolist(),
            "mse_per_chunk_by_view": {v: np.mean([[c[v] for c in r["mse_per_chunk_by_view"]] for r in rows], axis=0).tolist()
                                      for v in spec.views},
            "depth_valid_per_chunk": np.mean([[c["valid"] for c in r["depth_per_chunk"]] for r in rows], axis=0).tolist(),
            "depth_median_error_m_per_chunk": np.median([[c["median_error_m"] for c in r["depth_per_chunk"]]
                                                         for r in rows], axis=0).tolist(),
            "chunk2_cube_contact": _contact_shares([r["chunk2_cube_contact"] for r in rows]),
            "mse_per_chunk_by_label": {str(o): np.mean([m for m, r in zip(mse, rows) if r["label"] is o], axis=0).tolist()
                                       for o in (True, False) if any(r["label"] is o for r in rows)},
            "wall_s": round(time.time() - t0, 1), "cpu_s": round(time.process_time() - c0, 1)}


def _contact_level(rgb: torch.Tensor) -> torch.Tensor:
    """Contact colours ``(..., 3, h, w)`` in [0, 1] -> the JET level ``1 - d / cap`` of the nearest
    colour of the table (:func:`imac_data.core.contact.images.colorize`), NaN where black (no value)."""
    lut = torch.as_tensor(JET_LUT, dtype=torch.float32) / 255.0  # (256, 3)
    x = rgb.float().movedim(-3, -1)
    level = torch.cdist(x.reshape(-1, 3), lut).argmin(dim=-1).float().reshape(x.shape[:-1]) / 255.0
    return level.masked_fill(x.amax(dim=-1) < 0.05, float("nan"))


def _cube_contact(s2g: torch.Tensor, reference_rgb: torch.Tensor) -> bool | None:
    """Does an s2g video ``(H, 3, h, w)`` paint the cube (the red interior of its reference view
    ``(3, h, w)``) near a future gripper (JET level >= 0.9: within a tenth of the chunk's cap) in some
    frame? None when the reference shows no cube."""
    cube = interior(redness(reference_rgb) > RED_THRESHOLD)
    if int(cube.sum()) < 2:
        return None
    level = _contact_level(s2g)[:, cube]
    return bool((level.nan_to_num(0.0) >= CONTACT_NEAR).any())


def _chunk_two_contact(records, chunks, items, spec) -> dict:
    """The second chunk's s2g contact in the workspace view: rebuilt online from the generated
    reference (what the model was given) and recorded in the dataset, each judged on its own reference."""
    v, V = spec.views.index(WORKSPACE), len(spec.views)
    item = chunks[items[1]]
    recorded = mosaic.control_views(unit_frames(item["control.contact_s2g"]), V)[:, v]
    recorded_ref = mosaic.split(unit_frames(item["reference"]), V)[0][v]
    rebuilt_ref = mosaic.split(records[1].reference, V)[0][v]
    return {"recorded": _cube_contact(recorded, recorded_ref),
            "rebuilt": _cube_contact(records[1].controls["contact_s2g"][:, v], rebuilt_ref)}


def _contact_shares(rows: list[dict | None]) -> dict:
    """Over the replays: how often the cube's contact is present in chunk 2's s2g, recorded and rebuilt."""
    rows = [r for r in rows if r is not None]
    rec = [r for r in rows if r["recorded"]]
    return {"replays": len(rows), "recorded_present": len(rec),
            "rebuilt_present": sum(bool(r["rebuilt"]) for r in rows),
            "rebuilt_present_where_recorded": sum(bool(r["rebuilt"]) for r in rec),
            "rebuilt_cube_missing": sum(r["rebuilt"] is None for r in rows)}


def _moving_error(generated: torch.Tensor, recorded: torch.Tensor, reference: torch.Tensor) -> float:
    """RGB MSE of one chunk ``(H, 3, h, W)`` over the pixels that move in the recording: those
    that differ from its reference ``(3, h, W)`` by more than 0.1 in a channel, dilated 2 px (the
    mask of ``flow.focus_weight``, the loss weighting's; NaN if nothing moves)."""
    mask = flow.focus_weight(reference[None, :, None], recorded.transpose(0, 1)[None], 1.0, 0.1, 2)[0, 0] - 1.0
    err = ((generated - recorded) ** 2).sum(dim=1)
    return float((err * mask).sum() / (3 * mask.sum())) if mask.sum() > 0 else float("nan")


def _view_errors(generated: torch.Tensor, recorded: torch.Tensor, spec) -> dict[str, float]:
    """RGB MSE of one chunk per view (the mosaic's RGB row split into its views)."""
    g, _ = mosaic.split(generated, len(spec.views))
    r, _ = mosaic.split(recorded, len(spec.views))
    return {v: float(((g[:, i] - r[:, i]) ** 2).mean()) for i, v in enumerate(spec.views)}


def _depth_figures(generated: torch.Tensor, recorded: torch.Tensor, online, spec) -> dict[str, float]:
    """Of one chunk's generated depth, over the pixels where the recording's depth is valid: the
    share that decodes to valid metres, and the median absolute error (m) of those."""
    _, g = mosaic.split(generated, len(spec.views))
    _, r = mosaic.split(recorded, len(spec.views))
    g_m, g_bad = decode_depth(g, online.codec)
    r_m, r_bad = decode_depth(r, online.codec)
    where = ~r_bad
    both = where & ~g_bad
    return {"valid": float((~g_bad & where).sum() / where.sum().clamp_min(1)),
            "median_error_m": float((g_m - r_m)[both].abs().median()) if both.any() else float("nan")}


def none_is_policy_blind(plan: RankingPlan, model, online, chunks, start_episodes: list[int]) -> dict:
    """From the same starts and seeds, two policies get bit-identical frames from ``none``."""
    starts = episode_starts(chunks, start_episodes, seed=plan.seed, horizon_chunks=plan.chunks)
    a, b = load_policy(plan.policies[0]), load_policy(plan.policies[1])
    identical = []
    for start in starts:
        fa = torch.stack([r.frames for r in rollout_episode(model, online, a, start, steps=plan.steps)])
        fb = torch.stack([r.frames for r in rollout_episode(model, online, b, start, steps=plan.steps)])
        identical.append(bool(torch.equal(fa, fb)))
    return {"policies": [slug(plan.policies[0]), slug(plan.policies[1])], "starts": start_episodes,
            "bit_identical": identical}


def replays(plan: RankingPlan, mode: str, run: str | None = None) -> dict:
    """The gate: the recorded actions of real evaluation episodes (half successes) replayed in one
    mode's world model, judged against MuJoCo's labels; cached as ``wm/<mode>/replays.json``. Run
    alone (``--internal replays MODE [RUN]``) it measures the gate before any closed loop; ``RUN``
    names another trained run of the mode under ``runs/`` (an ablation)."""
    run_dir, wm_dir = ((_evaluated(plan, mode), plan.wm_dir(mode)) if run is None else
                       (plan.work / "runs" / run, plan.work / "wm" / run))
    done = wm_dir / "replays.json"
    if done.is_file():
        return json.loads(done.read_text())
    torch.set_num_threads(1)
    model, spec = load_world_model(run_dir, weights="ema", device=plan.device)
    labels = dataset_success_labels(lr.LeRobotDataset(EVAL_REPO, root=plan.eval_dataset))
    replay = recorded_episodes(plan, labels)
    chunks = open_chunks(spec, EVAL_REPO, str(plan.eval_dataset), episodes=replay)
    online = _online(plan, model, chunks)
    classifier = _classifier(plan)
    steps_list = sorted({plan.steps, plan.check_steps} if mode == GATED_MODE else {plan.steps})
    result = {str(k): replay_recorded(plan, model, chunks, online, replay, labels, k, LiftJudge(), classifier,
                                      seeds=plan.gate_seeds) for k in steps_list}
    _write(done, result)
    return result


def _evaluated(plan: RankingPlan, mode: str) -> Path:
    """The checkpoint ``mode`` is evaluated with, frozen as it ships when the evaluate stage has not done it (a step
    run alone)."""
    freeze_models(plan, (mode,))
    return plan.evaluated_model(mode)


def evaluated_policies(plan: RankingPlan, mode: str) -> tuple[str, ...]:
    """The policies run closed loop in ``mode``'s world model (``none`` is policy-blind: one, once)."""
    return plan.policies[:1] if run_mode(mode).blind else plan.policies


def policy_dir(plan: RankingPlan, mode: str, policy: str) -> Path:
    """Where one policy's closed loop in one mode's world model is kept (its ``closed_loop.json`` marks it done)."""
    return plan.wm_dir(mode) / slug(policy)


def evaluate_policy(plan: RankingPlan, mode: str, policy: str) -> dict:
    """One policy closed loop in one mode's world model from the evaluation starts, judged by both judges
    (cached: :func:`policy_dir`). The evaluate stage runs each policy in a process of its own, so that the
    machine's cores share the work evenly; :func:`evaluate_mode` then finds it done."""
    torch.set_num_threads(1)
    model = load_world_model(_evaluated(plan, mode), weights="ema", device=plan.device)[0]
    chunks = open_chunks(model.spec, EVAL_REPO, str(plan.eval_dataset), episodes=_start_episodes(plan))
    return _policy_closed_loop(plan, mode, policy, model, chunks, _online(plan, model, chunks))


def _start_episodes(plan: RankingPlan) -> list[int]:
    return [plan.eval_episode(0, s) for s in plan.wm_starts()]


def _online(plan: RankingPlan, model, chunks) -> OnlineControls:
    return OnlineControls.from_dataset(plan.eval_dataset, model.spec, info=dataset_info(chunks.lerobot.meta))


def _policy_closed_loop(plan: RankingPlan, mode: str, policy: str, model, chunks, online) -> dict:
    """One policy's closed loop in ``model`` (cached in :func:`policy_dir`), judged by both judges."""
    out = policy_dir(plan, mode, policy)
    done = out / "closed_loop.json"
    if done.is_file():
        return json.loads(done.read_text())
    config = ClosedLoopConfig(episodes=tuple(_start_episodes(plan)), horizon_chunks=plan.chunks,
                              sampler_steps=plan.steps, seed=plan.seed)
    t0, c0 = time.time(), time.process_time()
    result = run_closed_loop(model, chunks, online, load_policy(policy), out, config=config,
                             repo_id=f"local/{out.name}", judge=LiftJudge(), checkpoint=str(plan.evaluated_model(mode)),
                             overwrite=True, progress=False).to_dict()
    classifier = _classifier(plan)
    if classifier is not None:
        generated = lr.LeRobotDataset(f"local/{out.name}", root=out)
        verdicts = classifier.judge(episode_frames(generated, None, cameras(plan), 4))
        for row, v in zip(result["episodes"], verdicts):
            row["success_classifier"] = bool(v)
    chunk_ends(plan, policy, out, result["episodes"], chunks.layout.chunk)
    result.update(wall_s=round(time.time() - t0, 1), cpu_s=round(time.process_time() - c0, 1))
    _write(done, result)
    return result


def chunk_ends(plan: RankingPlan, policy: str, generated_root: Path, rows: list[dict], chunk: int) -> None:
    """Which chunk a closed loop parts from MuJoCo in: on each of ``rows`` (the world model's episodes, in the
    order of :meth:`RankingPlan.wm_starts`), at the end of every chunk, the lift judge's cube height (m; None
    where too few of the cube's points lie near the gripper) and whether it is held up, in the world model's
    episode (``chunk_held``) and in MuJoCo's from the same start (``real_chunk_held``); and the largest
    difference between the two runs' actions within each chunk (``action_gap``, rad): the open-loop policies
    act alike in both, so their verdicts part where the world model draws another outcome."""
    judge = LiftJudge()
    generated = lr.LeRobotDataset(f"local/{generated_root.name}", root=generated_root)
    real = lr.LeRobotDataset(EVAL_REPO, root=plan.eval_dataset)
    index = plan.names.index(slug(policy))
    real_episodes = [plan.eval_episode(index, s) for s in plan.wm_starts()]
    ours = list(range(len(rows)))  # the closed loop writes its episodes in the order of its starts
    steps = plan.chunks * chunk
    gaps = [np.abs(a[:steps] - b[:steps]).reshape(plan.chunks, chunk, -1).max(axis=(1, 2))
            for a, b in zip(_actions(generated, ours), _actions(real, real_episodes))]
    for key, heights in (("", chunk_end_heights(judge, generated, ours, chunk, plan.chunks)),
                         ("real_", chunk_end_heights(judge, real, real_episodes, chunk, plan.chunks))):
        for row, h in zip(rows, heights):
            row[f"{key}chunk_height_m"] = [None if np.isnan(x) else round(float(x), 4) for x in h]
            row[f"{key}chunk_held"] = [bool(x >= judge.lifted_z) for x in h]  # NaN: not held
    for row, gap in zip(rows, gaps):
        row["action_gap"] = [round(float(g), 5) for g in gap]


def chunk_end_heights(judge: LiftJudge, dataset, episodes: list[int], chunk: int, chunks: int) -> list[np.ndarray]:
    """The lift judge's cube height (m, NaN where it sees too few cube points near the gripper) at the last frame
    of each of the first ``chunks`` chunks of ``chunk`` frames (frames ``chunk``, ``2 chunk``, ...; frame 0 is
    the start) of each episode of ``dataset``."""
    at = [chunk * k for k in range(1, chunks + 1)]
    return [judge.heights(ep) for ep in episode_frames(dataset, episodes, [image_key(judge.view)], at=at,
                                                        geometry=True)]


def _actions(dataset, episodes: list[int]) -> list[np.ndarray]:
    """Each episode's actions ``(T, D)``."""
    table = dataset.meta.episodes
    row = {int(e): i for i, e in enumerate(table["episode_index"])}
    return [np.asarray(dataset.hf_dataset.select(range(int(table["dataset_from_index"][row[e]]),
                                                       int(table["dataset_to_index"][row[e]])))["action"], np.float32)
            for e in episodes]


def _classifier(plan: RankingPlan) -> SuccessClassifier | None:
    """The learned judge the judges stage trained, if it trained one."""
    saved = plan.work / "judges" / "classifier"
    return SuccessClassifier.load(saved) if saved.is_dir() else None


def evaluate_mode(plan: RankingPlan, mode: str) -> None:
    """-> ``wm/<mode>/outcomes.json``: every policy's closed loop and the recorded actions' replays (each
    made here unless its own process made it already), the none check, the action sensitivity."""
    torch.set_num_threads(1)
    t0, c0 = time.time(), time.process_time()
    out = plan.wm_dir(mode)
    model, spec = load_world_model(_evaluated(plan, mode), weights="ema", device=plan.device)
    evaluation = lr.LeRobotDataset(EVAL_REPO, root=plan.eval_dataset)
    labels = dataset_success_labels(evaluation)
    starts = _start_episodes(plan)
    replay = recorded_episodes(plan, labels)
    sens_episodes = replay[:4]
    chunks = open_chunks(spec, EVAL_REPO, str(plan.eval_dataset), episodes=sorted(set(starts + replay)))
    online = _online(plan, model, chunks)
    result = {"mode": mode, "start_episodes": starts, "sampler_steps": plan.steps, "policies": {}}
    blind = run_mode(mode).blind
    if blind:
        result["none_check"] = none_is_policy_blind(plan, model, online, chunks, starts[:2])
    for policy in evaluated_policies(plan, mode):
        result["policies"][slug(policy)] = _policy_closed_loop(plan, mode, policy, model, chunks, online)
    if not blind:
        result["recorded"] = replays(plan, mode)
    sens_chunks = open_chunks(spec, EVAL_REPO, str(plan.eval_dataset), episodes=sens_episodes)
    sens_chunks.preload(progress=False)
    sens_starts = [(e, c) for e in sens_episodes for c in (0, 1) if c < len(sens_chunks.episode_chunks(e))]
    sens = open_loop.action_sensitivity(model, sens_chunks, sens_starts, online, offsets=SENSITIVITY_OFFSETS,
                                        steps=plan.steps, seed=plan.seed)
    result["sensitivity"] = {"inside": sens.inside, "outside": sens.outside, "ratio": sens.ratio,
                             "region_share": sens.region_share, "samples": sens.samples,
                             "offsets_rad": SENSITIVITY_OFFSETS}
    torch.save(sens.example, out / "sensitivity_example.pt")
    result.update(wall_s=round(time.time() - t0, 1), cpu_s=round(time.process_time() - c0, 1))
    _write(out / "outcomes.json", result)


__all__ = ["evaluate_mode", "evaluate_policy", "evaluated_policies", "policy_dir", "recorded_episodes", "replays",
           "run_judges"]
