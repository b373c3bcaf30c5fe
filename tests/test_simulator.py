"""The MuJoCo policy runner (imac_model/evaluate/simulator.py) as a policy author meets it: the
depth it is shown against MuJoCo's own geometry, `--seeds` ranges, the refusals (message, exit
code, nothing left in --output), and episodes that re-simulate from their own files."""

from __future__ import annotations

import sys
import textwrap
import xml.etree.ElementTree as ET

import h5py
import numpy as np
import pytest
import torch
from gym_aloha.constants import ASSETS_DIR, normalize_puppet_gripper_position

from imac_data.core.cameras import backproject
from imac_data.core.metric_depth import area_resize_depth, resize_depth
from imac_data.errors import InputError
from imac_data.layout import depth_key
from imac_data.sources.hdf5 import read_episode
from imac_data.sources.sim.env import SimEnv
from imac_data.sources.sim.rig import CONTROL_DT
from imac_data.sources.sim.tasks import REST_HEIGHT, TABLE_Z
from imac_model.cli import main as model_main
from imac_model.evaluate.policies import load_policy
from imac_model.evaluate.simulator import SimRunConfig, SimRunner, parse_seeds, run_policy

HEAD = "cam_high"


@pytest.fixture(scope="module")
def runner():
    with SimRunner(SimRunConfig()) as r:
        yield r


@pytest.fixture
def in_tmp(tmp_path, monkeypatch):
    """Run from ``tmp_path`` as a policy author would (sys.path restored afterwards)."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "path", list(sys.path))
    return tmp_path


def test_area_resized_depth_stands_for_each_pixels_centre_and_ignores_unknown():
    # a depth ramp along the rows: the mean over an output pixel's area is the ramp at its centre (exactly
    # for whole-number factors; partly covered source pixels count by their centre's value otherwise)
    H, W = 96, 128
    u = (np.arange(W) + 0.5)[None].repeat(H, 0)  # continuous column coordinate of each pixel centre
    ramp = (1.0 + 0.001 * u).astype(np.float64)
    for h, w, within in ((48, 64, 0.0), (24, 32, 0.0), (32, 40, 0.05), (40, 56, 0.05)):  # source pixels
        centres = 1.0 + 0.001 * (np.arange(w) + 0.5) * (W / w)
        np.testing.assert_allclose(area_resize_depth(ramp, (h, w)), np.broadcast_to(centres, (h, w)),
                                   rtol=0, atol=0.001 * within + 1e-12)
    nearest = resize_depth(ramp, (48, 64))  # the source pixel holding the centre: a quarter pixel off it
    np.testing.assert_allclose(nearest - area_resize_depth(ramp, (48, 64)), 0.0005)
    # unknown (0, NaN) pixels are never averaged in; a pixel mostly unknown is unknown
    d = np.array([[1.0, 0.0, 2.0, 0.0], [3.0, 5.0, np.nan, 0.0]], np.float32)
    np.testing.assert_allclose(area_resize_depth(d, (1, 2)), [[3.0, 0.0]])
    np.testing.assert_allclose(area_resize_depth(d, (1, 2), min_valid=0.25), [[3.0, 2.0]])
    t = area_resize_depth(torch.from_numpy(d), (1, 2))
    assert isinstance(t, torch.Tensor) and t.dtype == torch.float32 and t.tolist() == [[3.0, 0.0]]
    with pytest.raises(InputError, match="size must be positive"):
        area_resize_depth(d, (0, 2))


def cube_centre_from_depth(depth: torch.Tensor, K: torch.Tensor, T_world_cam: torch.Tensor, near) -> np.ndarray:
    """The cube's centre (x, y) from depth alone: the points standing above the table near
    ``near`` (below the arm), weighted by their height, as a policy without colour would."""
    points = backproject(depth.double(), K.double(), T_world_cam.double())
    z = points[..., 2] - TABLE_Z
    keep = (depth > 0) & (z > 0.005) & (z < 0.1) & ((points[..., :2] - torch.as_tensor(near)).norm(dim=-1) < 0.06)
    w = z[keep]
    return ((points[keep][:, :2] * w[:, None]).sum(0) / w.sum()).numpy()


def test_the_depth_a_policy_sees_lies_on_its_rgb_pixels_rays(runner):
    """12 starts, the head view at the policy's 48x64 from the 96x128 render: the cube's centre
    from the observation's depth, back-projected with the rig's intrinsics at the view size and
    the camera pose at the observed state, against MuJoCo's cube. The nearest-pixel resize
    (a quarter pixel off each ray) misses it by more than 5 mm on average."""
    env, rig, views = runner.env, runner.rig, list(runner.rig.cameras)
    c = runner.config
    K = rig.intrinsics((c.view_height, c.view_width))[views.index(HEAD)]
    box = env.layout.object_bodies["box"]
    errors, nearest = [], []
    for seed in range(12):
        env.reset(seed)
        rendered = env.render()
        obs = runner.observe(rendered, torch.as_tensor(env.qpos()).float())
        pose = rig.camera_poses(obs["observation.state"][None], dtype=torch.float64)[0, views.index(HEAD)]
        truth = env.data.xpos[box][:2].copy()
        errors.append(cube_centre_from_depth(obs[depth_key(HEAD)], K, pose, truth) - truth)
        old = resize_depth(rendered["depth_mm"][HEAD].astype(np.float32) / 1000, (c.view_height, c.view_width))
        nearest.append(cube_centre_from_depth(torch.from_numpy(old), K, pose, truth) - truth)
    bias, old_bias = np.mean(errors, axis=0), np.mean(nearest, axis=0)
    assert np.linalg.norm(bias) <= 0.002, bias  # metres
    assert np.abs(old_bias).min() > 0.005, old_bias


def test_seeds_take_lists_and_inclusive_ranges():
    assert parse_seeds(["3", "10..12", "0"]) == [3, 10, 11, 12, 0]
    assert parse_seeds(["300000..300019"]) == list(range(300000, 300020))
    for bad, message in (("4..2", "needs A <= B"), ("a..3", "an integer or a range"), ("1...3", "an integer"),
                         ("-1", r"\[0, 2\^32 - 1\]")):
        with pytest.raises(InputError, match=message):
            parse_seeds([bad])


POLICIES = '''
import torch


class Short:
    """Answers 7-dimensional actions: one arm's worth."""

    def __call__(self, observation):
        return torch.zeros(8, 7)


class Stretch:
    """Moves the right shoulder and wrist a little more each chunk."""

    name = "stretch"

    def __init__(self):
        self.calls = 0

    def reset(self):
        self.calls = 0

    def __call__(self, observation):
        self.calls += 1
        actions = observation["observation.state"].repeat(8, 1)
        actions[:, 8] -= torch.linspace(0.01, 0.08, 8)
        actions[:, 11] += torch.linspace(0.02, 0.16, 8)
        return actions


class Lifter(Stretch):
    tasks = ("Pick up the cube with the right arm and lift it.",)
'''


def simulator(policy: str, output, *more: str) -> int:
    return model_main(["evaluate", "simulator", "--policy", policy, "--seeds", "3", "--chunks", "2",
                       "--output", str(output), "--no-progress", *more])


def test_refusals_name_what_was_run_and_leave_no_output(in_tmp, capsys):
    (in_tmp / "author_policies.py").write_text(textwrap.dedent(POLICIES))
    out = in_tmp / "sim"

    # a wrong action size names the simulator, not a world model; calibration.json is gone too
    assert simulator("python:author_policies:Short", out) == 2
    err = capsys.readouterr().err
    assert "Short returned 7-dimensional actions; the simulated ALOHA rig (task lift) has 14-dimensional" in err
    assert "world model" not in err
    assert not out.exists()
    out.mkdir()  # an empty directory given as --output stays empty
    assert simulator("python:author_policies:Short", out) == 2
    assert "14-dimensional" in capsys.readouterr().err and list(out.iterdir()) == []

    # a lift policy asked for another task: refused before any work, in one line
    for policy in ("python:author_policies:Lifter", "python:imac_model.experiments.ranking.policies:closed_loop"):
        assert simulator(policy, out, "--task", "transfer_cube") == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "acts on ['Pick up the cube with the right arm and lift it.']" in err
        assert "--task transfer_cube is 'Pick up the cube with the right arm and transfer it" in err
        assert list(out.iterdir()) == []

    # a module that is not there: where it was looked for
    assert simulator("python:not_written:Policy", out) == 2
    assert f"no module 'not_written' in the current directory {in_tmp}" in capsys.readouterr().err
    assert simulator("python:author_policies:Missing", out) == 2
    assert "module 'author_policies'" in capsys.readouterr().err and list(out.iterdir()) == []
    assert model_main(["evaluate", "simulator", "--policy", "hold", "--seeds", "5..1", "--output", str(out)]) == 2
    assert "--seeds '5..1'" in capsys.readouterr().err and list(out.iterdir()) == []


def test_an_episode_re_simulates_from_its_own_file(in_tmp):
    """The start seed and task in the HDF5 attributes, the rate from its fps, the recorded
    actions: MuJoCo retraces the recorded joints bit for bit."""
    (in_tmp / "stretch_policy.py").write_text(textwrap.dedent(POLICIES))
    rows = run_policy(load_policy("python:stretch_policy:Stretch"), [7, 8], in_tmp / "sim", progress=False,
                      config=SimRunConfig(settle_s=0.3))  # a start at rest, as the ranking's
    assert [r["seed"] for r in rows] == [7, 8]
    for i, seed in enumerate((7, 8)):
        path = in_tmp / "sim" / f"episode_{i}.hdf5"
        with h5py.File(path) as f:
            assert f.attrs["sim_seed"] == seed and f.attrs["sim_task"] == "lift" and f.attrs["sim_settle_s"] == 0.3
        ep = read_episode(path, load_depth=False)
        assert (ep.info.sim_seed, ep.info.sim_task, ep.info.sim_settle_s) == (seed, "lift", 0.3)
        env = SimEnv(ep.info.sim_task, frame_stride=round(1 / (ep.fps * CONTROL_DT)), settle_s=ep.info.sim_settle_s)
        env.reset(ep.info.sim_seed)
        qpos = [env.qpos()]
        for action in ep.action[:-1]:  # the last frame's action repeats the one before it
            env.step(action)
            qpos.append(env.qpos())
        assert np.ptp(ep.qpos[:, 11]) > 0.1  # the wrist moved
        np.testing.assert_array_equal(np.array(qpos), ep.qpos)
    with h5py.File(in_tmp / "sim" / "episode_0.hdf5", "r+") as f:
        f.attrs["sim_seed"] = "seven"
    with pytest.raises(InputError, match=r"episode_0.hdf5: attribute 'sim_seed' must be a non-negative integer"):
        read_episode(in_tmp / "sim" / "episode_0.hdf5")
    with h5py.File(in_tmp / "sim" / "episode_1.hdf5", "r+") as f:
        f.attrs["sim_settle_s"] = -1.0
    with pytest.raises(InputError, match=r"episode_1.hdf5: attribute 'sim_settle_s' must be a non-negative number"):
        read_episode(in_tmp / "sim" / "episode_1.hdf5")


def test_graded_action_noise_reaches_mujoco_as_drawn_and_repeats_at_each_start(in_tmp):
    """``noisy:STD:SPEC`` adds Gaussian noise to every action: read back from MuJoCo's recording (Stretch commands
    the state it is given plus fixed offsets, so each chunk's noise is its actions minus that), it has the asked
    spread and no bias, the same start meets the same noise, and STD 0 is the policy itself."""
    (in_tmp / "stretch_policy.py").write_text(textwrap.dedent(POLICIES))
    spec, std = "python:stretch_policy:Stretch", 0.02
    config = SimRunConfig(chunks=4)
    clean = run_policy(load_policy(spec), [7], in_tmp / "clean", progress=False, config=config)
    run_policy(load_policy(f"noisy:0:{spec}"), [7], in_tmp / "zero", progress=False, config=config)
    run_policy(load_policy(f"noisy:{std}:{spec}"), [7, 9, 7], in_tmp / "noisy", progress=False, config=config)
    assert clean and read_episode(in_tmp / "zero" / "episode_0.hdf5").action.tolist() == \
        read_episode(in_tmp / "clean" / "episode_0.hdf5").action.tolist()
    first, other, again = (read_episode(in_tmp / "noisy" / f"episode_{i}.hdf5") for i in range(3))
    np.testing.assert_array_equal(first.action, again.action)
    offsets = np.zeros((8, 14))
    offsets[:, 8], offsets[:, 11] = -np.linspace(0.01, 0.08, 8), np.linspace(0.02, 0.16, 8)
    noise = []
    for ep in (first, other):
        chunks = ep.action[:32].reshape(4, 8, 14)
        given = np.concatenate([ep.qpos[:1], chunks[:-1, -1]])  # measured at the start, then the last command
        noise.append(chunks - given[:, None] - offsets)
    noise = np.concatenate(noise).reshape(-1)
    assert abs(noise.std() / std - 1) < 0.1 and abs(noise.mean()) < 4 * std / np.sqrt(noise.size)
    assert not np.allclose(noise[:448], noise[448:])  # another start, other noise
    for bad in ("noisy:-1:hold", "noisy:abc:hold", "noisy:0.1"):
        with pytest.raises(InputError, match=f"policy '{bad}': expected noisy:STD:SPEC"):
            load_policy(bad)


def test_settling_puts_the_box_on_the_table_before_the_first_frame():
    """gym-aloha starts the box 3 cm above its resting height; with settle_s the first frame shows it at rest, where
    MuJoCo keeps it (its own contact solution is the oracle: the same height a second later, no velocity), at the
    start's x and y."""
    rest = TABLE_Z + REST_HEIGHT["box"]
    unsettled, settled = SimEnv("lift"), SimEnv("lift", settle_s=0.3)
    unsettled.reset(100_000)
    settled.reset(100_000)
    start, first = unsettled.object_position("box"), settled.object_position("box")
    assert start[2] == pytest.approx(rest + 0.03, abs=1e-6)  # in the air, as gym-aloha places it
    assert first[2] == pytest.approx(rest, abs=1e-3) and np.abs(first[:2] - start[:2]).max() < 1e-3
    assert settled.data.time == 0.0 and np.abs(settled.qpos() - unsettled.qpos()).max() < 1e-2  # the arms held
    held = settled.qpos()
    for _ in range(10):  # 0.4 s with the arms held: it stays
        settled.step(held)
    assert np.abs(settled.object_position("box") - first).max() < 1e-3
    for bad in (-0.1, 11.0):
        with pytest.raises(InputError, match=r"settle_s \(the physics run before the first frame; --settle\) must be in"):
            SimEnv("lift", settle_s=bad)


def aloha_command_bounds() -> tuple[np.ndarray, np.ndarray]:
    """The 14-D action's bounds as gym-aloha's MJCF saturates them, read from the XML itself: each arm joint's
    position actuator's ``ctrlrange``, the gripper's (its left finger's) through gym-aloha's own normalisation."""
    actuators = ET.parse(ASSETS_DIR / "bimanual_viperx_transfer_cube.xml").getroot().find("actuator")
    ranges = {a.get("joint"): [float(x) for x in a.get("ctrlrange").split()] for a in actuators}
    lo, hi = [], []
    for arm in ("vx300s_left", "vx300s_right"):
        for joint in ("waist", "shoulder", "elbow", "forearm_roll", "wrist_angle", "wrist_rotate"):
            lo.append(ranges[f"{arm}/{joint}"][0])
            hi.append(ranges[f"{arm}/{joint}"][1])
        lo.append(normalize_puppet_gripper_position(ranges[f"{arm}/left_finger"][0]))
        hi.append(normalize_puppet_gripper_position(ranges[f"{arm}/left_finger"][1]))
    return np.array(lo), np.array(hi)


BEYOND = {1: -5.0, 6: 3.0, 7: 9.0, 13: -4.2}  # left shoulder, left gripper, right waist, right gripper


def beyond_the_range_policy(obs):
    """Holds the state it is given, but commands four entries far outside what the actuators take."""
    actions = obs["observation.state"].clone().repeat(8, 1)
    for i, value in BEYOND.items():
        actions[:, i] = value
    return actions


def test_a_command_beyond_the_actuators_reaches_the_next_state_saturated_as_mujoco_saturates_it(runner):
    """A policy's command outside the actuators' ranges (an ACT gripper under action noise reached -4.2) is
    recorded as commanded, but the state the policy is given next is the command saturated at the ranges in
    gym-aloha's XML, where MuJoCo's actuators saturate it."""
    states = []

    def policy(obs):
        states.append(obs["observation.state"].clone())
        return beyond_the_range_policy(obs)

    episode = runner.run_episode(policy, 0)
    lo, hi = aloha_command_bounds()
    command = states[0].double().numpy().copy()
    for i, value in BEYOND.items():
        command[i] = value
    expected = np.clip(command, lo, hi)
    assert not np.allclose(expected, command)  # the case saturates
    for state in states[1:]:
        np.testing.assert_allclose(state.double().numpy(), expected, atol=1e-6)
    assert episode.action[0, 13] == np.float32(-4.2) and episode.action[0, 7] == 9.0  # the recording keeps the command
