"""Policy ranking in simulation (``make ranking``, ``imac-model ranking``): does the world model
rank policies the way MuJoCo does?

Stages, each cached under ``--work`` and resumed where it stopped, each timed (wall and CPU of
this process and its children):

1. ``simulate``: every policy in MuJoCo from the evaluation starts (``imac-model evaluate
   simulator``), and the world model's training rollouts (a mix of policies, other starts);
2. ``build``: both as LeRobot datasets with ``imac build`` (their success labels included);
3. ``decode``: the training chunks, decoded once;
4. ``train``: one world model per conditioning mode, the same CPU budget each;
5. ``judges``: the learned classifier, and both judges' accuracy on the real evaluation episodes;
6. ``evaluate``: every policy closed loop in every world model from the same starts and seeds
   (``none`` once per start, after checking its frames are bit-identical across policies), the
   recorded actions replayed for the judges' accuracy on generated frames, action sensitivity;
7. ``report``: ``docs/ranking/``.

``docs/ranking.md`` explains the protocol; the report holds the figures."""

from __future__ import annotations

import json
import os
import shutil
import sys
from dataclasses import replace
from functools import partial
from pathlib import Path

import numpy as np
import torch

from imac_data.errors import InputError
from imac_data.layout import info_path
from imac_model.config import CONTROL_STREAMS, SCENE_WARP
from imac_model.data.chunks import ChunkDataset, open_metadata, split_episodes
from imac_model.evaluate.simulator import SimRunConfig, SimRunner, run_policy
from imac_model.experiments.ranking.evaluation import evaluated_policies, policy_dir
from imac_model.experiments.ranking.gate import GATED_MODE, gate_minutes, gate_verdict, read_gates
from imac_model.experiments.ranking.plan import (
    EVAL_REPO,
    RECIPE,
    TRAIN_REPO,
    TRAIN_SEED0,
    RankingPlan,
    slug,
)
from imac_model.experiments.ranking.policies import training_policy
from imac_model.experiments.ranking.report import write_report
from imac_model.experiments.stages import MARK_TRAINED, REPO_ROOT, python, quote, run_all, then_mark_done
from imac_model.models.checkpoint import list_checkpoints, weights_sha256
from imac_model.pipelines.online_controls import OnlineControls
from imac_model.pipelines.packed_contact import contact_geometry, geometry_constants
from imac_model.training.archive import archives_in, read_archive, run_name, write_archive
from imac_model.training.log import LOG_FILE, continued_log, log_summary, progress_line, read_log
from imac_model.training.pack import export_pack
from imac_model.training.train import model_spec


def internal(plan: RankingPlan, what: str, *extra: str) -> list[str]:
    """argv of one of this module's steps in a fresh process (LeRobot's decoders and MuJoCo's
    GL context must not be forked after use)."""
    return python() + ["-m", "imac_model", "ranking", "--plan", str(plan.work / "plan.json"), "--internal", what,
                       *extra]


# --------------------------------------------------------------------------- 1. simulate


SIDES = ("train", "eval")  # the world model's training rollouts, the evaluation episodes


def stage_simulate(plan: RankingPlan, sides: tuple[str, ...] = SIDES) -> None:
    # the training rollouts first: decoding and training wait on them, not on the evaluation episodes
    commands = []
    parts = max(1, min(plan.jobs, plan.train_episodes)) if "train" in sides else 0
    for k in range(parts):
        out = plan.work / "sim" / "train" / f"part_{k}"
        if not (out / ".done").is_file():
            shutil.rmtree(out, ignore_errors=True)
            commands.append((f"simulate training part {k}", then_mark_done(internal(plan, "train-rollouts", str(k)),
                                                                            out / ".done"),
                             plan.work / "logs" / f"sim_train_{k}.log"))
    seeds = [str(s) for _, s in plan.eval_seeds()]
    for spec, name in zip(plan.policies, plan.names) if "eval" in sides else ():
        out = plan.sim_dir(name)
        if (out / ".done").is_file():
            continue
        shutil.rmtree(out, ignore_errors=True)
        argv = python() + ["-m", "imac_model", "evaluate", "simulator", "--policy", spec, "--seeds", *seeds,
                           "--chunks", str(plan.chunks), "--view-size", *map(str, plan.view_size), "--views", *plan.views,
                           "--settle", str(plan.settle_s), "--output", str(out), "--no-progress"]
        commands.append((f"simulate {name}", then_mark_done(argv, out / ".done"), plan.work / "logs" / f"sim_{name}.log"))
    run_all(commands, plan.jobs, tag="ranking")


def simulate_training_part(plan: RankingPlan, part: int) -> None:
    parts = max(1, min(plan.jobs, plan.train_episodes))
    out = plan.work / "sim" / "train" / f"part_{part}"
    with SimRunner(SimRunConfig(chunks=plan.chunks, view_height=plan.view_size[0], view_width=plan.view_size[1],
                                   views=plan.views, settle_s=plan.settle_s)) as runner:
        rows = []
        for i in range(part, plan.train_episodes, parts):
            p = training_policy(i, plan.training_offsets)
            rows += run_policy(p, [TRAIN_SEED0 + i], out / f"ep_{i:05d}", runner=runner, progress=False)
            rows[-1].update(index=i, policy=p.name, offset=p.offset.tolist())
    (out / "outcomes.json").write_text(json.dumps(rows, indent=1))


# --------------------------------------------------------------------------- 2. build


def _link_episodes(sources: list[Path], dest: Path) -> None:
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
        _link_episodes(sources, src_dir)
        argv = python() + ["-m", "imac_data.build", "--repo", repo, "--recipe", str(RECIPE), "--source", str(src_dir),
                           "--root", str(root), "--episodes", str(len(sources)), "--workers", str(workers),
                           "--no-progress", "--overwrite",
                           "--timings", str(plan.work / f"build_timings_{root.name}.json")]
        commands.append((f"build {root.name}", argv, plan.work / "logs" / f"build_{root.name}.log"))
    run_all(commands, plan.jobs, tag="ranking")


# --------------------------------------------------------------------------- 3-4. decode, train


def decode_chunks(plan: RankingPlan) -> None:
    torch.set_num_threads(1)
    run = plan.run_config("motion+contact")  # every stream: the other modes reuse its cache
    meta = open_metadata(run.data)
    _, layout = model_spec(run, meta)
    assert set(layout.streams) >= set(CONTROL_STREAMS)
    for eps in split_episodes(meta.total_episodes, run.data.held_out_episodes):
        ds = ChunkDataset(TRAIN_REPO, layout, root=run.data.root, episodes=eps, cache="memory",
                          cache_dir=run.data.cache_dir)
        ds.preload(num_workers=1, progress=False)


def export_training_pack(plan: RankingPlan) -> None:
    """The decoded training and held-out chunks as one tensor pack (:mod:`imac_model.training.pack`):
    what the GPU preset trains from on a machine with torch alone."""
    run = plan.run_config("motion+contact")
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
    stage_simulate(plan, ("train",))
    stage_build(plan, ("train",))
    stage_decode(plan)
    run_all([("pack", internal(plan, "pack"), plan.work / "logs" / "pack.log")], 1, tag="ranking")


def import_gpu_runs(plan: RankingPlan, directory: Path) -> list[str]:
    """Run archives (:mod:`imac_model.training.archive`: ``scripts/gpu_ranking.sh``'s output, or
    :func:`export_runs`') -> this work directory's trained runs (``runs/<run>``), so ``judges``,
    ``evaluate`` and ``report`` go on here. A run that is not one of the plan's modes (an ablation) is
    imported beside them; the evaluations of a run it replaces (``wm/<run>``) are dropped, being of another
    model. A run that started from the weights it replaces (``INIT``: its summary's ``init_sha256`` is
    theirs) continues that run's log, so the report shows the whole training. Returns the runs imported."""
    directory, done = Path(directory), []
    if not directory.is_dir():
        raise InputError(f"--import-gpu {directory}: no such directory")
    for tar in archives_in(directory):
        files = read_archive(tar)
        rows = [json.loads(line) for line in files[LOG_FILE].decode().splitlines() if line.strip()]
        name = run_name(tar)
        run = plan.work / "runs" / name
        earlier = list_checkpoints(run)
        started_from = log_summary(rows).get("init_sha256")
        if started_from and earlier and weights_sha256(earlier[-1]) == started_from:
            rows = continued_log(read_log(run), rows)
        summary = rows[-1].get("summary", rows[-1])
        tmp = run.with_name(run.name + ".importing")  # the run replaces any earlier one whole, or not at all
        shutil.rmtree(tmp, ignore_errors=True)
        ckpt = tmp / "checkpoints" / f"step_{int(summary['steps']):06d}"
        ckpt.mkdir(parents=True)
        (ckpt / "model.json").write_bytes(files["model.json"])
        (ckpt / "model.safetensors").write_bytes(files["model.safetensors"])
        (tmp / LOG_FILE).write_text("".join(json.dumps(r) + "\n" for r in rows))
        (tmp / "DONE.json").write_text(json.dumps(summary, indent=1))
        shutil.rmtree(run, ignore_errors=True)
        os.replace(tmp, run)
        shutil.rmtree(plan.work / "wm" / name, ignore_errors=True)
        done.append(name)
    if not done:
        raise InputError(f"{directory}: no <run>.tar or <run>.tar.xz of scripts/gpu_ranking.sh")
    return done


def export_runs(plan: RankingPlan, directory: Path, runs: list[str] | None = None) -> list[Path]:
    """This work directory's trained runs (default: the plan's modes') as run archives
    ``directory/<run>.tar.xz``: the latest checkpoint and the whole log, which :func:`import_gpu_runs`
    reads back on another machine and ``INIT`` starts a loan from. Every run is checked before any is written."""
    names = runs or [plan.run_dir(mode).name for mode in plan.modes if mode != "none"]
    found = {n: list_checkpoints(plan.work / "runs" / n) for n in names}
    missing = [n for n, ckpts in found.items() if not ckpts]
    if missing:
        raise InputError(f"--export-runs: no trained run {missing} under {plan.work / 'runs'}")
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    return [write_archive(ckpts[-1], plan.work / "runs" / n / LOG_FILE, directory / f"{n}.tar.xz")
            for n, ckpts in found.items()]


def train_on_gpu(plan: RankingPlan) -> None:
    """The GPU preset's training: ``scripts/gpu_ranking.sh`` here when this machine has a GPU, else
    a clear word on how to run it on one and bring the checkpoints back (``--import-gpu``)."""
    if all((plan.run_dir(mode) / "DONE.json").is_file() for mode in plan.modes):
        return
    if not torch.cuda.is_available():
        raise InputError(f"the GPU preset trains on a GPU: on a GPU machine with this repository and {plan.pack}, run "
                         f"OUT=DIR MINUTES={plan.gpu_minutes:g} bash scripts/gpu_ranking.sh, then here imac-model "
                         f"ranking --preset gpu --work {plan.work} --import-gpu DIR")
    out = plan.work / "gpu" / "out"
    argv = ["env", f"OUT={out}", f"MINUTES={plan.gpu_minutes:g}", f"PACK={plan.pack}", f"PYTHON={sys.executable}",
            "bash", str(REPO_ROOT / "scripts" / "gpu_ranking.sh")]
    run_all([("train on the GPU", argv, plan.work / "logs" / "train_gpu.log")], 1, tag="ranking")
    import_gpu_runs(plan, out)


def stage_decode(plan: RankingPlan) -> None:
    if any((plan.work / "chunkcache").glob("*")):
        return
    run_all([("decode", internal(plan, "decode"), plan.work / "logs" / "decode.log")], 1, tag="ranking")


def train_command(plan: RankingPlan, mode: str, minutes: float | None = None, finish: bool = True,
                  changes: dict | None = None) -> list[str]:
    """argv training ``mode`` (resuming its checkpoints) up to ``minutes`` CPU-minutes (default: its
    budget); with ``finish``, the run is then marked trained (``DONE.json``). ``changes``: run-config
    fields set on top (an ablation's arm: its output directory and the one setting it changes)."""
    overrides = {**plan.mode_overrides(mode), **(changes or {})}
    if minutes is not None:
        overrides["train.max_cpu_minutes"] = minutes
    sets = [a for k, v in overrides.items() for a in ("--set", f"{k}={json.dumps(v)}")]
    script = " ".join(map(quote, python() + ["-m", "imac_model", "train", "--config", plan.config, "--no-progress",
                                             *sets]))
    if finish:
        script += f" && {quote(sys.executable)} -c {quote(MARK_TRAINED)} {quote(overrides['train.output_dir'])}"
    return ["bash", "-c", script]


class GateStop(RuntimeError):
    """The early gate was not passed in time: the benchmark stops (the report says what it showed)."""


def train_gated(plan: RankingPlan) -> None:
    """motion+contact in segments of ``gate_every`` CPU-minutes, each followed by the early gate
    (:mod:`.gate`); raises :class:`GateStop` when the gate says stop."""
    mode, log = GATED_MODE, plan.work / "logs" / f"train_{slug(GATED_MODE)}.log"
    measured = {g["budget_minutes"] for g in read_gates(plan)}
    for minutes in gate_minutes(plan):
        if minutes not in measured:
            last = minutes == gate_minutes(plan)[-1]
            run_all([(f"train {mode} to {minutes:g} CPU-minutes", train_command(plan, mode, minutes, finish=last), log,
                      partial(progress_line, plan.run_dir(mode), minutes))], 1, tag="ranking")
            run_all([(f"gate {mode} at {minutes:g} CPU-minutes", internal(plan, "gate", f"{minutes:g}"),
                      plan.work / "logs" / "gate.log")], 1, tag="ranking")
        gates = [g for g in read_gates(plan) if g["budget_minutes"] <= minutes]  # those up to this point
        score = gates[-1]["from_chunk"]["0"]["balanced_accuracy"]
        print(f"[ranking]   gate at {minutes:g} CPU-minutes: balanced accuracy {score:.2f} (goal {plan.gate_min:g})",
              file=sys.stderr, flush=True)
        if gate_verdict(plan, gates) == "stop":
            write_report(plan)
            raise GateStop(f"the early gate: {mode}'s lift judge on replays of held-out training rollouts reached "
                           f"{max(g['from_chunk']['0']['balanced_accuracy'] for g in gates):.2f} balanced accuracy by "
                           f"{minutes:g} CPU-minutes, below {plan.gate_min:g}; the benchmark stops here "
                           f"(docs/ranking.md, \"The early gate\"; the gates: {plan.docs / 'README.md'})")


def stage_train(plan: RankingPlan) -> None:
    if plan.gpu_minutes is not None:
        return train_on_gpu(plan)
    gated = plan.gate_every is not None and GATED_MODE in plan.modes
    if gated and not (plan.run_dir(GATED_MODE) / "DONE.json").is_file():
        train_gated(plan)  # first, alone: the other modes train only once it has passed
    commands = [(f"train {mode}", train_command(plan, mode), plan.work / "logs" / f"train_{slug(mode)}.log",
                 partial(progress_line, plan.run_dir(mode), plan.none_minutes if mode == "none" else plan.cpu_minutes))
                for mode in plan.modes if not (plan.run_dir(mode) / "DONE.json").is_file()]
    run_all(commands, plan.jobs, tag="ranking")


# --------------------------------------------------------------------------- 5-6. judges, evaluate


def stage_judges(plan: RankingPlan) -> None:
    if (plan.work / "judges" / "real.json").is_file():
        return
    run_all([("judges", internal(plan, "judges"), plan.work / "logs" / "judges.log")], 1, tag="ranking")


def _gated_at_the_end(plan: RankingPlan, mode: str) -> bool:
    """Whether a gate of ``mode`` measured its last checkpoint (the same replays, seeds and weights give
    the same figures, so it is not measured twice)."""
    last = list_checkpoints(plan.run_dir(mode))
    return bool(last) and any(g.get("checkpoint") == last[-1].name for g in read_gates(plan, mode))


def stage_evaluate(plan: RankingPlan) -> None:
    # the gate of every compared mode at the end of its training, beside motion+contact's hourly ones
    budget = plan.gpu_minutes if plan.gpu_minutes is not None else plan.cpu_minutes
    gates = [(f"gate {mode}", internal(plan, "gate", f"{budget:g}", mode), plan.work / "logs" / "gate.log")
             for mode in plan.modes if mode != "none" and not _gated_at_the_end(plan, mode)]
    run_all(gates, plan.jobs, tag="ranking")
    # each mode's replays and each policy's closed loop in a process of its own, the longest first, so that the cores
    # stay busy to the end (one process per mode left one idle while motion+contact's ran on); then each mode's
    # outcomes from them, with the none check and the action sensitivity
    modes = [m for m in plan.modes if not (plan.wm_dir(m) / "outcomes.json").is_file()]

    def log(mode: str, what: str) -> Path:
        return plan.work / "logs" / f"evaluate_{slug(mode.replace('+', '_'))}{what}.log"

    replaying = [(f"replays {m}", internal(plan, "replays", m), log(m, "_replays")) for m in modes
                 if m != "none" and not (plan.wm_dir(m) / "replays.json").is_file()]
    closed_loops = [(f"evaluate {m} {slug(p)}", internal(plan, "evaluate", m, p), log(m, f"_{slug(p)}"))
                    for m in modes for p in evaluated_policies(plan, m)
                    if not (policy_dir(plan, m, p) / "closed_loop.json").is_file()]
    run_all(replaying + closed_loops, plan.jobs, tag="ranking")
    run_all([(f"evaluate {m}", internal(plan, "evaluate", m), log(m, "")) for m in modes], plan.jobs, tag="ranking")


def stage_report(plan: RankingPlan) -> None:
    write_report(plan)


STAGE_FUNCTIONS = {"simulate": stage_simulate, "build": stage_build, "decode": stage_decode, "pack": stage_pack,
                   "train": stage_train,
                   "judges": stage_judges, "evaluate": stage_evaluate, "report": stage_report}
