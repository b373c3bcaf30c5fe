"""``imac-model sample``: generate a future chunk of a dataset episode (or roll out N chunks,
controls rebuilt online) and show it beside the recording: an mp4, optionally a still."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from imac_data.console import run_command
from imac_data.errors import InputError
from imac_model.evaluate.pictures import write_mp4, write_png
from imac_model.models.checkpoint import load_world_model, resolve_checkpoint, run_config_of
from imac_model.pipelines.sampling import (
    evaluate_episodes,
    online_controls_for,
    open_chunks,
    robot_region_errors,
    sample_chunk,
    sample_rollout_chunks,
    summary_of,
)


def run(args: argparse.Namespace) -> int:
    return run_command(lambda: _sample(args))


def _sample(args: argparse.Namespace) -> int:
    if len(args.episode) > 1 and not args.evaluate:
        raise InputError("several --episode values need --evaluate")
    path = resolve_checkpoint(args.checkpoint)
    model, spec = load_world_model(path, weights=args.weights, guidance=args.guidance)
    run = run_config_of(path) or {}
    dataset = args.dataset or spec.dataset
    root = args.root if args.root is not None else (run.get("data", {}).get("root") if not args.dataset else None)
    chunks = open_chunks(spec, dataset, root, episodes=args.episode)
    if args.chunks < 1:
        raise InputError(f"--chunks {args.chunks}: must be >= 1")
    if args.chunks > 1:
        return _rollout_main(args, model, spec, chunks, run, path)
    if args.evaluate:
        e = evaluate_episodes(model, chunks, args.episode, steps=args.steps, seed=args.seed)
        print(f"{e['chunks']} chunks of episodes {args.episode} ({path}): {summary_of(e)}")
        return 0
    episode = args.episode[0]
    s = sample_chunk(model, chunks, episode, args.chunk, steps=args.steps, seed=args.seed)
    out = Path(args.out) if args.out else path / "samples" / f"episode_{episode}_chunk_{args.chunk}.mp4"
    out.parent.mkdir(parents=True, exist_ok=True)
    write_mp4(s, out, spec.fps, args.scale)
    if args.png:
        write_png(s, Path(args.png), args.scale)
    print(f"wrote {out}" + (f" and {args.png}" if args.png else "") + f" (episode {episode}, reference frame "
          f"{s.reference_frame}, {int(s.valid.sum())} future frames): {summary_of(robot_region_errors(s))}")
    return 0


def _rollout_main(args, model, spec, chunks, run, path) -> int:
    online = online_controls_for(spec, chunks, run)
    if args.evaluate:
        per_index: dict[int, list[float]] = {}
        for e in args.episode:
            n_items = len(chunks.episode_chunks(e))
            for start in range(0, n_items - args.chunks + 1, args.chunks):
                _, parts, _ = sample_rollout_chunks(model, chunks, e, start, args.chunks, online, steps=args.steps,
                                                    seed=args.seed, recorded_states=args.recorded_states)
                for i, part in enumerate(parts):
                    per_index.setdefault(i, []).append(robot_region_errors(part)["mse"])
        print(f"{len(per_index.get(0, []))} rollouts of {args.chunks} chunks, episodes {args.episode} ({path}): "
              "pixel MSE vs recorded per chunk " + ", ".join(f"{i + 1}: {np.mean(v):.4f}" for i, v in sorted(per_index.items())))
        return 0
    episode = args.episode[0]
    whole, parts, invalid = sample_rollout_chunks(model, chunks, episode, args.chunk, args.chunks, online,
                                                  steps=args.steps, seed=args.seed,
                                                  recorded_states=args.recorded_states)
    out = (Path(args.out) if args.out else
           path / "samples" / f"episode_{episode}_chunk_{args.chunk}_x{args.chunks}.mp4")
    out.parent.mkdir(parents=True, exist_ok=True)
    write_mp4(whole, out, spec.fps, args.scale)
    if args.png:
        write_png(whole, Path(args.png), args.scale)
    errors = ", ".join(f"{i + 1}: {robot_region_errors(p)['mse']:.4f}" for i, p in enumerate(parts))
    extra = f"; invalid generated depth at the boundaries {np.round(invalid, 4).tolist()}" if invalid else ""
    print(f"wrote {out}" + (f" and {args.png}" if args.png else "") + f" (episode {episode}, {args.chunks} chunks "
          f"from reference frame {whole.reference_frame}): pixel MSE vs recorded per chunk {errors}{extra}")
    return 0
