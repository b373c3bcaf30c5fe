"""The ranking benchmark's ``build`` stage: the simulated training rollouts and evaluation episodes
as LeRobot datasets with ``imac build`` (their success labels included); and ``decode``: the
training chunks decoded once into the chunk cache every mode's training reads."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from imac_data.layout import info_path
from imac_model.experiments.ranking.plan import EVAL_REPO, GATED_MODE, RECIPE, TRAIN_REPO, RankingPlan, internal
from imac_model.experiments.ranking.simulate import SIDES, stage_simulate
from imac_model.experiments.stages import python, run_all
from imac_model.training.dataset_source import decode_to_cache


def link_episodes(sources: list[Path], dest: Path) -> None:
    """One source directory of ``episode_<i>.hdf5`` links, in the given order."""
    tmp = dest.with_name(dest.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    for i, src in enumerate(sources):
        (tmp / f"episode_{i}.hdf5").symlink_to(src.resolve())
    calibration = next(p for p in (s.parent / "calibration.json" for s in sources) if p.is_file())
    shutil.copy(calibration, tmp / "calibration.json")
    shutil.rmtree(dest, ignore_errors=True)
    os.replace(tmp, dest)


def stage_build(plan: RankingPlan, sides: tuple[str, ...] = SIDES) -> None:
    parts = max(1, min(plan.jobs, plan.train_episodes))
    train = [plan.work / "sim" / "train" / f"part_{i % parts}" / f"ep_{i:05d}" / "episode_0.hdf5"
             for i in range(plan.train_episodes)]
    n_eval = len(plan.eval_seeds())
    evals = [plan.sim_dir(name) / f"episode_{i}.hdf5" for name in plan.names for i in range(n_eval)]
    todo = [(repo, root, sources, src_dir) for side, repo, root, sources, src_dir in (
        ("train", TRAIN_REPO, plan.train_dataset, train, plan.work / "sim" / "train_all"),
        ("eval", EVAL_REPO, plan.eval_dataset, evals, plan.work / "sim" / "eval_all"))
        if side in sides and not info_path(root).is_file()]  # a build moves its dataset into place only when complete
    workers = plan.jobs if len(todo) == 1 else 1  # one build alone gets every process
    commands = []
    for repo, root, sources, src_dir in todo:
        link_episodes(sources, src_dir)
        argv = python() + ["-m", "imac_data.build", "--repo", repo, "--recipe", str(RECIPE), "--source", str(src_dir),
                           "--root", str(root), "--episodes", str(len(sources)), "--workers", str(workers),
                           "--no-progress", "--overwrite",
                           "--timings", str(plan.work / f"build_timings_{root.name}.json")]
        commands.append((f"build {root.name}", argv, plan.work / "logs" / f"build_{root.name}.log"))
    run_all(commands, plan.jobs, tag="ranking")


def decode_chunks(plan: RankingPlan) -> None:
    decode_to_cache(plan.run_config(GATED_MODE))  # every stream: the other modes reuse its cache


def stage_decode(plan: RankingPlan) -> None:
    if any((plan.work / "chunkcache").glob("*")):
        return
    run_all([("decode", internal(plan, "decode"), plan.work / "logs" / "decode.log")], 1, tag="ranking")


def training_side(plan: RankingPlan) -> None:
    """What training needs of the earlier stages, each skipped when done: the training rollouts simulated, built
    and decoded, none of the evaluation episodes (so the world models can train while the policies still do)."""
    if not info_path(plan.train_dataset).is_file():  # built: its rollouts are not needed again
        stage_simulate(plan, ("train",))
        stage_build(plan, ("train",))
    stage_decode(plan)
