"""The one staged flow every build writes through, and the request that starts a build.

A new dataset (or an edited copy of an existing one) is assembled in ``.ROOT.staging`` next
to the output, under the output's lock, validated there, and only then renamed into place;
the previous output is removed once the new one is there. A failure leaves the output as it
was (a resumable build keeps its finished shards in staging).
"""

from __future__ import annotations

import contextlib
import os
import shutil
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from imac_data import lerobot_compat as lr
from imac_data.augment.timing import StageTimer
from imac_data.core.render import check_device
from imac_data.dataset.files import copy_for_edit
from imac_data.dataset.info import read_info
from imac_data.dataset.output import (
    check_output,
    check_sibling,
    make_sibling_dir,
    output_lock,
    output_sibling,
    remove_sibling,
    staging_dir,
    swap_into_place,
)
from imac_data.dataset.validate import validate_dataset
from imac_data.recipes import Recipe

__all__ = ["BuildRequest", "Stage", "staged_output", "BUILD_KEY"]

BUILD_KEY = "BUILD_KEY"  # in a resumable staging directory: what its shards were built for


@dataclass(frozen=True)
class BuildRequest:
    repo_id: str
    recipe: Recipe
    root: Path
    source_path: Path | None = None  # overrides recipe.source.path
    episodes: int | None = None  # overrides recipe.source.episodes
    overwrite: bool = False
    progress: bool = True
    timings: Path | None = None  # also write the build's stage timings here (JSON)
    wait: bool = False  # wait for another build of the same root instead of refusing
    device: str = "cpu"  # where the robot is rendered and contact painted (Rig.device)

    def __post_init__(self):
        # absolute, as its siblings are (output_sibling): the swap renames the root itself
        object.__setattr__(self, "root", Path(os.path.abspath(self.root)))
        check_device(self.device)  # before anything is read or written


@dataclass(frozen=True)
class Stage:
    """A staging directory: the new dataset is assembled in :attr:`dataset`; a build may keep
    other work (shards, a downloaded source) beside it."""

    dir: Path

    @property
    def dataset(self) -> Path:
        return self.dir / "dataset"

    @property
    def arrow_cache(self) -> Path:
        """Where LeRobot's Arrow copies of the staged datasets' parquet files go (they leave with the staging)."""
        return self.dir / "arrow"


def _prepare(staging: Path, key: str | None) -> None:
    """A fresh staging directory, or the one a killed build with the same ``key`` left."""
    key_file = staging / BUILD_KEY
    if key is not None and key_file.is_file() and key_file.read_text() == key:
        return
    remove_sibling(staging)
    make_sibling_dir(staging)
    if key is not None:
        key_file.write_text(key)


@contextlib.contextmanager
def staged_output(root: Path, *, overwrite: bool = False, wait: bool = False, key: str | None = None,
                  edit: bool = False, sample: int = 2, validate: bool = True,
                  timer: StageTimer | None = None, what: str = "--root") -> Iterator[Stage]:
    """Write the dataset at ``root`` through a staging directory::

        with staged_output(root, overwrite=True) as stage:
            ...  # write the dataset at stage.dataset

    When the block ends without error the dataset is validated (``sample`` frames per episode,
    timed as ``validate``; ``validate=False`` for a dataset that is not an imac one) and swapped
    into place; on error nothing changes at ``root``.
    ``key``: a resumable build (staging is kept for a rerun with the same key; only the
    half-made dataset is removed). ``edit``: start from a copy of the dataset at ``root``
    (its videos hard-linked) instead of an empty one. ``wait``: wait for another writer of
    ``root`` instead of refusing. ``what``: the output's name in messages (its option).
    """
    root = Path(os.path.abspath(root))
    timer = timer if timer is not None else StageTimer()
    with output_lock(root, wait=wait):
        if edit:
            read_info(root)
            for suffix in ("staging", "old"):  # the swap keeps the original at .old: refuse a user's path up front
                check_sibling(output_sibling(root, suffix))
        else:
            check_output(root, overwrite=overwrite, what=what)  # again, under the lock: a build we waited for may have made it
        stage = Stage(staging_dir(root))
        _prepare(stage.dir, key)
        shutil.rmtree(stage.dataset, ignore_errors=True)
        try:
            if edit:
                copy_for_edit(root, stage.dataset)
            yield stage
            if validate:
                # the Arrow copies of a path about to go: in the staging, not the user's cache
                with timer("validate"), lr.arrow_cache_in(stage.arrow_cache):
                    validate_dataset(stage.dataset, sample=sample).raise_if_invalid()
            swap_into_place(stage.dataset, root)
        except BaseException:
            shutil.rmtree(stage.dataset if key is not None else stage.dir, ignore_errors=True)
            raise
        shutil.rmtree(stage.dir, ignore_errors=True)
