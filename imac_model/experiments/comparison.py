"""The paper's comparison at small scale (``make experiment``, ``imac-model experiment``):
record 44 simulated episodes, build them, decode their chunks once, train five conditioning
settings for the same CPU budget each, evaluate multi-chunk rollouts and action sensitivity
on held-out episodes, and write ``docs/experiment/``. Every stage is cached under ``--work``
and resumes where it stopped; each stage's wall and CPU seconds are recorded."""

from __future__ import annotations

import json
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

from imac_data.layout import info_path
from imac_data.metadata import dataset_info
from imac_data.recipes import load_recipe
from imac_model.config import load_run_config
from imac_model.data.chunks import ChunkDataset, open_metadata, resolve_layout
from imac_model.evaluate import open_loop
from imac_model.experiments.comparison_report import write_report
from imac_model.experiments.stages import REPO_ROOT, python, run_all, then_mark_done, train_job
from imac_model.models.backbones.build import spatial_multiple, temporal_factor
from imac_model.models.checkpoint import load_world_model
from imac_model.modes import CONTROL_STREAMS
from imac_model.pipelines.online_controls import OnlineControls
from imac_model.training.dataset_source import decode_to_cache
from imac_model.training.log import read_log

REPO = "local/imac_experiment"
RECIPE = REPO_ROOT / "recipes" / "aloha_sim_transfer_cube_experiment.yaml"
CONFIG = REPO_ROOT / "imac_model" / "configs" / "experiment.yaml"
STAGES = ("record", "build", "decode", "train", "evaluate", "report")
GROUP = 4  # episodes recorded per resumable group
ROLLOUT_CHUNKS = 4  # chunks per evaluated rollout
SENSITIVITY_CHUNKS = (2, 6)  # start chunks of the action-sensitivity samples (mid-motion)
# the deviation of the second action sequence: both waists and shoulders, radians at the chunk's last step
SENSITIVITY_OFFSETS = {0: 0.35, 1: -0.25, 7: -0.35, 8: -0.25}


@dataclass(frozen=True)
class Setting:
    name: str  # as in the tables
    slug: str  # directory name
    overrides: dict = field(default_factory=dict)


SETTINGS = (
    Setting("none", "none", {"conditioning.mode": "none"}),
    Setting("action-vector", "action_vector", {"conditioning.mode": "action-vector"}),
    Setting("motion", "motion", {"conditioning.mode": "motion"}),
    Setting("motion+contact", "motion_contact", {"conditioning.mode": "motion+contact"}),
    Setting("motion+contact + rollout", "motion_contact_rollout", {"conditioning.mode": "motion+contact",
                                                                   "rollout.chunks": 4}),
)


@dataclass
class Plan:
    work: Path
    docs: Path
    episodes: int = 44
    held_out: int = 8
    cpu_minutes: float = 15.0
    jobs: int = 5
    seed: int = 0
    steps: int | None = None  # Euler steps at evaluation (None: the model's)
    warmup_epochs: float = 5.0  # the rollout setting's ordinary (clean-reference) steps first

    @property
    def dataset(self) -> Path:
        return self.work / "dataset"

    @property
    def cache(self) -> Path:
        return self.work / "chunkcache"

    @property
    def held_out_episodes(self) -> list[int]:
        return list(range(self.episodes - self.held_out, self.episodes))

    def run_dir(self, s: Setting) -> Path:
        return self.work / "runs" / s.slug

    def eval_file(self, s: Setting) -> Path:
        return self.work / "eval" / f"{s.slug}.json"

    def overrides(self, s: Setting) -> dict:
        return {"data.dataset": REPO, "data.root": str(self.dataset), "data.cache_dir": str(self.cache),
                "data.held_out_episodes": self.held_out_episodes, "train.max_cpu_minutes": self.cpu_minutes,
                "train.output_dir": str(self.run_dir(s)), "train.seed": self.seed, **s.overrides,
                **({"rollout.warmup_epochs": self.warmup_epochs} if "rollout.chunks" in s.overrides else {})}


# --------------------------------------------------------------------------- stages


def stage_record(plan: Plan) -> None:
    if info_path(plan.dataset).is_file():
        return  # built already
    sim = load_recipe(RECIPE).source.sim
    groups = [(g, min(GROUP, plan.episodes - g * GROUP)) for g in range((plan.episodes + GROUP - 1) // GROUP)]
    commands = []
    for g, n in groups:
        out = plan.work / "sim" / f"group_{g:02d}"
        if (out / ".done").is_file():
            continue
        shutil.rmtree(out, ignore_errors=True)  # a group interrupted mid-way is recorded again
        argv = python() + ["-m", "imac_data", "simulate", "--task", sim.task, "--episodes", str(n), "--out", str(out),
                            "--width", str(sim.width), "--height", str(sim.height), "--seed", str(sim.seed + g * GROUP),
                            "--noise", str(sim.noise), "--frame-stride", str(sim.frame_stride), "--quiet"]
        # the group is marked done only when the recorder exits cleanly
        commands.append((f"record group {g}", then_mark_done(argv, out / ".done"), plan.work / "logs" / "record.log"))
    run_all(commands, 2)
    # one source directory: episode i = seed + i, in natural order
    src = plan.work / "sim" / "all"
    tmp = src.with_name("all.tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    i = 0
    for g, n in groups:
        d = plan.work / "sim" / f"group_{g:02d}"
        for j in range(n):
            (tmp / f"episode_{i}.hdf5").symlink_to((d / f"episode_{j}.hdf5").resolve())
            i += 1
    shutil.copy(plan.work / "sim" / "group_00" / "calibration.json", tmp / "calibration.json")
    shutil.rmtree(src, ignore_errors=True)
    os.replace(tmp, src)


def stage_build(plan: Plan) -> None:
    if info_path(plan.dataset).is_file():
        return  # the build moves a dataset into place only when it is complete
    argv = python() + ["-m", "imac_data.build", "--repo", REPO, "--recipe", str(RECIPE),
                        "--source", str(plan.work / "sim" / "all"), "--root", str(plan.dataset),
                        "--episodes", str(plan.episodes), "--workers", "2", "--no-progress",
                        "--timings", str(plan.work / "build_timings.json")]
    run_all([("build", argv, plan.work / "logs" / "build.log")], 1)


def run_config(plan: Plan, s: Setting):
    return load_run_config(CONFIG, plan.overrides(s))


def decode_chunks(plan: Plan) -> None:
    """(in a fresh process: LeRobot's video decoders must not be forked after use)"""
    decode_to_cache(run_config(plan, SETTINGS[3]), workers=2)  # every control stream: the others reuse its cache


def stage_decode(plan: Plan) -> None:
    argv = python() + ["-m", "imac_model", "experiment", *plan_args(plan), "--internal", "decode"]
    run_all([("decode", argv, plan.work / "logs" / "decode.log")], 1)


def _done_file(plan: Plan, s: Setting) -> Path:
    return plan.run_dir(s) / "DONE.json"


def stage_train(plan: Plan) -> None:
    commands = []
    for s in SETTINGS:
        if _done_file(plan, s).is_file():
            continue
        commands.append((f"train {s.name}", train_job(CONFIG, plan.overrides(s)),
                         plan.work / "logs" / f"train_{s.slug}.log"))
    run_all(commands, plan.jobs)


def stage_evaluate(plan: Plan) -> None:
    commands = []
    for s in SETTINGS:
        if plan.eval_file(s).is_file():
            continue
        argv = python() + ["-m", "imac_model", "experiment", *plan_args(plan), "--internal", "evaluate", "--setting",
                            s.slug]
        commands.append((f"evaluate {s.name}", argv, plan.work / "logs" / f"evaluate_{s.slug}.log"))
    run_all(commands, 2)


def evaluate_setting(plan: Plan, s: Setting) -> None:
    """One setting's held-out evaluation (in its own process) -> ``eval/<slug>.json`` + ``.pt``."""
    import torch

    torch.set_num_threads(1)
    t_wall, t_cpu = time.time(), time.process_time()
    model, spec = load_world_model(plan.run_dir(s), weights="ema")
    run = run_config(plan, s)
    meta = open_metadata(run.data)
    info = dataset_info(meta)
    layout = resolve_layout(info, run.data, CONTROL_STREAMS, spatial_multiple=spatial_multiple(spec.backbone),
                            temporal_factor=temporal_factor(spec.backbone), mode="motion+contact")
    held = plan.held_out_episodes
    ds = ChunkDataset(REPO, layout, root=run.data.root, episodes=held, cache="memory", cache_dir=run.data.cache_dir)
    ds.preload(progress=False)
    online = OnlineControls.from_dataset(plan.dataset, spec, info=info, resolution=run.rollout.resolution,
                                         max_walk_distance=run.rollout.max_walk_distance)
    starts = open_loop.rollout_starts(ds, held, ROLLOUT_CHUNKS, ROLLOUT_CHUNKS)
    videos = open_loop.rollout_videos(model, ds, starts, ROLLOUT_CHUNKS, online, steps=plan.steps, seed=plan.seed)
    H = spec.chunk
    metrics = open_loop.per_chunk_metrics(videos.generated, videos.recorded, horizon=H, views=spec.views,
                                          sampler_steps=plan.steps or spec.flow.sample_steps, seed=plan.seed)
    by_outcome = {}
    for label in (True, False):
        idx = [i for i, (e, _) in enumerate(starts) if ds.success.get(e) is label]
        if idx:
            m = open_loop.per_chunk_metrics(videos.generated[idx], videos.recorded[idx], horizon=H, views=spec.views)
            by_outcome["success" if label else "failure"] = {"rollouts": len(idx), "chunks": open_loop.summarise(m)}
    copy = open_loop.copy_reference_mse(videos.reference, videos.recorded, H, len(spec.views))
    sens_starts = [(e, c) for e in held for c in SENSITIVITY_CHUNKS if c < len(ds.episode_chunks(e))]
    sens = open_loop.action_sensitivity(model, ds, sens_starts, online, offsets=SENSITIVITY_OFFSETS,
                                        steps=plan.steps, seed=plan.seed)
    log = read_log(plan.run_dir(s))
    chunks = open_loop.summarise(metrics)
    result = {
        "setting": s.name, "slug": s.slug, "overrides": s.overrides,
        "rollouts": len(starts), "starts": starts, "chunks": chunks,
        "mse_growth": open_loop.growth([c["mse"] for c in chunks]),
        "copy_reference_mse": copy, "by_outcome": by_outcome,
        "per_view": [{v: r["pooled"][v] for v in spec.views} for r in metrics],
        "protocol": metrics[0]["protocol"],
        "invalid_generated_depth": (sum(videos.invalid_depth) / len(videos.invalid_depth)
                                    if videos.invalid_depth else None),
        "sensitivity": {"inside": sens.inside, "outside": sens.outside, "ratio": sens.ratio,
                        "region_share": sens.region_share, "samples": sens.samples,
                        "offsets_rad": SENSITIVITY_OFFSETS, "start_chunks": list(SENSITIVITY_CHUNKS),
                        "example_start": sens.example.get("start")},
        "training": {"steps": log[-1]["step"], "cpu_s": log[-1].get("cpu_s"), "wall_s": log[-1].get("wall_s"),
                     "heldout_loss_first": log[0].get("heldout_loss"),
                     "heldout_loss_last": next((r["heldout_loss"] for r in reversed(log) if "heldout_loss" in r), None),
                     "rollout_steps": _rollout_steps(log)},
        "evaluation_wall_s": round(time.time() - t_wall, 1), "evaluation_cpu_s": round(time.process_time() - t_cpu, 1),
    }
    show = next((i for i, (e, c) in enumerate(starts) if c == ROLLOUT_CHUNKS), 0)
    plan.eval_file(s).parent.mkdir(parents=True, exist_ok=True)
    torch.save({"generated": videos.generated[show], "recorded": videos.recorded[show],
                "reference": videos.reference[show], "start": starts[show], "sensitivity": sens.example},
               plan.eval_file(s).with_suffix(".pt"))
    tmp = plan.eval_file(s).with_suffix(".tmp")
    tmp.write_text(json.dumps(result, indent=1))
    os.replace(tmp, plan.eval_file(s))


def _rollout_steps(log: list[dict]) -> int:
    """Steps trained as R-chunk rollouts (from the logged phase of each logging window)."""
    steps, prev = 0, 0
    for r in log:
        if "loss" not in r:
            continue
        if r.get("phase") == "rollout":
            steps += r["step"] - prev
        prev = r["step"]
    return steps


def stage_report(plan: Plan) -> None:
    write_report(plan, SETTINGS)


# --------------------------------------------------------------------------- CLI


def plan_args(plan: Plan) -> list[str]:
    args = ["--work", str(plan.work), "--docs", str(plan.docs), "--episodes", str(plan.episodes),
            "--held-out", str(plan.held_out), "--cpu-minutes", str(plan.cpu_minutes), "--jobs", str(plan.jobs),
            "--seed", str(plan.seed), "--warmup-epochs", str(plan.warmup_epochs)]
    return args + (["--steps", str(plan.steps)] if plan.steps else [])
