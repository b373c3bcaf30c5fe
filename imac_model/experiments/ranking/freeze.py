"""The world models as the repository ships them: each trained mode's latest checkpoint as a run archive of its EMA
weights in float16 (``<work>/shipped/<run>.tar.xz``), unpacked beside it. The evaluate stage runs these, so a
report's verdicts are the shipped models' own, not those of weights that differ in the last bits
(docs/ranking.md, "The shipped world models")."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from imac_data.errors import InputError
from imac_model.experiments.ranking.plan import RankingPlan
from imac_model.models.checkpoint import list_checkpoints
from imac_model.training.archive import unpack_checkpoint, write_archive
from imac_model.training.log import LOG_FILE


def unpack_run(archive: Path, directory: Path) -> None:
    """A run archive's checkpoint as ``directory``, whole or not at all."""
    tmp = directory.with_name(f"{directory.name}.unpacking{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    unpack_checkpoint(archive, tmp)
    shutil.rmtree(directory, ignore_errors=True)
    os.replace(tmp, directory)


def freeze_models(plan: RankingPlan, modes: tuple[str, ...] | None = None) -> None:
    """Each of the plan's trained modes (or ``modes``) as it ships (``evaluate_half``): its float16 EMA archive, and
    the checkpoint the evaluation loads unpacked from it (skipped where done)."""
    if not plan.evaluate_half:
        return
    for mode in modes or plan.modes:
        archive, unpacked = plan.shipped_archive(mode), plan.evaluated_model(mode)
        if unpacked.is_dir():
            continue
        found = list_checkpoints(plan.run_dir(mode))
        if not found:
            raise InputError(f"{plan.run_dir(mode)}: {mode} has no trained checkpoint to evaluate (run the train stage)")
        write_archive(found[-1], plan.run_dir(mode) / LOG_FILE, archive, ema_half=True)
        unpack_run(archive, unpacked)


__all__ = ["freeze_models", "unpack_run"]
