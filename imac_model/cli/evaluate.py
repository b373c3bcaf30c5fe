"""``imac-model evaluate``: evaluation from the command line.

Subcommands (each writes a JSON with its protocol; ``--help`` on each lists its options):

* ``closed-loop``: run a policy in the world model from a real dataset's start frames and
  write the generated episodes as a LeRobot dataset (:mod:`imac_model.evaluate.closed_loop`);
* ``simulator``: run a policy in MuJoCo under the same observation contract and write its
  episodes, with MuJoCo's success labels, for ``imac build`` (:mod:`imac_model.evaluate.simulator`);
* ``video-metrics``: MSE/PSNR/SSIM (and FID/FVD with local weights) of N-chunk rollouts of the
  recorded actions against the recording (:mod:`imac_model.evaluate.open_loop`,
  :mod:`imac_model.evaluate.video_metrics`);
* ``label``: import per-episode success labels (a CSV scored by people) into a dataset of
  generated episodes;
* ``correlate``: world-model vs real success over policies and groups, from a CSV or JSON of
  per-episode successes (:mod:`imac_model.evaluate.statistics`), with the scatter plot.

JSON output is strict: a non-finite number (PSNR of identical frames is +inf) is written as
``null`` and listed, with its value, under ``"nonfinite"`` (:func:`json_ready`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from imac_data import lerobot_compat as lr
from imac_data.console import run_command
from imac_data.dataset.columns import add_episode_columns
from imac_data.dataset.output import check_output
from imac_data.errors import InputError
from imac_data.layout import SUCCESS_COLUMN, info_path
from imac_data.metadata import dataset_info
from imac_model.data import mosaic
from imac_model.evaluate.closed_loop import ClosedLoopConfig, run_closed_loop
from imac_model.evaluate.open_loop import rollout_starts, rollout_videos
from imac_model.evaluate.policies import load_policy
from imac_model.evaluate.results import read_outcomes, write_json
from imac_model.evaluate.simulator import SimRunConfig, parse_seeds, run_policy
from imac_model.evaluate.statistics import plot_policy_scatter, policy_correlation
from imac_model.evaluate.success import CsvJudge, SuccessClassifier, load_judge
from imac_model.evaluate.video_metrics import VideoMetricsConfig, compute_video_metrics
from imac_model.models.checkpoint import load_world_model, read_spec, resolve_checkpoint, run_config_of
from imac_model.modes import MODES
from imac_model.pipelines.online_controls import OnlineControls
from imac_model.pipelines.sampling import online_controls_for, open_chunks


def load_checkpoint(path: str, *, mode: str | None = None, weights: str = "ema", device: str = "cpu",
                    guidance: float | None = None):
    """``(model, spec, checkpoint dir, run config)``; with ``mode``, refuse a checkpoint
    trained with another conditioning mode; ``guidance``: the sampler's, instead of the saved one."""
    ckpt = resolve_checkpoint(path)
    spec = read_spec(ckpt)
    if mode is not None:
        if mode not in MODES:
            raise InputError(f"--mode {mode!r}: must be one of {list(MODES)}")
        if spec.conditioning.mode != mode:
            raise InputError(f"{ckpt}: the checkpoint was trained with conditioning mode "
                             f"{spec.conditioning.mode!r}, not {mode!r} (its model.json); evaluate it with "
                             f"--mode {spec.conditioning.mode} or pick a {mode} checkpoint")
    model, spec = load_world_model(ckpt, weights=weights, device=device, guidance=guidance)
    return model, spec, ckpt, run_config_of(ckpt) or {}


def open_source(spec, run: Mapping, dataset: str | None, root: str | None, episodes=None):
    """The source dataset's chunks (default: the one the model was trained on)."""
    repo = dataset or spec.dataset
    if root is None and not dataset:
        root = (run.get("data") or {}).get("root")
    return open_chunks(spec, repo, root, episodes=episodes)


def default_episodes(chunks, run: Mapping) -> list[int]:
    """The run's held-out episodes, or else every episode of the dataset."""
    held = list((run.get("data") or {}).get("held_out_episodes") or [])
    return held or list(range(chunks.lerobot.meta.total_episodes))


def _online(spec, chunks, run):
    return online_controls_for(spec, chunks, run) or OnlineControls.from_dataset(
        chunks.lerobot.root, spec, info=dataset_info(chunks.lerobot.meta))


def _camera_map(items) -> dict[str, str] | None:
    if not items:
        return None
    out = {}
    for item in items:
        if "=" not in item:
            raise InputError(f"--camera-map {item!r}: expected POLICY_KEY=VIEW, e.g. observation.images.top=cam_high")
        k, v = item.split("=", 1)
        out[k.strip()] = v.strip()
    return out


# --------------------------------------------------------------------------- subcommands


def cmd_closed_loop(args) -> int:
    # a user's directory given as --output, or a staging path next to it that is not ours: refused before any work
    check_output(Path(args.output), overwrite=args.overwrite, what="--output")
    model, spec, ckpt, run = load_checkpoint(args.checkpoint, mode=args.mode, weights=args.weights, device=args.device,
                                             guidance=args.guidance)
    chunks = open_source(spec, run, args.dataset, args.root)
    episodes = args.episodes if args.episodes is not None else default_episodes(chunks, run)
    config = ClosedLoopConfig(episodes=tuple(episodes), horizon_chunks=args.horizon_chunks,
                              sampler_steps=args.steps, seed=args.seed, judge_frames=args.judge_frames)
    policy = "recorded" if args.policy == "recorded" else load_policy(
        args.policy, camera_map=_camera_map(args.camera_map), device=args.device)
    if args.success_classifier and args.judge:
        raise InputError("give --judge or --success-classifier (the same as --judge classifier:DIR), not both")
    spec_of_judge = f"classifier:{args.success_classifier}" if args.success_classifier else args.judge
    judge = load_judge(spec_of_judge) if spec_of_judge else None
    if isinstance(judge, SuccessClassifier):
        wanted = {f"observation.images.{v}" for v in spec.views}
        missing = [c for c in judge.config.cameras if c not in wanted]
        if missing:
            raise InputError(f"{spec_of_judge}: the classifier reads cameras {missing}, which the world "
                             f"model does not generate (views {list(spec.views)})")
    output = Path(args.output)
    result = run_closed_loop(model, chunks, _online(spec, chunks, run), policy, output, config=config,
                             repo_id=args.repo_id or f"local/{output.name}", judge=judge, checkpoint=str(ckpt),
                             overwrite=args.overwrite, progress=not args.no_progress)
    out = write_json(args.json or output / "closed_loop.json", result.to_dict())
    rate = result.to_dict()["success_rate"]
    print(f"wrote {len(result.episodes)} generated episodes to {output} and {out}"
          + ("" if rate is None else f"; success rate {rate:.3f} ({judge.name})"))
    return 0


def cmd_simulator(args) -> int:
    config = SimRunConfig(task=args.task, chunks=args.chunks, chunk=args.chunk, view_height=args.view_size[0],
                          view_width=args.view_size[1], render_height=args.render_size[0],
                          render_width=args.render_size[1], views=tuple(args.views), settle_s=args.settle)
    seeds = parse_seeds(args.seeds)
    output = Path(args.output) if args.output else None
    if output is not None and any(output.glob("episode_*.hdf5")):
        raise InputError(f"--output {output} already holds episodes; choose an empty directory")
    policy = load_policy(args.policy)
    rows = run_policy(policy, seeds, output, config=config, progress=not args.no_progress)
    rate = float(np.mean([r["success"] for r in rows]))
    result = {"policy": args.policy, "task": args.task,
              "protocol": {**dataclasses.asdict(config), "success": "read off MuJoCo",
                           "observation": f"{config.view_height}x{config.view_width} views (RGB antialiased, depth "
                                          f"area-resized) of a {config.render_height}x{config.render_width} render"},
              "episodes": rows, "success_rate": rate}
    json_path = args.json or (output / "outcomes.json" if output is not None else None)
    if json_path:
        write_json(json_path, result)
    print(f"{args.policy} on {args.task}: success {sum(r['success'] for r in rows)}/{len(rows)} ({rate:.3f})"
          + (f"; episodes in {output}" if output is not None else ""))
    return 0


def cmd_video_metrics(args) -> int:
    model, spec, ckpt, run = load_checkpoint(args.checkpoint, mode=args.mode, weights=args.weights, device=args.device,
                                             guidance=args.guidance)
    chunks = open_source(spec, run, args.dataset, args.root)
    episodes = args.episodes if args.episodes is not None else default_episodes(chunks, run)
    bad = [e for e in episodes if not 0 <= e < chunks.lerobot.meta.total_episodes]
    if bad:
        raise InputError(f"--episodes {bad}: the dataset has episodes 0..{chunks.lerobot.meta.total_episodes - 1}")
    if args.chunks < 1:
        raise InputError(f"--chunks {args.chunks}: must be >= 1")
    config = VideoMetricsConfig(metrics=tuple(args.metrics), mosaic_rows=1, batch_size=args.batch_size,
                                device=args.device)
    starts = rollout_starts(chunks, episodes, args.chunks, args.chunks)
    if not starts:
        raise InputError(f"episodes {episodes}: no {args.chunks}-chunk rollout fits inside them")
    online = _online(spec, chunks, run)
    videos = rollout_videos(model, chunks, starts, args.chunks, online, steps=args.steps, seed=args.seed,
                            batch_size=args.batch_size, progress=not args.no_progress)
    V = len(spec.views)
    g_rgb, _ = mosaic.split(videos.generated, V)  # (N, T, V, 3, h, w) uint8
    r_rgb, _ = mosaic.split(videos.recorded, V)
    tasks_col = chunks.lerobot.meta.episodes["tasks"]
    tasks = [(tasks_col[e][0] if tasks_col[e] else "") or "task" for e, _ in starts]
    result = compute_video_metrics({v: g_rgb[:, :, i] for i, v in enumerate(spec.views)},
                                   {v: r_rgb[:, :, i] for i, v in enumerate(spec.views)}, tasks=tasks,
                                   sampler_steps=args.steps or spec.flow.sample_steps, seed=args.seed, config=config,
                                   fid_weights=args.fid_weights, fvd_weights=args.fvd_weights,
                                   protocol_extra={"checkpoint": str(ckpt), "conditioning_mode": spec.conditioning.mode,
                                                   "chunks": args.chunks, "chunk_frames": spec.chunk,
                                                   "starts": [list(s) for s in starts],
                                                   "rollout": "recorded actions; chunk 1 with the dataset's controls, "
                                                              "later chunks from generated frames, controls rebuilt "
                                                              "online",
                                                   "invalid_depth": videos.invalid_depth})
    out = write_json(args.json, result)
    pooled = result["pooled"].get("mosaic") or result["pooled"][spec.views[0]]
    shown = ", ".join(f"{k} {v:.4f}" if isinstance(v, float) and math.isfinite(v) else f"{k} {v}"
                      for k, v in pooled.items() if k != "n_samples")
    print(f"wrote {out}: {len(starts)} rollouts of {args.chunks} chunk(s); pooled: {shown}")
    return 0


def cmd_label(args) -> int:
    root = Path(args.dataset)
    if not info_path(root).is_file():
        raise InputError(f"{root} is not a LeRobot dataset (no meta/info.json)")
    meta = lr.LeRobotDatasetMetadata(args.repo_id or f"local/{root.name}", root=root)
    table = meta.episodes
    episodes = [int(e) for e in table["episode_index"]]
    sources = table["imac/source"] if "imac/source" in table.column_names else [None] * len(episodes)
    if any(s != "world_model" for s in sources):
        raise InputError(f"{root}: only datasets of generated episodes (imac/source = world_model, written by "
                         "`closed-loop`) are labelled in place; a recorded dataset is never modified")
    judge = CsvJudge.from_csv(args.labels, known_episodes=episodes)
    import pyarrow as pa

    missing = [e for e in episodes if e not in judge.labels]
    rows = [{SUCCESS_COLUMN: judge.labels.get(e)} for e in episodes]
    add_episode_columns(root, rows, {SUCCESS_COLUMN: pa.bool_()})
    result = {"dataset": str(root), "labels": str(args.labels), "labelled": len(judge.labels),
              "unlabelled_episodes": missing,
              "success": {str(e): judge.labels[e] for e in sorted(judge.labels)},
              "success_rate": float(np.mean(list(judge.labels.values())))}
    if args.json:
        write_json(args.json, result)
    print(f"labelled {len(judge.labels)} of {len(episodes)} episodes of {root} (success rate "
          f"{result['success_rate']:.3f})" + (f"; no label for {missing}" if missing else ""))
    return 0


def cmd_correlate(args) -> int:
    wm, real = read_outcomes(args.outcomes)
    result = policy_correlation(wm, real, replicates=args.replicates, confidence=args.confidence, seed=args.seed,
                                paired=args.paired, normalize=args.normalize, interval=args.interval)
    result["source"] = str(args.outcomes)
    if args.png:
        plot_policy_scatter(result, args.png, title=args.title)
    out = write_json(args.json, result)
    g = result["levels"]["group"]
    fmt = lambda v: "n/a" if v is None else f"{v:.3f}"  # noqa: E731
    print(f"wrote {out}" + (f" and {args.png}" if args.png else "") + f": {g['n_points']} points, "
          f"pearson {fmt(g['pearson']['value'])}, spearman {fmt(g['spearman']['value'])}, "
          f"kendall {fmt(g['kendall']['value'])}, mmrv {fmt(g['mmrv']['value'])}")
    return 0


def run(args) -> int:
    body = {"closed-loop": cmd_closed_loop, "simulator": cmd_simulator, "video-metrics": cmd_video_metrics, "label": cmd_label,
            "correlate": cmd_correlate}[args.evaluate_command]
    return run_command(lambda: body(args))
