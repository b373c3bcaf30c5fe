"""The controller map phi (imac_data.core.motion): absolute targets, accumulated deltas,
gripper mapping, frame alignment; gym-aloha's position actuators as the oracle."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
import torch
from gym_aloha.constants import START_ARM_POSE, normalize_puppet_gripper_position, unnormalize_puppet_gripper_position

from imac_data.core.motion import Controller, GripperActionMap, frame_configurations, rollout
from imac_data.core.robot import aloha
from imac_data.errors import InputError
from imac_data.sources.sim import rig as sim_rig


def test_absolute_targets_are_the_last_command():
    rng = np.random.default_rng(0)
    q_t, a = rng.normal(size=(2, 4)), rng.normal(size=(2, 5, 4))
    ctl = Controller(grippers=(GripperActionMap(3, scale=0.5, offset=0.1),))
    q = rollout(q_t, a, ctl)
    assert q.shape == (2, 5, 4)
    np.testing.assert_array_equal(q[..., :3], a[..., :3])
    np.testing.assert_allclose(q[..., 3], 0.1 + 0.5 * a[..., 3])
    # torch in, torch out, same values
    qt = rollout(torch.tensor(q_t), torch.tensor(a), ctl)
    assert isinstance(qt, torch.Tensor)
    np.testing.assert_allclose(qt.numpy(), q)


def test_delta_actions_accumulate_grippers_stay_absolute():
    q_t = np.array([1.0, 2.0, 0.5])
    a = np.array([[0.1, -0.2, 0.9], [0.1, -0.2, 0.2], [0.3, 0.0, 0.0]])
    ctl = Controller(mode="delta", grippers=(GripperActionMap(2),))
    q = rollout(q_t, a, ctl)
    np.testing.assert_allclose(q, [[1.1, 1.8, 0.9], [1.2, 1.6, 0.2], [1.5, 1.6, 0.0]])
    # q_{t+k} = phi(q_t, a_{t:t+k-1}): row k-1 only depends on the first k actions
    np.testing.assert_allclose(rollout(q_t, a[:2], ctl), q[:2])
    acc = rollout(q_t, a, Controller(mode="delta", grippers=(GripperActionMap(2),), delta_grippers=True))
    np.testing.assert_allclose(acc[:, 2], [1.4, 1.6, 1.6])
    other = rollout(q_t, a, Controller(mode="delta", absolute_indices=(0,)))
    np.testing.assert_allclose(other[:, 0], a[:, 0])
    np.testing.assert_allclose(other[:, 2], [1.4, 1.6, 1.6])


def test_clipping():
    ctl = Controller(grippers=(GripperActionMap(1, low=0.0, high=1.0),), clip_low=(-1.0, -np.inf),
                     clip_high=(1.0, np.inf))
    q = rollout(np.zeros(2), np.array([[2.0, 1.5], [-3.0, -0.5]]), ctl)
    np.testing.assert_allclose(q, [[1.0, 1.0], [-1.0, 0.0]])
    assert ctl.to_dict()["clip_low"] == [-1.0, None]


def test_frame_configurations_alignment():
    """Frame t shows the command that drove the robot into it (action[t-1]); frame 0, which
    no command precedes, shows the measured state."""
    state = np.arange(12.0).reshape(4, 3)
    action = 100 + np.arange(12.0).reshape(4, 3)
    q = frame_configurations(state, action, source="action")
    np.testing.assert_array_equal(q[0], state[0])
    np.testing.assert_array_equal(q[1:], action[:-1])
    np.testing.assert_array_equal(frame_configurations(state, action, source="state"), state)
    delta = frame_configurations(state, action, source="action", controller=Controller(mode="delta"))
    np.testing.assert_array_equal(delta[1:], state[:-1] + action[:-1])
    qt = frame_configurations(torch.tensor(state), torch.tensor(action))
    assert isinstance(qt, torch.Tensor) and torch.equal(qt, torch.tensor(q))


def test_bad_input():
    with pytest.raises(InputError, match="mode"):
        Controller(mode="velocity")
    with pytest.raises(InputError, match="mapped twice"):
        Controller(grippers=(GripperActionMap(1), GripperActionMap(1)))
    with pytest.raises(InputError, match="low"):
        GripperActionMap(0, low=1.0, high=0.0)
    with pytest.raises(InputError, match="out of range"):
        rollout(np.zeros(3), np.zeros((2, 3)), Controller(grippers=(GripperActionMap(5),)))
    with pytest.raises(InputError, match="does not match"):
        rollout(np.zeros(4), np.zeros((2, 3)))
    with pytest.raises(InputError, match="non-finite"):
        rollout(np.zeros(3), np.array([[0.0, np.nan, 0.0]]))
    with pytest.raises(InputError, match="source"):
        frame_configurations(np.zeros((2, 3)), np.zeros((2, 3)), source="policy")
    with pytest.raises(InputError, match="does not match"):
        frame_configurations(np.zeros((2, 3)), np.zeros((3, 3)))
    with pytest.raises(InputError, match="non-finite"):
        frame_configurations(np.array([[0.0, np.inf]]), source="state")
    with pytest.raises(InputError, match="needs the episode's actions"):
        frame_configurations(np.zeros((2, 3)), None, source="action")


def test_aloha_controller_matches_gym_aloha_actuators():
    """phi for gym-aloha (absolute targets, identity gripper map, ctrlrange saturation)
    against MuJoCo itself: actions written to the position actuators exactly as gym-aloha
    does (arm joints; fingers = +/- unnormalize(gripper)), physics run until settled; the
    measured joints are phi's prediction up to the servos' residual error.

    The grippers are commanded half open and "beyond open" (1.0 is past the fingers'
    ctrlrange, which saturates it). A fully closed command is not tested: the two fingers
    touch at 0.0224 m (normalised 0.10) before reaching their limit, which is contact,
    not the controller."""
    model = sim_rig.load_mujoco_model("transfer_cube")
    data = mujoco.MjData(model)
    start = np.asarray(START_ARM_POSE, dtype=float)
    rng = np.random.default_rng(3)
    q0 = np.r_[start[0:6], 0.5, start[8:14], 0.5]
    action = q0 + np.r_[rng.uniform(-0.3, 0.3, 6), 0.0, rng.uniform(-0.3, 0.3, 6), 0.0]
    action[[6, 13]] = [0.5, 1.0]
    data.qpos[:16] = start
    for k in range(2):
        finger = unnormalize_puppet_gripper_position(action[7 * k + 6])
        data.ctrl[8 * k: 8 * k + 8] = np.r_[action[7 * k: 7 * k + 6], finger, -finger]
    mujoco.mj_forward(model, data)
    for _ in range(1500):  # 3 s at 2 ms
        mujoco.mj_step(model, data)
    qp = data.qpos[:16]
    measured = np.r_[qp[0:6], normalize_puppet_gripper_position(qp[6]), qp[8:14],
                     normalize_puppet_gripper_position(qp[14])]
    predicted = rollout(q0, action[None], aloha.controller("transfer_cube"))[0]
    arms = np.r_[0:6, 7:13]
    np.testing.assert_allclose(measured[arms], predicted[arms], atol=0.015)  # rad
    np.testing.assert_allclose(measured[[6, 13]], predicted[[6, 13]], atol=0.01)  # 0.4 mm of finger travel
    # without the actuators' saturation the "beyond open" gripper would be predicted off
    naive = rollout(q0, action[None], aloha.controller())[0]
    assert abs(naive[13] - measured[13]) > 0.02
