"""The main job: a recipe -> a LeRobot dataset with every added stream.

Everything that can be checked is checked first, read-only: the recipe's inputs, that the
output neither is nor holds an input, that an existing output may be replaced, and the robot
description. Then the source's type decides the flow (:data:`BUILDS`, by
:attr:`imac_data.recipes.SourceType.build`): HDF5 or simulated episodes
(:mod:`~imac_data.build.from_episodes`) or a LeRobot dataset
(:mod:`~imac_data.build.from_lerobot`), both through the one staged flow
(:mod:`~imac_data.build.staging`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

from imac_data import lerobot_compat as lr
from imac_data.build.from_episodes import build_from_episodes, cpu_seconds
from imac_data.build.from_lerobot import build_from_lerobot
from imac_data.build.staging import BuildRequest
from imac_data.build.workers import limit_malloc_arenas
from imac_data.core.rig import Rig
from imac_data.dataset.output import check_output, refuse_overlap
from imac_data.errors import InputError
from imac_data.recipes import missing_inputs, source_type

__all__ = ["build_dataset", "input_paths", "BUILDS"]


def _build_lerobot(req: BuildRequest, robot, **_) -> None:
    build_from_lerobot(req, robot)  # one process, no shards: the executor's options do not apply


# SourceType.build -> the build that reads that kind of source
BUILDS: dict[str, Callable[..., None]] = {"episodes": build_from_episodes, "lerobot": _build_lerobot}


def build_dataset(req: BuildRequest, *, executor: str = "local", workers: int | None = None,
                  ray_address: str | None = None):
    """Run the whole build; returns the loaded ``LeRobotDataset`` at ``req.root``."""
    t_start, usage_start = time.perf_counter(), cpu_seconds()
    limit_malloc_arenas()  # before the rig's threads allocate: this process may be the only worker
    recipe = req.recipe
    if executor not in ("local", "ray"):
        raise InputError(f"--executor must be 'local' or 'ray', got {executor!r}")
    problems = missing_inputs(recipe, req.source_path)
    if problems:
        raise InputError(f"recipe {recipe.file} needs inputs that are not there:\n  - " + "\n  - ".join(problems))
    refuse_overlap(req.root, input_paths(req))  # before anything is recorded or written
    check_output(req.root, overwrite=req.overwrite)
    robot = Rig.robot_from_recipe(recipe)  # a bad URDF or joint map fails before any recording
    build = BUILDS[source_type(recipe.source.type).build]
    build(req, robot, executor=executor, workers=workers, ray_address=ray_address, t_start=t_start,
          usage_start=usage_start)
    return lr.LeRobotDataset(req.repo_id, root=req.root)


def input_paths(req: BuildRequest) -> dict[str, Path | None]:
    """The user's files a build reads (never written or deleted)."""
    recipe = req.recipe
    return {
        source_type(recipe.source.type).input_name: req.source_path or recipe.resolve_path(recipe.source.path),
        "calibration": recipe.resolve_path(recipe.cameras.calibration),
        "recipe": Path(recipe.file) if recipe.file else None,
        "robot URDF": recipe.resolve_path(recipe.robot.urdf),
        "LeRobot calibration": recipe.resolve_path(recipe.robot.calibration),
        "episode metadata": recipe.resolve_path(recipe.source.metadata),
    }
