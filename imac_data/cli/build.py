"""``imac build``: a recipe -> a dataset with every added stream (the main job)."""

from __future__ import annotations

import argparse
import time

from imac_data.build.flow import build_dataset
from imac_data.build.staging import BuildRequest
from imac_data.console import quiet_libraries, run_command, silence_progress_bars
from imac_data.dataset.card import push_to_hub
from imac_data.errors import InputError
from imac_data.lerobot_compat import default_root
from imac_data.recipes import find_recipe, load_recipe


def run(args: argparse.Namespace) -> int:
    quiet_libraries()
    if args.no_progress:
        silence_progress_bars()
    return run_command(lambda: _build(args))


def _build(args: argparse.Namespace) -> int:
    t0 = time.perf_counter()
    if "/" not in args.repo:
        raise InputError(f"--repo must look like <user>/<name>, got {args.repo!r}")
    recipe = load_recipe(args.recipe or find_recipe(args.repo.split("/", 1)[1]))
    if args.episodes is not None and args.episodes <= 0:
        raise InputError(f"--episodes must be positive, got {args.episodes}")
    if args.source is not None and not args.source.exists():
        raise InputError(f"--source: path does not exist: {args.source}")
    if args.workers is not None and args.workers <= 0:
        raise InputError(f"--workers must be positive, got {args.workers}")
    req = BuildRequest(repo_id=args.repo, recipe=recipe, root=args.root or default_root(args.repo),
                       source_path=args.source, episodes=args.episodes, overwrite=args.overwrite,
                       progress=not args.no_progress, timings=args.timings, wait=args.wait,
                       device=args.device)
    dataset = build_dataset(req, executor=args.executor, workers=args.workers, ray_address=args.ray_address)
    dt = time.perf_counter() - t0
    if args.push_to_hub:
        push_to_hub(req.root, args.repo, recipe, private=args.private)
        print(f"pushed {args.repo} to the hub")
    size = sum(f.stat().st_size for f in req.root.rglob("*") if f.is_file())
    frames = dataset.meta.total_frames
    print(f"built {args.repo}: {dataset.meta.total_episodes} episodes, {frames} frames in {dt:.1f} s "
          f"({frames / dt:.1f} frames/s), {size / 1e6:.1f} MB at {req.root}")
    return 0
