"""The ranking benchmark's first stage (``simulate``): every policy in MuJoCo from the evaluation
starts (``imac-model evaluate simulator``), and the world model's training rollouts (the scripted mix,
and the plan's ``training_policies`` at their share; other starts), in parallel processes."""

from __future__ import annotations

import json
import shutil

from imac_model.evaluate.policies import load_policy, policy_name
from imac_model.evaluate.simulator import SimRunConfig, SimRunner, run_policy
from imac_model.experiments.ranking.plan import TRAIN_SEED0, RankingPlan, internal, slug
from imac_model.experiments.ranking.policies import training_policy
from imac_model.experiments.stages import python, run_all, then_mark_done

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
    loaded: dict = {}  # the training policies this part runs, each loaded once
    with SimRunner(SimRunConfig(chunks=plan.chunks, view_height=plan.view_size[0], view_width=plan.view_size[1],
                                   views=plan.views, settle_s=plan.settle_s)) as runner:
        rows = []
        for i in range(part, plan.train_episodes, parts):
            spec = plan.training_policy_of(i)
            p = training_policy(i, plan.training_offsets) if spec is None else \
                loaded.setdefault(spec, load_policy(spec))
            rows += run_policy(p, [TRAIN_SEED0 + i], out / f"ep_{i:05d}", runner=runner, progress=False)
            rows[-1].update(index=i, policy=policy_name(p) if spec is None else slug(spec),
                            offset=None if spec is not None else p.offset.tolist())
    (out / "outcomes.json").write_text(json.dumps(rows, indent=1))
