"""Checkpoints of a LeRobot policy for the ranking benchmark (docs/ranking.md, "LeRobot checkpoints"), made the way
the README promises a user makes them:

1. ``demos``: lift demonstrations in MuJoCo, with the benchmark's protocol (the workspace view at 48x64, 4 chunks,
   the box settled) and the scripted ``closed_loop`` policy, from starts no evaluation uses; the successes are kept;
2. ``build``: ``imac build`` makes them a LeRobot dataset with every stream (``<work>/demos``);
3. ``select``: LeRobot's own ``remove_feature`` keeps what the policy sees, the workspace view, the state and the
   actions (``<work>/policy_data``: one video to decode a sample instead of twenty), and its ``delete_episodes``
   the demonstrations whose arm took the expert's other IK branch (:func:`other_branch`);
4. ``train``: ``lerobot-train`` trains ACT on it (``benchmarks/configs/lerobot_act.yaml``), keeping a checkpoint
   every ``--save-every`` steps.

Every stage resumes: a finished one is skipped, and the training continues from its last checkpoint::

    python -m benchmarks.lerobot_policy --work runs/lerobot_act
    python -m benchmarks.lerobot_policy --work runs/lerobot_act --list   # the checkpoints, as --policies specs
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
from pathlib import Path

import numpy as np
import torch
import yaml

from imac_data import lerobot_compat as lr
from imac_data.core.motion import rollout
from imac_data.core.robot.platforms import PLATFORMS, simulator_platform
from imac_data.layout import STATE, image_key, info_path
from imac_model.experiments.ranking.datasets import link_episodes
from imac_model.experiments.ranking.plan import POLICY_MODULE, RECIPE, RankingPlan
from imac_model.experiments.ranking.policies import RIGHT_ARM, WORKSPACE
from imac_model.experiments.stages import REPO_ROOT, StageLog, python, run_all, then_mark_done

CONFIG = REPO_ROOT / "benchmarks" / "configs" / "lerobot_act.yaml"
DEMO_SEED0 = 300_000  # demonstration d starts from DEMO_SEED0 + d: never an evaluation start or a training rollout's
EXPERT = f"python:{POLICY_MODULE}:closed_loop"  # MuJoCo success 1.00 on the evaluation starts
DEMO_REPO, POLICY_REPO = "local/lift_demos", "local/lift_demos_policy"
KEEP = (image_key(WORKSPACE), STATE, "action")  # what the policy sees and does
ROLLS = (RIGHT_ARM.start + 3, RIGHT_ARM.start + 5)  # the right forearm's and wrist's roll joints in the actions


def simulate_demos(work: Path, plan: RankingPlan, demos: int, jobs: int) -> None:
    """``demos`` expert episodes in ``jobs`` processes (``<work>/sim/part_k``)."""
    commands = []
    for k in range(jobs):
        seeds = [str(DEMO_SEED0 + d) for d in range(k, demos, jobs)]
        out = work / "sim" / f"part_{k}"
        if not seeds or (out / ".done").is_file():
            continue
        shutil.rmtree(out, ignore_errors=True)
        argv = python() + ["-m", "imac_model", "evaluate", "simulator", "--policy", EXPERT, "--seeds", *seeds,
                           "--chunks", str(plan.chunks), "--view-size", *map(str, plan.view_size),
                           "--views", *plan.views, "--settle", str(plan.settle_s), "--output", str(out),
                           "--no-progress"]
        commands.append((f"demonstrations part {k}", then_mark_done(argv, out / ".done"),
                         work / "logs" / f"sim_{k}.log"))
    run_all(commands, jobs, tag="lerobot_policy")


def successful_episodes(work: Path, jobs: int) -> list[Path]:
    """The demonstrations that lifted the cube, in seed order."""
    kept = []
    for k in range(jobs):
        part = work / "sim" / f"part_{k}"
        if (part / "outcomes.json").is_file():
            rows = json.loads((part / "outcomes.json").read_text())["episodes"]
            kept += [(r["seed"], part / f"episode_{r['episode_index']}.hdf5") for r in rows if r["success"]]
    return [path for _, path in sorted(kept)]


def build_demos(work: Path, jobs: int) -> Path:
    root = work / "demos"
    if info_path(root).is_file():  # a build moves its dataset into place only when complete
        return root
    episodes = successful_episodes(work, jobs)
    if not episodes:
        raise SystemExit(f"lerobot_policy: no successful demonstration under {work / 'sim'}")
    link_episodes(episodes, work / "sim" / "kept")
    argv = python() + ["-m", "imac_data.build", "--repo", DEMO_REPO, "--recipe", str(RECIPE),
                       "--source", str(work / "sim" / "kept"), "--root", str(root), "--episodes", str(len(episodes)),
                       "--workers", str(jobs), "--no-progress", "--overwrite"]
    run_all([("build demonstrations", argv, work / "logs" / "build.log")], 1, tag="lerobot_policy")
    return root


def other_branch(actions: np.ndarray, episodes: np.ndarray) -> list[int]:
    """The demonstrations whose arm took the other inverse-kinematics branch: the expert's IK reaches the same grasp
    with the right forearm and wrist rolled by about pi in some episodes (docs/ranking.md), a second mode that a
    policy trained on both would average into neither."""
    rolled = np.abs(actions[:, list(ROLLS)]).max(axis=1) > np.pi / 2
    return sorted({int(e) for e in episodes[rolled]})


STD_FLOOR = 0.01  # radians (and the gripper's 0..1): the least spread a joint's statistics may claim


def floor_std(stats_file: Path) -> None:
    """The state's and actions' standard deviations raised to ``STD_FLOOR``. The left arm holds still: its joints
    spread by 1e-6 to 1e-3 rad over the demonstrations, so LeRobot's mean-std normalisation made a 1e-4 rad
    difference (commanded against measured, as the runners give it after the first chunk) an input of up to 100
    standard deviations, and the left arm's jitter a target the policy cannot predict."""
    stats = json.loads(stats_file.read_text())
    for key in (STATE, "action"):
        stats[key]["std"] = [max(float(x), STD_FLOOR) for x in stats[key]["std"]]
    stats_file.write_text(json.dumps(stats, indent=4))


def commanded_states(states: np.ndarray, actions: np.ndarray, episodes: np.ndarray) -> np.ndarray:
    """The state the benchmark's runners give a policy (:mod:`imac_model.evaluate.simulator`, and the world model's
    closed loop alike): each episode's measured configuration at its first frame, then the configuration its actions
    so far command (phi, the simulator rig's controller). The recording's measured state differs from it most where
    the gripper closes on the cube (0.22 rad on average at the chunk starts, up to 0.56): ACT trained on the
    measured state erred four times as much given the commanded one (docs/ranking.md, "LeRobot checkpoints")."""
    controller = PLATFORMS[simulator_platform()].controller("lift")  # the benchmark's task
    out = np.empty_like(states, dtype=np.float32)
    for e in np.unique(episodes):
        rows = np.flatnonzero(episodes == e)
        q0 = torch.as_tensor(states[rows[0]], dtype=torch.float32)[None]
        chain = rollout(q0, torch.as_tensor(actions[rows[:-1]], dtype=torch.float32)[None], controller)[0]
        out[rows] = torch.cat([q0, chain]).numpy()
    return out


def with_commanded_state(dataset, output_dir: Path):
    """``dataset`` with its ``observation.state`` replaced by :func:`commanded_states`, by LeRobot's own
    ``remove_feature`` and ``modify_features``, and the statistics of the new column (LeRobot's
    ``get_feature_stats``) written into ``stats.json``, which ``modify_features`` leaves without them."""
    columns = dataset.hf_dataset.with_format("numpy")
    index = np.asarray(columns["index"])
    commanded = dict(zip(index.tolist(), commanded_states(np.stack(columns[STATE]), np.stack(columns["action"]),
                                                          np.asarray(columns["episode_index"]))))
    info = dict(dataset.meta.features[STATE])
    bare = output_dir.with_name(output_dir.name + ".bare")
    shutil.rmtree(bare, ignore_errors=True)
    stripped = lr.remove_feature(dataset, feature_names=[STATE], output_dir=bare, repo_id=POLICY_REPO)
    out = lr.modify_features(stripped, add_features={STATE: (lambda row, ep, frame: commanded[int(row["index"])], info)},
                             output_dir=output_dir, repo_id=POLICY_REPO)
    shutil.rmtree(bare, ignore_errors=True)
    stats_file = output_dir / "meta" / "stats.json"
    stats = json.loads(stats_file.read_text())
    values = np.stack([commanded[i] for i in sorted(commanded)])
    stats[STATE] = {k: np.asarray(v).tolist() for k, v in lr.get_feature_stats(values, axis=0, keepdims=False).items()}
    stats_file.write_text(json.dumps(stats, indent=4))
    return out


def select_features(work: Path, demos: Path) -> Path:
    """What the policy trains on, cut from the built dataset by LeRobot's own tools: ``KEEP`` (``remove_feature``),
    the demonstrations of one IK branch (``delete_episodes``; which were dropped goes to ``selection.json``), and
    the state as the runners give it (:func:`with_commanded_state`)."""
    out = work / "policy_data"
    if info_path(out).is_file():
        return out
    dataset = lr.LeRobotDataset(DEMO_REPO, root=demos)
    drop = [k for k, f in dataset.meta.features.items()
            if k not in KEEP and (f["dtype"] in ("video", "image") or k.startswith(("camera_pose.", "control.")))]
    columns = dataset.hf_dataset.with_format("numpy")
    dropped = other_branch(np.stack(columns["action"]), np.asarray(columns["episode_index"]))
    if len(dropped) == dataset.meta.total_episodes:
        raise SystemExit(f"lerobot_policy: every demonstration in {demos} took the other IK branch; simulate more")
    tmp = [out.with_name(out.name + s) for s in (".episodes", ".cut", ".tmp")]
    for t in tmp:
        shutil.rmtree(t, ignore_errors=True)
    # episodes first: LeRobot 0.4.4's remove_feature keeps the removed features' per-episode statistics, on which
    # its delete_episodes then fails ("Shape of quantile 'min' must be (3,1,1)")
    if dropped:
        dataset = lr.delete_episodes(dataset, episode_indices=dropped, output_dir=tmp[0],
                                                repo_id=DEMO_REPO)
    cut = lr.remove_feature(dataset, feature_names=drop, output_dir=tmp[1], repo_id=POLICY_REPO)
    with_commanded_state(cut, tmp[2])
    for t in tmp[:2]:
        shutil.rmtree(t, ignore_errors=True)
    floor_std(tmp[2] / "meta" / "stats.json")
    os.replace(tmp[2], out)
    (work / "selection.json").write_text(json.dumps({"demonstrations": dataset.meta.total_episodes + len(dropped),
                                                     "kept": dataset.meta.total_episodes,
                                                     "other_ik_branch": dropped}, indent=1))
    return out


def train_config(work: Path, data: Path, plan: RankingPlan, steps: int, save_every: int, seed: int) -> Path:
    """lerobot-train's config file: ``CONFIG`` with this run's dataset, features, directory and length."""
    info = json.loads(info_path(data).read_text())["features"]
    config = yaml.safe_load(CONFIG.read_text())
    config["dataset"].update(repo_id=POLICY_REPO, root=str(data))
    config["dataset"]["image_transforms"]["tfs"]["resize"]["kwargs"]["size"] = list(plan.view_size)
    config["policy"].update(
        input_features={STATE: {"type": "STATE", "shape": info[STATE]["shape"]},
                        image_key(WORKSPACE): {"type": "VISUAL", "shape": [3, *plan.view_size]}},
        output_features={"action": {"type": "ACTION", "shape": info["action"]["shape"]}})
    config.update(output_dir=str(work / "train"), seed=seed, steps=steps, save_freq=save_every)
    path = work / "train_config.yaml"
    path.write_text(yaml.safe_dump(config, sort_keys=False))
    return path


def checkpoints(work: Path) -> list[Path]:
    """Every kept checkpoint's ``pretrained_model`` directory, in step order."""
    root = work / "train" / "checkpoints"
    return sorted(p / "pretrained_model" for p in root.glob("[0-9]*") if (p / "pretrained_model").is_dir())


def train(work: Path, config: Path, steps: int, threads: int) -> None:
    last = work / "train" / "checkpoints" / "last" / "pretrained_model"
    done = checkpoints(work)
    if done and int(done[-1].parent.name) >= steps:
        return
    if last.is_dir():  # lerobot-train's own resume: the weights, the optimiser and the data order
        argv = [f"--config_path={last / 'train_config.json'}", "--resume=true", f"--steps={steps}"]
    else:
        shutil.rmtree(work / "train", ignore_errors=True)  # no checkpoint yet: lerobot-train refuses an old directory
        argv = [f"--config_path={config}"]
    env_threads = {"OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)}
    command = ["env", *(f"{k}={v}" for k, v in env_threads.items()),
               *python(), "-m", "lerobot.scripts.lerobot_train", *argv]

    def progress() -> str:
        kept = checkpoints(work)
        return f"checkpoint {kept[-1].parent.name} of {steps}" if kept else "no checkpoint yet"

    print("lerobot_policy: lerobot-train " + " ".join(argv), flush=True)
    run_all([("lerobot-train", command, work / "logs" / "train.log", progress)], 1, tag="lerobot_policy")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.lerobot_policy", description=__doc__.split("\n\n")[0])
    p.add_argument("--work", type=Path, default=Path("runs/lerobot_act"), help="every stage's output (resumable)")
    p.add_argument("--demos", type=int, default=200, help="demonstrations simulated (the successes are kept)")
    p.add_argument("--steps", type=int, default=20_000, help="lerobot-train steps")
    p.add_argument("--save-every", type=int, default=2_000, help="steps between kept checkpoints")
    p.add_argument("--seed", type=int, default=1000, help="lerobot-train's seed")
    p.add_argument("--jobs", type=int, default=2, help="processes for the demonstrations and the build")
    p.add_argument("--threads", type=int, default=1, help="lerobot-train's CPU threads")
    p.add_argument("--list", action="store_true", help="print the kept checkpoints as lerobot: specs and stop")
    args = p.parse_args(argv)
    work = args.work.resolve()
    if not args.list:
        plan = RankingPlan(work=work, docs=work)  # the benchmark's protocol: view size, views, chunks, settling
        stages = StageLog(work / "stages.json", tag="lerobot_policy")  # wall and CPU seconds, children included
        stages.run("demos", lambda: simulate_demos(work, plan, args.demos, args.jobs))
        stages.run("build", lambda: build_demos(work, args.jobs))
        stages.run("select", lambda: select_features(work, work / "demos"))
        config = train_config(work, work / "policy_data", plan, args.steps, args.save_every, args.seed)
        stages.run("train", lambda: train(work, config, args.steps, args.threads))
    specs = [f"lerobot:{c}" for c in checkpoints(work)]
    print("\n".join(specs) if specs else f"lerobot_policy: no checkpoint under {work / 'train'}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
