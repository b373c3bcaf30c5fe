"""``python -m imac_model.evaluate``: evaluation from the command line.

Subcommands (each writes a JSON with its protocol; ``--help`` on each lists its options):

* ``closed-loop``: run a policy in the world model from a real dataset's start frames and
  write the generated episodes as a LeRobot dataset (:mod:`imac_model.evaluate.closed_loop`);
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

import argparse
import csv
import json
import math
import os
import sys
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from imac_data.errors import InputError

# --------------------------------------------------------------------------- strict JSON


def json_ready(tree, path: str = "", found: dict | None = None):
    """``tree`` with every non-finite float replaced by None (recorded in ``found`` as
    ``{dotted.path: "inf" | "-inf" | "nan"}``), numpy scalars as Python numbers, paths and
    tuples as strings and lists."""
    found = {} if found is None else found
    if isinstance(tree, Mapping):
        return {str(k): json_ready(v, f"{path}.{k}" if path else str(k), found) for k, v in tree.items()}
    if isinstance(tree, (list, tuple)):
        return [json_ready(v, f"{path}[{i}]", found) for i, v in enumerate(tree)]
    if isinstance(tree, (bool, np.bool_)):
        return bool(tree)
    if isinstance(tree, (int, np.integer)):
        return int(tree)
    if isinstance(tree, (float, np.floating)):
        x = float(tree)
        if math.isfinite(x):
            return x
        found[path] = "nan" if math.isnan(x) else ("inf" if x > 0 else "-inf")
        return None
    if isinstance(tree, Path):
        return str(tree)
    if isinstance(tree, np.ndarray):
        return json_ready(tree.tolist(), path, found)
    return tree


def write_json(path: str | Path, result: Mapping) -> Path:
    """Write ``result`` as strict JSON (see :func:`json_ready`), atomically."""
    found: dict = {}
    clean = json_ready(result, "", found)
    if found:
        clean["nonfinite"] = found
    text = json.dumps(clean, indent=2, allow_nan=False)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text + "\n")
    os.replace(tmp, path)
    return path


# --------------------------------------------------------------------------- shared pieces


def load_checkpoint(path: str, *, mode: str | None = None, weights: str = "ema", device: str = "cpu"):
    """``(model, spec, checkpoint dir, run config)``; with ``mode``, refuse a checkpoint
    trained with another conditioning mode."""
    from imac_model.checkpoint import load_world_model, read_spec, resolve_checkpoint, run_config_of
    from imac_model.config import MODES

    ckpt = resolve_checkpoint(path)
    spec = read_spec(ckpt)
    if mode is not None:
        if mode not in MODES:
            raise InputError(f"--mode {mode!r}: must be one of {list(MODES)}")
        if spec.conditioning.mode != mode:
            raise InputError(f"{ckpt}: the checkpoint was trained with conditioning mode "
                             f"{spec.conditioning.mode!r}, not {mode!r} (its model.json); evaluate it with "
                             f"--mode {spec.conditioning.mode} or pick a {mode} checkpoint")
    model, spec = load_world_model(ckpt, weights=weights, device=device)
    return model, spec, ckpt, run_config_of(ckpt) or {}


def open_source(spec, run: Mapping, dataset: str | None, root: str | None, episodes=None):
    """The source dataset's chunks (default: the one the model was trained on)."""
    from imac_model.sample import open_chunks

    repo = dataset or spec.dataset
    if root is None and not dataset:
        root = (run.get("data") or {}).get("root")
    return open_chunks(spec, repo, root, episodes=episodes)


def default_episodes(chunks, run: Mapping) -> list[int]:
    """The run's held-out episodes, or else every episode of the dataset."""
    held = list((run.get("data") or {}).get("held_out_episodes") or [])
    return held or list(range(chunks.lerobot.meta.total_episodes))


def _online(spec, chunks, run):
    from imac_model.online_controls import OnlineControls
    from imac_model.sample import online_controls_for

    return online_controls_for(spec, chunks, run) or OnlineControls.from_dataset(
        chunks.lerobot.root, spec, info=chunks.lerobot.meta.info)


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
    from imac_model.evaluate.closed_loop import ClosedLoopConfig, run_closed_loop
    from imac_model.evaluate.policies import load_policy

    model, spec, ckpt, run = load_checkpoint(args.checkpoint, mode=args.mode, weights=args.weights, device=args.device)
    chunks = open_source(spec, run, args.dataset, args.root)
    episodes = args.episodes if args.episodes is not None else default_episodes(chunks, run)
    config = ClosedLoopConfig(episodes=tuple(episodes), horizon_chunks=args.horizon_chunks,
                              sampler_steps=args.steps, seed=args.seed, judge_frames=args.judge_frames)
    policy = "recorded" if args.policy == "recorded" else load_policy(
        args.policy, camera_map=_camera_map(args.camera_map), device=args.device)
    judge = None
    if args.success_classifier:
        from imac_model.evaluate.success import SuccessClassifier

        judge = SuccessClassifier.load(args.success_classifier)
        wanted = {f"observation.images.{v}" for v in spec.views}
        missing = [c for c in judge.config.cameras if c not in wanted]
        if missing:
            raise InputError(f"{args.success_classifier}: the classifier reads cameras {missing}, which the world "
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


def cmd_video_metrics(args) -> int:
    from imac_model import mosaic
    from imac_model.evaluate.open_loop import rollout_starts, rollout_videos
    from imac_model.evaluate.video_metrics import VideoMetricsConfig, compute_video_metrics

    model, spec, ckpt, run = load_checkpoint(args.checkpoint, mode=args.mode, weights=args.weights, device=args.device)
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
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    from imac_model.evaluate.success import CsvJudge

    root = Path(args.dataset)
    if not (root / "meta" / "info.json").is_file():
        raise InputError(f"{root} is not a LeRobot dataset (no meta/info.json)")
    meta = LeRobotDatasetMetadata(args.repo_id or f"local/{root.name}", root=root)
    table = meta.episodes
    episodes = [int(e) for e in table["episode_index"]]
    sources = table["imac/source"] if "imac/source" in table.column_names else [None] * len(episodes)
    if any(s != "world_model" for s in sources):
        raise InputError(f"{root}: only datasets of generated episodes (imac/source = world_model, written by "
                         "`closed-loop`) are labelled in place; a recorded dataset is never modified")
    judge = CsvJudge.from_csv(args.labels, known_episodes=episodes)
    import pyarrow as pa

    from imac_data.dataset.columns import add_episode_columns

    missing = [e for e in episodes if e not in judge.labels]
    rows = [{"imac/success": judge.labels.get(e)} for e in episodes]
    add_episode_columns(root, rows, {"imac/success": pa.bool_()})
    result = {"dataset": str(root), "labels": str(args.labels), "labelled": len(judge.labels),
              "unlabelled_episodes": missing,
              "success": {str(e): judge.labels[e] for e in sorted(judge.labels)},
              "success_rate": float(np.mean(list(judge.labels.values())))}
    if args.json:
        write_json(args.json, result)
    print(f"labelled {len(judge.labels)} of {len(episodes)} episodes of {root} (success rate "
          f"{result['success_rate']:.3f})" + (f"; no label for {missing}" if missing else ""))
    return 0


_SOURCES = {"world_model": "world_model", "wm": "world_model", "world-model": "world_model", "real": "real"}


def read_outcomes(path: str | Path) -> tuple[dict, dict]:
    """Per-episode outcomes ``(world_model, real)``, each ``{policy or (policy, group): [0/1 ...]}``,
    from a CSV (columns ``policy``, ``source`` = world_model | real, ``success``; optional
    ``group``) or a JSON ``{"world_model": {policy: [..] or {group: [..]}}, "real": {...}}``."""
    from imac_model.evaluate.success import _FALSE, _TRUE

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: outcomes file not found")
    sides: dict[str, dict] = {"world_model": {}, "real": {}}
    if path.suffix.lower() == ".json":
        try:
            data = json.loads(path.read_text())
        except json.JSONDecodeError as e:
            raise InputError(f"{path}: not JSON ({e})") from None
        if not isinstance(data, dict) or set(data) != {"world_model", "real"}:
            raise InputError(f"{path}: expected an object with exactly the keys 'world_model' and 'real'")
        for side, policies in data.items():
            if not isinstance(policies, dict):
                raise InputError(f"{path}: {side!r} must map policies to outcome lists (or groups to lists)")
            for policy, v in policies.items():
                if isinstance(v, dict):
                    for group, outcomes in v.items():
                        sides[side][(policy, group)] = outcomes
                else:
                    sides[side][policy] = v
        return sides["world_model"], sides["real"]
    with path.open(newline="") as f:
        reader = csv.DictReader(f)
        columns = [c.strip() for c in (reader.fieldnames or [])]
        for col in ("policy", "source", "success"):
            if col not in columns:
                raise InputError(f"{path}: missing column {col!r} (columns: {columns}); expected "
                                 "policy,group,source,success with source world_model or real")
        grouped = "group" in columns
        for line, row in enumerate(reader, start=2):
            row = {k.strip(): (v or "").strip() for k, v in row.items() if k is not None}
            side = _SOURCES.get(row["source"].lower())
            if side is None:
                raise InputError(f"{path}:{line}: source {row['source']!r} is not world_model or real")
            value = row["success"].lower()
            if value in _TRUE | _FALSE:
                outcome = 1.0 if value in _TRUE else 0.0
            else:
                try:
                    outcome = float(value)
                except ValueError:
                    raise InputError(f"{path}:{line}: success {row['success']!r} is not 1/0, true/false or a "
                                     "score") from None
            key = (row["policy"], row["group"]) if grouped and row.get("group") else row["policy"]
            sides[side].setdefault(key, []).append(outcome)
    if not sides["world_model"] and not sides["real"]:
        raise InputError(f"{path}: no outcomes")
    return sides["world_model"], sides["real"]


def cmd_correlate(args) -> int:
    from imac_model.evaluate.statistics import plot_policy_scatter, policy_correlation

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


# --------------------------------------------------------------------------- parser


def _model_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--checkpoint", required=True, help="world-model checkpoint directory or run directory")
    p.add_argument("--mode", help="the conditioning mode you mean to evaluate; a checkpoint trained with another "
                                  "is refused (none, motion, motion+contact, action-vector)")
    p.add_argument("--dataset", help="LeRobot repo id of the source dataset (default: the model's)")
    p.add_argument("--root", help="source dataset directory (default: the training run's)")
    p.add_argument("--episodes", type=int, nargs="+",
                   help="start episodes (default: the run's held-out episodes, else all)")
    p.add_argument("--steps", type=int, help="sampler (Euler) steps (default: the model's flow.sample_steps)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--weights", choices=("ema", "raw"), default="ema")
    p.add_argument("--device", default="cpu")
    p.add_argument("--no-progress", action="store_true")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m imac_model.evaluate",
                                description="Evaluation of the world model: closed-loop policy evaluation, open-loop "
                                            "video metrics, success labels, world-model vs real correlations.")
    sub = p.add_subparsers(dest="command", required=True)

    c = sub.add_parser("closed-loop", help="run a policy in the world model; write a LeRobot dataset of its episodes")
    _model_args(c)
    c.add_argument("--policy", required=True,
                   help="recorded (replay each start episode's actions), hold, lerobot:DIR (a LeRobot policy "
                        "checkpoint directory) or python:MODULE:NAME (a callable observation -> (K, D) actions)")
    c.add_argument("--camera-map", nargs="+", metavar="POLICY_KEY=VIEW",
                   help="lerobot policies: which world-model view feeds each of the policy's camera keys "
                        "(default: observation.images.X reads view X)")
    c.add_argument("--output", required=True, help="directory of the LeRobot dataset of generated episodes")
    c.add_argument("--repo-id", help="its repo id (default local/<output name>)")
    c.add_argument("--overwrite", action="store_true")
    c.add_argument("--horizon-chunks", type=int,
                   help="world-model chunks per episode (default: enough to cover each recorded episode)")
    c.add_argument("--success-classifier", help="a saved SuccessClassifier directory: judges every episode")
    c.add_argument("--judge-frames", type=int, default=4, help="last frames per view the judge sees")
    c.add_argument("--json", help="result JSON (default <output>/closed_loop.json)")
    c.set_defaults(func=cmd_closed_loop)

    v = sub.add_parser("video-metrics", help="rollouts of the recorded actions against the recording")
    _model_args(v)
    v.add_argument("--chunks", type=int, default=1, help="chunks per rollout (default 1)")
    v.add_argument("--metrics", nargs="+", default=["mse", "psnr", "ssim"],
                   help="of mse psnr ssim fid fvd (FID/FVD need local weights, see the README)")
    v.add_argument("--fid-weights", help="FID Inception weights file (default under $XDG_CACHE_HOME/imac/weights)")
    v.add_argument("--fvd-weights", help="FVD I3D weights file (default under $XDG_CACHE_HOME/imac/weights)")
    v.add_argument("--batch-size", type=int, default=8)
    v.add_argument("--json", required=True, help="result JSON")
    v.set_defaults(func=cmd_video_metrics)

    lab = sub.add_parser("label", help="import success labels (CSV episode_index,success) into generated episodes")
    lab.add_argument("--dataset", required=True, help="directory of a dataset written by closed-loop")
    lab.add_argument("--labels", required=True, help="CSV with columns episode_index, success")
    lab.add_argument("--repo-id")
    lab.add_argument("--json", help="also write the labels and success rate here")
    lab.set_defaults(func=cmd_label)

    r = sub.add_parser("correlate", help="world-model vs real success: correlations, MMRV, bootstrap, scatter plot")
    r.add_argument("--outcomes", required=True,
                   help="CSV (policy,group,source,success; source world_model or real) or JSON "
                        "{world_model: {policy: [..]}, real: {...}}")
    r.add_argument("--json", required=True, help="result JSON")
    r.add_argument("--png", help="scatter plot (PNG)")
    r.add_argument("--title")
    r.add_argument("--replicates", type=int, default=2000)
    r.add_argument("--confidence", type=float, default=0.95)
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--paired", action="store_true", help="resample world-model and real episodes together")
    r.add_argument("--normalize", default="none", choices=("none", "max", "minmax"),
                   help="rates normalised per side before the statistics (default none)")
    r.add_argument("--interval", default="bc", choices=("bc", "percentile", "basic"),
                   help="bootstrap interval (default bc, bias-corrected)")
    r.set_defaults(func=cmd_correlate)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except InputError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2


__all__ = ["build_parser", "json_ready", "load_checkpoint", "main", "read_outcomes", "write_json"]
