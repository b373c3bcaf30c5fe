"""A build from raw HDF5 episodes (recorded, or simulated on the fly): one shard per episode,
built by the workers, merged, carded, validated and swapped into place."""

from __future__ import annotations

import functools
import hashlib
import json
import resource
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path

import torch
from tqdm.auto import tqdm

import imac_data
from imac_data import lerobot_compat as lr
from imac_data.augment.timing import StageTimer
from imac_data.build.staging import BuildRequest, staged_output
from imac_data.build.workers import ShardJob, cpu_cores, default_workers, run_jobs, run_local, threads_per_worker
from imac_data.core.cameras import same_aspect
from imac_data.core.rig import Rig
from imac_data.core.robot.description import description_bytes, write_description
from imac_data.core.robot.joint_ranges import joint_range_warning
from imac_data.core.robot.lerobot_units import units_refusal
from imac_data.core.robot.platforms import simulated_platforms
from imac_data.dataset.card import write_card
from imac_data.dataset.ingest import BaseWriter, IngestOptions
from imac_data.dataset.merge import MERGE_FAN_IN, merge_datasets
from imac_data.dataset.output import check_output, estimate_build_bytes, refuse_overlap, warn_if_short_of_space
from imac_data.errors import InputError
from imac_data.layout import CALIBRATION, cache_home
from imac_data.recipes import Recipe, joint_units
from imac_data.sources.depth import check_depth_inputs
from imac_data.sources.hdf5 import EpisodeReader, check_episodes, episode_paths
from imac_data.sources.sim.recorder import SimConfig, record_dataset

__all__ = ["build_from_episodes", "ingest_episodes", "source_episodes", "build_key"]


def source_episodes(req: BuildRequest) -> tuple[list[Path], Path]:
    """The episode files to build and the calibration file that goes with them."""
    recipe, src = req.recipe, req.recipe.source
    n = req.episodes if req.episodes is not None else src.episodes
    path = req.source_path or recipe.resolve_path(src.path)
    if src.type in simulated_platforms() and (path is None or not path.exists()):  # the simulator records it
        path = record_sim_episodes(recipe, n, path, req.progress)
    if path is None or not path.exists():
        raise InputError(f"source path does not exist: {path}")
    paths = episode_paths(path)
    if n is not None:
        if n > len(paths):
            raise InputError(f"{path}: asked for {n} episodes, the directory has {len(paths)}")
        paths = paths[:n]
    calibration = recipe.resolve_path(recipe.cameras.calibration) or path / CALIBRATION
    if not calibration.is_file():
        raise InputError(
            f"calibration file not found: {calibration} (set cameras.calibration in {recipe.file or 'the recipe'})"
        )
    return paths, calibration


def record_sim_episodes(recipe: Recipe, n: int | None, path: Path | None, progress: bool) -> Path:
    """Record the recipe's simulated episodes (once; later builds reuse them)."""
    sim = recipe.source.sim
    config = SimConfig(task=sim.task, num_episodes=n or 2, width=sim.width, height=sim.height, seed=sim.seed,
                       noise=sim.noise, frame_stride=sim.frame_stride, with_segmentation=sim.segmentation)
    if path is None:
        key = hashlib.sha256(json.dumps(asdict(config), sort_keys=True).encode()).hexdigest()[:12]
        path = cache_home() / "sim" / f"{recipe.name}-{key}"
    if (path / CALIBRATION).is_file() and len(list(path.glob("episode_*.hdf5"))) >= config.num_episodes:
        return path
    print(f"[build] recording {config.num_episodes} simulated {sim.task} episodes into {path}", file=sys.stderr)
    record_dataset(config, path, progress=progress, overwrite=True)
    return path


def build_key(recipe: Recipe, paths: list[Path], calibration_path: Path, repo_id: str, rig_block: dict) -> str:
    """What a resumable staging directory was built for: the recipe, the source files (path,
    size, mtime), the calibration, the rig (with the sha256 of the URDF and every mesh) and our
    code. A different key starts over."""
    h = hashlib.sha256()
    h.update(json.dumps([repo_id, imac_data.__version__, repr(recipe), rig_block], default=str,
                        sort_keys=True).encode())
    for src in sorted(Path(imac_data.__file__).parent.rglob("*.py")):  # the code that made the shards
        h.update(src.read_bytes())
    for p in [*paths, calibration_path]:
        st = p.stat()
        h.update(f"{p.resolve()}|{st.st_size}|{st.st_mtime_ns}".encode())
    return h.hexdigest()


def build_from_episodes(req: BuildRequest, robot, *, executor: str = "local", workers: int | None = None,
                        ray_address: str | None = None, t_start: float | None = None,
                        usage_start: float | None = None) -> None:
    """Build ``req`` from HDF5 episodes with the recipe's ``robot`` already loaded."""
    t_start = t_start if t_start is not None else time.perf_counter()
    usage_start = usage_start if usage_start is not None else cpu_seconds()
    recipe = req.recipe
    paths, calibration_path = source_episodes(req)
    refuse_overlap(req.root, {"source episodes": paths[0].parent, "calibration": calibration_path})
    rig = Rig.from_recipe(recipe, calibration_path, robot=robot)
    probe = check_episodes(paths, rig.cameras, robot)
    warning = joint_range_warning(robot, *probe["qpos_range"], source=f"the episodes in {paths[0].parent}",
                                  recipe=recipe.file or "the recipe")
    if warning:
        print(warning, file=sys.stderr)
    units = joint_units(recipe)  # the LeRobot units the joint map takes: values they cannot record are refused
    refusal = units and units_refusal(units, *probe["qpos_range"], source=f"the episodes in {paths[0].parent}",
                                      recipe=recipe.file or "the recipe")
    if refusal:
        raise InputError(refusal)
    check_depth_inputs(recipe.depth, recipe.file, len(rig.names))
    _check_stream_resolution(recipe, rig.cameras)
    need = estimate_build_bytes(probe["total_frames"], probe["image_hw"], recipe.augment.resolution,
                                description_bytes(robot), copies=3 if len(paths) > MERGE_FAN_IN else 2)
    warn_if_short_of_space(req.root, need)
    fps = recipe.fps if recipe.fps is not None else probe["fps"]  # check_episodes: the same in every episode
    if fps is None:
        raise InputError(f"{recipe.file}: fps: the episodes do not record their rate; set fps in the recipe")
    if not float(fps).is_integer():  # LeRobot stores an integer fps and stamps frame i at i / fps
        raise InputError(f"{paths[0]}: attribute 'fps' is {fps}: a LeRobot dataset has a whole number of frames per "
                         "second; set fps in the recipe to the rate its timestamps should use")
    defaults = recipe.source.episode_defaults
    options = IngestOptions(fps=fps, task=recipe.task, source=defaults.source, policy_name=defaults.policy_name,
                            checkpoint=defaults.checkpoint, robot_type=robot.name, state_names=rig.state_names)

    block = rig.to_info()
    key = build_key(recipe, paths, calibration_path, req.repo_id, block)
    timer = StageTimer()  # the build's own stages, in this process
    with staged_output(req.root, overwrite=req.overwrite, wait=req.wait, key=key, timer=timer) as stage:
        (stage.dir / "shards").mkdir(exist_ok=True)
        description = stage.dir / "robot"
        write_description(robot, description)
        workers = workers or default_workers(len(paths))
        threads = threads_per_worker(min(workers, len(paths)))
        jobs = [ShardJob(i, p, stage.dir / "shards" / f"episode_{i:06d}", req.repo_id, recipe.augment, block,
                         description, options, stage.dir / "timings" / f"episode_{i:06d}.json", threads,
                         recipe.depth, recipe.file, req.device)
                for i, p in enumerate(paths)]
        t_jobs = time.perf_counter()
        run_jobs(jobs, executor=executor, workers=workers, ray_address=ray_address, progress=req.progress)
        t_jobs = time.perf_counter() - t_jobs
        with timer("merge"):
            # the merge's groups on this machine's cores, also when Ray built the shards
            run_groups = functools.partial(run_local, workers=min(workers, cpu_cores()), threads=threads)
            merge_datasets([j.shard_dir for j in jobs], stage.dataset, req.repo_id, description_dir=description,
                           run_groups=run_groups,
                           imac_extra={**({"joint_units": units} if units else {}),
                                       "build": {"recipe": recipe.name, "episodes": len(jobs),
                                                 "command": f"python -m imac_data.build --repo {req.repo_id}"}})
            write_card(stage.dataset, req.repo_id, recipe)
        timings = _timings_report(jobs, timer)  # read before the swap removes staging
    report = {"workers": workers, "threads": threads, "executor": executor, "episodes_wall_s": t_jobs,
              "wall_s": time.perf_counter() - t_start, "cpu_s": cpu_seconds() - usage_start, **timings}
    report["stages"] = _add_stages(report["stages"], timer)
    if req.timings is not None:
        req.timings.parent.mkdir(parents=True, exist_ok=True)
        req.timings.write_text(json.dumps(report, indent=1))
    # the table is the build's report, not a progress bar: --no-progress keeps it
    print(_timings_table(report), file=sys.stderr)


def ingest_episodes(paths: Sequence[str | Path], *, rig, repo_id: str, root: str | Path, options: IngestOptions,
                    overwrite: bool = False, progress: bool = True, chunk_frames: int = 32):
    """Write ``paths`` (HDF5 episodes) as a base dataset at ``root`` (no added streams): the
    base features, the rig in ``info["imac"]`` and its robot description, read and encoded
    ``chunk_frames`` frames at a time. Returns the loaded ``LeRobotDataset``."""
    paths = [Path(p) for p in paths]
    root = Path(root)
    check_output(root, overwrite=overwrite, what="output")  # replaces only a dataset; leftovers only ours
    probe = check_episodes(paths, rig.cameras, rig.robot)
    if options.state_names is not None and len(options.state_names) != probe["dof"]:
        raise InputError(f"state_names has {len(options.state_names)} names for a {probe['dof']}-D joint vector")
    with EpisodeReader(paths[0]) as first:
        image_hw, with_velocity = dict(first.image_hw), first.qvel is not None
    rig = rig.with_image_sizes(image_hw)
    with staged_output(root, overwrite=overwrite) as stage:
        writer = BaseWriter(stage.dataset, repo_id, image_hw=image_hw, dof=probe["dof"],
                            with_velocity=with_velocity, options=options)
        try:
            for path in tqdm(paths, desc="ingest episodes", unit="ep", disable=not progress):
                with EpisodeReader(path) as ep:
                    if ep.image_hw != image_hw:
                        raise InputError(f"{path}: image sizes {ep.image_hw} differ from {paths[0]}'s {image_hw}")
                    writer.begin_episode(ep.num_frames, ep.info)
                    for lo in range(0, ep.num_frames, chunk_frames):
                        hi = min(lo + chunk_frames, ep.num_frames)
                        poses = rig.camera_poses(ep.qpos[lo:hi], dtype=torch.float64).numpy()
                        writer.add(ep.qpos[lo:hi], ep.action[lo:hi], None if ep.qvel is None else ep.qvel[lo:hi],
                                   {c: ep.images(c, lo, hi) for c in writer.cameras},
                                   {c: poses[:, v] for v, c in enumerate(rig.names)})
                    writer.end_episode()
            writer.finish(rig)
        except BaseException:
            writer.abort()
            raise
    return lr.LeRobotDataset(repo_id, root=root)


def cpu_seconds() -> float:
    """CPU seconds of this process and its finished child processes (pool workers)."""
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def _timings_report(jobs, timer: StageTimer) -> dict:
    """Per episode (the workers' side files) and their sum."""
    total = StageTimer()
    episodes = []
    for job in jobs:
        if job.timings_file.is_file():  # a resumed build has no timings for shards it did not redo
            d = json.loads(job.timings_file.read_text())
            episodes.append(d)
            total.add(d)
    return {"frames": total.frames, "episodes_timed": len(episodes), "stages": total.to_dict(), "episodes": episodes}


def _add_stages(stages: dict, timer: StageTimer) -> dict:
    total = StageTimer()
    total.add(stages)
    total.add(timer)
    return total.to_dict()


def _timings_table(report: dict) -> str:
    t = StageTimer()
    t.add(report["stages"])
    frames = max(report["frames"], 1)
    head = (f"[build] {report['frames']} frames, {report['workers']} worker(s) x {report['threads']} thread(s) "
            f"({report['executor']}): {report['wall_s']:.1f} s wall ({frames / report['wall_s']:.2f} frames/s), "
            f"{report['cpu_s']:.1f} s CPU here and in pool workers ({report['cpu_s'] / frames * 1e3:.0f} ms/frame)")
    return head + "\n" + t.table("[build] stage")


def _check_stream_resolution(recipe: Recipe, calibration) -> None:
    """The added streams keep each camera's aspect ratio (they are rescaled, not cropped)."""
    h, w = recipe.augment.resolution
    for cam in calibration.values():
        if not same_aspect((h, w), (cam.height, cam.width)):
            raise InputError(
                f"{recipe.file}: augment.height/width {h}x{w} has another aspect ratio than camera {cam.name!r} "
                f"({cam.height}x{cam.width}); pick a size of the same aspect ratio"
            )
