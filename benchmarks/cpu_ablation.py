"""Ablations on the ranking benchmark's CPU preset: an arm continues the preset's ``motion+contact``
run from one of its checkpoints with one design choice changed, to a CPU budget (process CPU time,
one thread; default the preset's, ``plan.cpu_minutes``), and is measured by the same early gate (its
held-out training rollouts replayed; balanced accuracy of the lift judge from every chunk). The
baseline is the preset's own run, which continues from the same checkpoint unchanged (a resumed run
draws the same batches and noise), measured by its gate at the end of the budget::

    python -m benchmarks.cpu_ablation rollout --work runs/ranking_cpu --from-step 3800 \\
        --json benchmarks/results/rollout_cpu_ablation.json

Past the preset's budget (``--minutes``) the preset has no gate; the baseline is then another arm
(``--baseline``), trained by its own call (two calls run side by side, one core each)::

    python -m benchmarks.cpu_ablation reference-noise --from-step 5627 --minutes 240 &
    python -m benchmarks.cpu_ablation first-frame --from-step 5627 --minutes 240 --baseline reference-noise

The arm lives in ``<work>/runs/<arm>`` (checkpoint, log, gates); an interrupted call resumes. The
first-frame and scene-warp arms' branches widen the checkpoint (:func:`add_first_frame`,
:func:`add_scene_warp`), so they start as the model they branch from. The arms are the one table of :mod:`imac_model.experiments.ranking.ablations`."""

from __future__ import annotations

import argparse
import json
import os
import shutil
from dataclasses import replace
from functools import partial
from pathlib import Path

import torch
import yaml
from safetensors.torch import save_file

from imac_data.errors import InputError
from imac_model.config import ModelSpec, save_config
from imac_model.experiments.ranking.ablations import ABLATIONS
from imac_model.experiments.ranking.ablations import ablation as ablation_arm
from imac_model.experiments.ranking.gate import GATED_MODE, read_gates
from imac_model.experiments.ranking.plan import RankingPlan, internal
from imac_model.experiments.ranking.training import train_command
from imac_model.experiments.stages import run_all
from imac_model.models.checkpoint import (
    CONFIG,
    EMA,
    SPEC,
    STATE,
    WEIGHTS,
    is_sharded,
    read_spec,
    read_trainer_state,
    read_weights,
    resolve_checkpoint,
    run_config_of,
)
from imac_model.models.world_model import WorldModel
from imac_model.training.log import progress_line, read_log, write_log


def arm_run(plan: RankingPlan, ablation: str, minutes: float) -> tuple[str, dict]:
    """The arm's run name (suffixed with its budget when it is not the preset's) and its changes."""
    arm = ablation_arm(ablation, plan.chunks)
    arm, changes = arm.arm, arm.changes
    return (arm if minutes == plan.cpu_minutes else f"{arm}_to{minutes:g}"), changes


# --------------------------------------------------------------------------- branching a checkpoint


def widen_front(state: dict[str, torch.Tensor], shapes: dict[str, torch.Size]) -> dict[str, torch.Tensor]:
    """Tensors whose one frame-sized dimension grew by a frame, zero-padded at its front."""
    out = {}
    for k, v in state.items():
        shape = shapes.get(k, v.shape)
        grown = [d for d in range(v.ndim) if v.shape[d] != shape[d]] if len(shape) == v.ndim else None
        if grown is None or len(grown) > 1:
            raise InputError(f"weight {k}: shape {tuple(v.shape)} cannot grow into {tuple(shape)}")
        if grown:
            d = grown[0]
            wide = v.new_zeros(shape)
            wide.narrow(d, shape[d] - v.shape[d], v.shape[d]).copy_(v)
            v = wide
        out[k] = v
    return out


def add_first_frame(path: str | Path) -> None:
    """Turn a plain checkpoint into one of the same model conditioned on the episode's first frame
    (``conditioning.first_frame``), in place: the first frame is the first of the frame sequence, so
    every weight sized by it grows a zero slice at its front (weights, EMA, the optimizer's moments),
    and the model computes what it did until training teaches it to look (an ablation's branch)."""
    path = resolve_checkpoint(path)
    spec = read_spec(path)
    if spec.conditioning.first_frame:
        return
    model = WorldModel(replace(spec, conditioning=replace(spec.conditioning, first_frame=True)))
    shapes = {k: v.shape for k, v in model.state_dict().items()}
    state = read_trainer_state(path)
    names = [k for k, p in model.named_parameters() if p.requires_grad]  # the optimizer's parameter order
    for i, moments in state["optimizer"]["state"].items():
        tensors = {m: v for m, v in moments.items() if torch.is_tensor(v) and v.ndim}
        moments.update(widen_front(tensors, {m: shapes[names[int(i)]] for m in tensors}))
    _rewrite(path, model.spec, lambda weights: widen_front(weights, shapes), state, "first_frame")


def add_scene_warp(path: str | Path) -> None:
    """Turn a plain checkpoint into one of the same model with the scene-warp control stream
    (``conditioning.scene_warp``), in place: the stream's projection is zero like any new control
    layer's (weights and EMA), the optimizer's moments follow their parameters to their new
    places, so the model computes what it did until training teaches it to look (an ablation's branch)."""
    path = resolve_checkpoint(path)
    spec = read_spec(path)
    if spec.conditioning.scene_warp:
        return
    model = WorldModel(replace(spec, conditioning=replace(spec.conditioning, scene_warp=True)))
    fresh = model.state_dict()
    before = [k for k, p in WorldModel(spec).named_parameters() if p.requires_grad]
    after = [k for k, p in model.named_parameters() if p.requires_grad]
    state = read_trainer_state(path)
    optimizer = state["optimizer"]
    optimizer["state"] = {after.index(before[int(i)]): m for i, m in optimizer["state"].items()}
    if len(optimizer["param_groups"]) != 1:
        raise InputError(f"{path}: the optimizer has {len(optimizer['param_groups'])} parameter groups; "
                         "the scene warp is added to checkpoints with one")
    optimizer["param_groups"][0]["params"] = list(range(len(after)))
    _rewrite(path, model.spec, lambda weights: {k: weights.get(k, fresh[k]) for k in fresh}, state, "scene_warp")


def _rewrite(path: Path, spec: ModelSpec, weights_of, state: dict, switch: str) -> None:
    """Write a branched checkpoint beside ``path`` and swap it in whole: its weights and EMA through
    ``weights_of``, the trainer ``state``, the ``spec`` and the run's ``conditioning.<switch>`` on."""
    if is_sharded(path):
        raise InputError(f"{path}: a sharded checkpoint cannot be branched here; branch a plain one")
    tmp = path.with_name(path.name + ".widening")
    shutil.rmtree(tmp, ignore_errors=True)
    shutil.copytree(path, tmp)
    save_file(weights_of(read_weights(path / WEIGHTS)), str(tmp / WEIGHTS))
    if (path / EMA).is_file():
        save_file(weights_of(read_weights(path / EMA)), str(tmp / EMA))
    torch.save(state, tmp / STATE)
    save_config(spec, tmp / SPEC)
    run = run_config_of(path)
    if run is not None:
        run.setdefault("conditioning", {})[switch] = True
        (tmp / CONFIG).write_text(yaml.safe_dump(run, sort_keys=False))
    shutil.rmtree(path)
    os.replace(tmp, path)


def respec(checkpoint: Path, changes: dict) -> None:
    """The branched checkpoint's model spec with the arm's changes to it (``flow.*``, ...), so the
    trainer resumes it as the arm's model; a first-frame arm's weights widened first."""
    if changes.get("conditioning.first_frame"):
        add_first_frame(checkpoint)
    if changes.get("conditioning.scene_warp"):
        add_scene_warp(checkpoint)
    spec = json.loads((checkpoint / SPEC).read_text())
    for key, value in changes.items():
        section, _, name = key.rpartition(".")
        if section in spec:  # (a run's settings, such as rollout.chunks, are not the model's)
            spec[section][name] = value
    (checkpoint / SPEC).write_text(json.dumps(spec, indent=1) + "\n")


def branch(plan: RankingPlan, arm: str, from_step: int, changes: dict | None = None,
           source: str | None = None) -> Path:
    """``<work>/runs/<arm>``: a copy of the preset's motion+contact run (or of the run ``source``)
    at ``from_step`` (its checkpoint, the log up to it), unless it exists; a first-frame arm's
    checkpoint widened."""
    base = plan.run_dir(GATED_MODE) if source is None else plan.work / "runs" / source
    run = plan.work / "runs" / arm
    if (run / "branch.json").is_file():
        return run
    source = base / "checkpoints" / f"step_{from_step:06d}"
    if not source.is_dir():
        have = sorted(p.name for p in (base / "checkpoints").glob("step_*"))
        raise InputError(f"--from-step {from_step}: {source} does not exist (the run keeps {have or 'none'})")
    tmp = run.with_name(run.name + ".branching")
    shutil.rmtree(tmp, ignore_errors=True)
    shutil.copytree(source, tmp / "checkpoints" / source.name)
    respec(tmp / "checkpoints" / source.name, changes or {})
    rows = read_log(base, upto=from_step)
    write_log(tmp, rows)
    (tmp / "branch.json").write_text(json.dumps({"from": str(base.relative_to(plan.work)), "step": from_step,
                                                 "cpu_s": rows[-1].get("cpu_s")}, indent=1) + "\n")
    tmp.rename(run)
    return run


def train_arm(plan: RankingPlan, run: Path, changes: dict, minutes: float) -> None:
    """Train the arm to ``minutes`` CPU-minutes with ``changes`` (resumes; marks it trained)."""
    if (run / "DONE.json").is_file():
        return
    argv = train_command(plan, GATED_MODE, minutes, changes={"train.output_dir": str(run), **changes})
    run_all([(f"train {run.name}", argv, plan.work / "logs" / f"train_{run.name}.log",
              partial(progress_line, run, minutes))], 1, tag="ablation")


def final_gate(plan: RankingPlan, run_name: str, from_step: int, minutes: float) -> dict | None:
    """The run's gate at the end of its budget, of a checkpoint at or after ``from_step``."""
    return next((g for g in reversed(read_gates(plan, run_name))
                 if g["budget_minutes"] == minutes and g["step"] >= from_step), None)


def ablate(plan: RankingPlan, ablation: str, from_step: int, minutes: float | None = None,
           baseline: str | None = None, source: str | None = None) -> dict | None:
    """Branch (from the preset's run, or the run ``source``), train and gate the arm; its figures
    beside the baseline's (the preset's run, or the arm ``baseline`` at the same budget), or None
    while the baseline has no gate there yet."""
    minutes = float(plan.cpu_minutes if minutes is None else minutes)
    arm, changes = arm_run(plan, ablation, minutes)
    run = branch(plan, arm, from_step, changes, source)
    train_arm(plan, run, changes, minutes)
    if final_gate(plan, arm, from_step, minutes) is None:
        run_all([(f"gate {arm}", internal(plan, "gate", f"{minutes:g}", arm),
                  plan.work / "logs" / f"gate_{arm}.log")], 1, tag="ablation")
    base_run, base_changes = ((plan.run_dir(GATED_MODE).name, {}) if baseline is None
                              else arm_run(plan, baseline, minutes))
    base_gate = final_gate(plan, base_run, from_step, minutes)
    if base_gate is None:
        if baseline is not None:
            how = f"python -m benchmarks.cpu_ablation {baseline} --from-step {from_step} --minutes {minutes:g}"
        elif minutes > plan.cpu_minutes:
            how = (f"the preset stops at {plan.cpu_minutes:g}, so name another arm trained to {minutes:g} as the "
                   f"baseline (--baseline ARM)")
        else:
            how = f"run the CPU preset to the end of its budget (imac-model ranking --work {plan.work})"
        print(f"[ablation] {arm} is gated; its baseline {base_run} has no gate at {minutes:g} CPU-minutes after "
              f"step {from_step} yet: {how}, then this again")
        return None
    batch = plan.run_config(GATED_MODE).train.batch_size
    result = {"ablation": ablation, "changes": changes, "from_step": from_step, "cpu_minutes": minutes,
              "baseline_changes": base_changes}
    for name, gate, run_name, ch in (("baseline", base_gate, base_run, base_changes),
                                     ("arm", final_gate(plan, arm, from_step, minutes), arm, changes)):
        rows = read_log(plan.work / "runs" / run_name)
        chunks_per_step = batch * int(ch.get("rollout.chunks", 1))
        result[name] = {"run": run_name, "step": gate["step"], "chunks": (gate["step"] - from_step) * chunks_per_step,
                        "balanced_accuracy_from_chunk": {k: v["balanced_accuracy"]
                                                         for k, v in gate["from_chunk"].items()},
                        "cube_at_chunk_end": gate.get("cube_at_chunk_end"),
                        "heldout_loss": next((r["heldout_loss"] for r in reversed(rows) if "heldout_loss" in r),
                                             None)}
    return result


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("ablation", choices=sorted(ABLATIONS))
    p.add_argument("--work", default="runs/ranking_cpu", help="the CPU preset's work directory")
    p.add_argument("--from-step", type=int, required=True, help="the checkpoint of motion+contact the arm starts from")
    p.add_argument("--minutes", type=float, help="the CPU budget to train to (default: the preset's)")
    p.add_argument("--baseline", choices=sorted(ABLATIONS),
                   help="compare with this arm at the same budget (default: the preset's own run)")
    p.add_argument("--from-run", help="branch from this run of the work directory (default: the preset's)")
    p.add_argument("--json", help="write the figures here")
    args = p.parse_args(argv)
    plan = RankingPlan.load(Path(args.work) / "plan.json")
    result = ablate(plan, args.ablation, args.from_step, args.minutes, args.baseline, args.from_run)
    if result is None:
        return 0
    for name in ("baseline", "arm"):
        r = result[name]
        gate = " ".join(f"{x:.2f}" for x in r["balanced_accuracy_from_chunk"].values())
        print(f"{name:8s} {r['run']}: step {r['step']}, {r['chunks']} chunks trained after step {args.from_step}; "
              f"gate from chunk 1.. {gate}; held-out loss {r['heldout_loss']:.4f}; cube at each chunk's end "
              f"{r['cube_at_chunk_end']}")
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
