"""benchmarks.lerobot_policy at toy size: simulated demonstrations, ``imac build``, LeRobot's ``remove_feature`` and
``lerobot-train``, resumed; the checkpoints load through the benchmark's ``lerobot:`` policies and see what the
world model draws (docs/ranking.md, "LeRobot checkpoints")."""

from __future__ import annotations

import json

import torch
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from benchmarks import lerobot_policy
from imac_data.layout import STATE, image_key, info_path
from imac_model.evaluate.policies import load_policy, make_observation, recorded_actions_policy
from imac_model.evaluate.simulator import SimRunConfig, SimRunner
from imac_model.experiments.ranking.plan import RankingPlan
from imac_model.experiments.ranking.policies import WORKSPACE


def test_demonstrations_become_act_checkpoints_that_resume_and_act_on_the_world_models_view(tmp_path, capsys):
    work = tmp_path / "act"
    args = ["--work", str(work), "--demos", "2", "--jobs", "1", "--save-every", "1"]
    assert lerobot_policy.main([*args, "--steps", "1"]) == 0
    assert lerobot_policy.main([*args, "--steps", "2"]) == 0  # resumes from step 1
    specs = capsys.readouterr().out.strip().splitlines()[-2:]
    assert [s.rsplit("/", 2)[-2] for s in specs] == ["000001", "000002"]
    assert "'resume': True" in (work / "logs" / "train.log").read_text()  # lerobot-train's own config print

    stages = json.loads((work / "stages.json").read_text())  # each run's cost, stage by stage
    assert [e["stage"] for e in stages] == ["demos", "build", "select", "train"] * 2
    demos = json.loads(info_path(work / "demos").read_text())["features"]
    assert any(k.startswith("control.motion.") for k in demos)  # an imac build, every stream
    # the demonstration whose arm rolled onto the expert's other IK branch is dropped by LeRobot's delete_episodes
    selection = json.loads((work / "selection.json").read_text())
    assert selection == {"demonstrations": 2, "kept": 1, "other_ik_branch": [1]}
    assert json.loads(info_path(work / "policy_data").read_text())["total_episodes"] == 1
    stats = json.loads((work / "policy_data" / "meta" / "stats.json").read_text())
    assert min(stats[STATE]["std"] + stats["action"]["std"]) == lerobot_policy.STD_FLOOR  # the still left arm
    kept = json.loads(info_path(work / "policy_data").read_text())["features"]
    assert {k for k, f in kept.items() if f["dtype"] == "video"} == {image_key(WORKSPACE)}
    assert {STATE, "action"} <= set(kept) and not any(k.startswith(("control.", "camera_pose.")) for k in kept)

    # the state is the one the benchmark's runners give at each chunk start: MuJoCo's own runner, replaying the kept
    # demonstration's actions, hands the policy the measured state first and the commanded one after
    data = LeRobotDataset("local/policy", root=work / "policy_data").hf_dataset.with_format("torch")
    states, actions = torch.stack(list(data[STATE])), torch.stack(list(data["action"]))
    plan = RankingPlan(work=work, docs=work)
    with SimRunner(SimRunConfig(chunks=plan.chunks, view_height=plan.view_size[0], view_width=plan.view_size[1],
                                views=plan.views, settle_s=plan.settle_s)) as runner:
        replay = runner.run_episode(recorded_actions_policy(actions), lerobot_policy.DEMO_SEED0, keep_observations=True)
    given = torch.stack([o[STATE] for o in replay.observations])
    starts = [8 * n for n in range(plan.chunks)]
    assert torch.allclose(given, states[starts], atol=1e-6), (given - states[starts]).abs().max()
    measured = torch.as_tensor(replay.qpos[starts], dtype=torch.float32)
    assert torch.equal(states[0], measured[0]) and (states[starts[1:]] - measured[1:]).abs().max() > 1e-3

    policy = load_policy(specs[-1])
    assert policy.image_shapes == {image_key(WORKSPACE): (3, 48, 64)}
    obs = make_observation(torch.rand(1, 3, 48, 64), None, torch.zeros(14), [WORKSPACE], "lift")
    assert tuple(policy(obs).shape) == (8, 14)
