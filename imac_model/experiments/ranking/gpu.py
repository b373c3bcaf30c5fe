"""The GPU preset's side of the ranking benchmark: the tensor pack and its runs file (what the GPU
machine trains, :mod:`imac_model.training.runs`), and run archives in and out of a work directory.
``docs/ranking.md`` ("The GPU preset") has the commands."""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
import yaml

from imac_data.errors import InputError
from imac_model.data.chunks import ChunkDataset, open_metadata, split_episodes
from imac_model.data.pack import export_pack
from imac_model.experiments.ranking.ablations import ablation
from imac_model.experiments.ranking.datasets import training_side
from imac_model.experiments.ranking.plan import GATED_MODE, SEED_MARK, TRAIN_REPO, RankingPlan, internal
from imac_model.experiments.stages import REPO_ROOT, python, run_all
from imac_model.models.checkpoint import list_checkpoints
from imac_model.modes import SCENE_WARP
from imac_model.pipelines.online_controls import OnlineControls
from imac_model.pipelines.packed_contact import contact_geometry, geometry_constants
from imac_model.training.archive import GATES, archives_in, read_archive, run_name, unpack_checkpoint, write_archive
from imac_model.training.dataset_source import model_spec
from imac_model.training.log import LOG_FILE
from imac_model.training.runs import RUNS_FILE, RunsFile

GPU_CONFIG = REPO_ROOT / "imac_model" / "configs" / "ranking_gpu.yaml"  # the pack runs' training settings


def export_training_pack(plan: RankingPlan) -> None:
    """The decoded training and held-out chunks as one tensor pack (:mod:`imac_model.data.pack`), and its
    runs file beside it: what the GPU preset trains from on a machine with torch alone."""
    run = plan.run_config(GATED_MODE)
    meta = open_metadata(run.data)
    spec, layout = model_spec(run, meta)
    layout = replace(layout, streams=layout.streams + (SCENE_WARP,))  # derived here: the GPU machine cannot render
    train, held = split_episodes(meta.total_episodes, run.data.held_out_episodes)
    ds = ChunkDataset(TRAIN_REPO, layout, root=run.data.root, episodes=train + held, cache="memory",
                      cache_dir=run.data.cache_dir)
    ds.preload(num_workers=1, progress=False)
    items = [ds[i] for i in range(len(ds))]
    export_pack(items, [e in set(held) for _, e, _ in ds.index], spec, plan.pack,
                geometry=pack_geometry(OnlineControls.from_dataset(run.data.root, spec), items))
    runs_file(plan).to_yaml(plan.pack.parent / RUNS_FILE)


def runs_file(plan: RankingPlan) -> RunsFile:
    """What the GPU machine trains: the plan's compared modes (``none`` trains on the CPU) and its ablations'
    arms (:mod:`.ablations`), on the gated mode's run config with the GPU settings
    (``imac_model/configs/ranking_gpu.yaml``), ``gpu_minutes`` of wall time each."""
    base = plan.run_config(GATED_MODE).replace(**yaml.safe_load(GPU_CONFIG.read_text()),
                                                **{"train.max_minutes": plan.gpu_minutes, "train.max_cpu_minutes": None})
    runs = {plan.run_dir(mode).name: {k: plan.mode_overrides(mode)[k] for k in ("conditioning.mode", "train.seed")
                                      if k == "conditioning.mode" or SEED_MARK in mode}
            for mode in plan.compared_modes}  # none trains on the CPU (stage_train)
    for name in plan.gpu_ablations:
        arm = ablation(name, plan.chunks)
        runs[arm.arm] = {"conditioning.mode": GATED_MODE, **arm.changes}
    data = base.to_dict()
    for key in ("dataset", "root", "cache_dir"):  # the pack replaces the dataset there
        data["data"].pop(key, None)
    return RunsFile(pack=str(plan.pack), base=data, runs=runs)


def pack_geometry(online: OnlineControls, items: list[dict], batch: int = 64) -> dict:
    """The items' contact geometry (:mod:`imac_model.pipelines.packed_contact`), rendered here in
    batches: what the pack's trainer rebuilds contact images from on a machine without a renderer."""
    parts = [contact_geometry(online, torch.stack([it["state"] for it in items[i:i + batch]]),
                              torch.stack([it["actions"] for it in items[i:i + batch]]))
             for i in range(0, len(items), batch)]
    return {**geometry_constants(online), **{k: np.concatenate([p[k] for p in parts]) for k in parts[0]}}


def stage_pack(plan: RankingPlan) -> None:
    if plan.pack.is_file():
        return
    # run before the others (--stages pack on a new work directory, a GPU waiting): only the training side, so
    # the pack is ready in about half the time and the evaluation episodes can be made while the GPU trains
    training_side(plan)
    run_all([("pack", internal(plan, "pack"), plan.work / "logs" / "pack.log")], 1, tag="ranking")


def import_gpu_runs(plan: RankingPlan, directory: Path) -> list[str]:
    """Run archives (:mod:`imac_model.training.archive`: the GPU machine's output, or :func:`export_runs`')
    -> this work directory's trained runs (``runs/<run>``), so ``judges``, ``evaluate`` and ``report`` go
    on here. A run that is not one of the plan's modes (an ablation) is imported beside them; a run it
    replaces goes whole, and so do its evaluations (``wm/<run>``), being of another model. Returns the runs
    imported."""
    directory, done = Path(directory), []
    if not directory.is_dir():
        raise InputError(f"--import-gpu {directory}: no such directory")
    for tar in archives_in(directory):
        files = read_archive(tar)
        rows = [json.loads(line) for line in files[LOG_FILE].decode().splitlines() if line.strip()]
        last = next((r for r in reversed(rows) if "step" in r), None)
        if last is None:
            raise InputError(f"{tar}: its log has no step")
        name = run_name(tar)
        run = plan.work / "runs" / name
        tmp = run.with_name(run.name + ".importing")  # the run replaces any earlier one whole, or not at all
        shutil.rmtree(tmp, ignore_errors=True)
        unpack_checkpoint(tar, tmp / "checkpoints" / f"step_{int(last['step']):06d}")
        (tmp / LOG_FILE).write_text("".join(json.dumps(r) + "\n" for r in rows))
        if GATES in files:  # a CPU-trained run's early gates travel with it
            (tmp / GATES).write_bytes(files[GATES])
        (tmp / "DONE.json").write_text(json.dumps(last, indent=1))
        shutil.rmtree(run, ignore_errors=True)
        os.replace(tmp, run)
        shutil.rmtree(plan.work / "wm" / name, ignore_errors=True)
        shutil.rmtree(plan.work / "shipped" / name, ignore_errors=True)  # frozen from the run replaced
        (plan.work / "shipped" / f"{name}.tar.xz").unlink(missing_ok=True)
        done.append(name)
    if not done:
        raise InputError(f"{directory}: no run archive <run>.tar or <run>.tar.xz there")
    return done


def export_runs(plan: RankingPlan, directory: Path, runs: list[str] | None = None) -> list[Path]:
    """This work directory's trained runs (default: the plan's modes') as run archives
    ``directory/<run>.tar.xz``: the latest checkpoint as it ships (its EMA in float16, what the evaluation loads and
    a GPU loan hands back), the whole log and the early gates, which :func:`import_gpu_runs` reads back on another
    machine and ``train.init`` starts a run from. Every run is checked before any is written."""
    names = runs or [plan.run_dir(mode).name for mode in plan.compared_modes]
    found = {n: list_checkpoints(plan.work / "runs" / n) for n in names}
    # only finished runs (DONE.json), since an imported one is marked trained: that also makes it safe to export
    # while another run trains in the work directory
    missing = [n for n, ckpts in found.items() if not ckpts or not (plan.work / "runs" / n / "DONE.json").is_file()]
    if missing:
        raise InputError(f"--export-runs: no trained run {missing} under {plan.work / 'runs'} (a run is trained once "
                         "its DONE.json is written; one still training is exported when it ends)")
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    return [write_archive(ckpts[-1], plan.work / "runs" / n / LOG_FILE, directory / f"{n}.tar.xz", ema_half=True,
                          gates=plan.work / "runs" / n / GATES) for n, ckpts in found.items()]


def train_on_gpu(plan: RankingPlan) -> None:
    """The GPU preset's training: the runs file trained here when this machine has a GPU, else a clear word
    on how to run it on one and bring the archives back (``--import-gpu``)."""
    if all((plan.run_dir(mode) / "DONE.json").is_file() for mode in plan.compared_modes):
        return
    command = f"python scripts/gpu_train.py {plan.pack.parent / RUNS_FILE} OUT"
    if not torch.cuda.is_available():
        raise InputError(f"the GPU preset trains on a GPU: on a GPU machine with this repository and "
                         f"{plan.pack.parent}, run {command}, then here imac-model ranking --preset gpu --work "
                         f"{plan.work} --import-gpu OUT")
    out = plan.work / "gpu" / "out"
    argv = python() + [str(REPO_ROOT / "scripts" / "gpu_train.py"), str(plan.pack.parent / RUNS_FILE), str(out)]
    run_all([("train on the GPU", argv, plan.work / "logs" / "train_gpu.log")], 1, tag="ranking")
    import_gpu_runs(plan, out)
