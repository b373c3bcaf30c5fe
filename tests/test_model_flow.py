"""Flow matching and the sampler: analytic cases and diffusers' own Euler scheduler as oracles."""

import numpy as np
import pytest
import torch

from imac_model.schedulers import flow


def test_one_step_clean_estimate_recovers_data_with_the_true_velocity():
    g = torch.Generator().manual_seed(0)
    x0, x1 = torch.randn(4, 8, 3, 5, 6, generator=g), torch.randn(4, 8, 3, 5, 6, generator=g)
    tau = torch.tensor([0.0, 0.25, 0.7, 0.999])
    x_tau = flow.interpolate(x0, x1, tau)
    x1_hat = flow.clean_estimate(x_tau, flow.target_velocity(x0, x1), tau)
    torch.testing.assert_close(x1_hat, x1, rtol=0, atol=1e-5)
    # and a wrong velocity does not (the estimate is not trivially x1)
    assert (flow.clean_estimate(x_tau, 0.9 * flow.target_velocity(x0, x1), tau) - x1).abs().max() > 0.01


def test_time_convention_tau0_noise_tau1_data_and_wan_timesteps():
    x0, x1 = torch.zeros(2, 3), torch.ones(2, 3)
    assert torch.equal(flow.interpolate(x0, x1, torch.zeros(2)), x0)
    assert torch.equal(flow.interpolate(x0, x1, torch.ones(2)), x1)
    torch.testing.assert_close(flow.wan_timestep(torch.tensor([0.0, 0.25, 1.0])), torch.tensor([1000.0, 750.0, 0.0]))


@pytest.mark.parametrize("shift", [1.0, 5.0])
def test_euler_sampler_matches_diffusers_flow_match_euler_scheduler(shift):
    """Our sampler in tau against diffusers' FlowMatchEulerDiscreteScheduler in sigma = 1 - tau,
    fed Wan's convention (the model predicts noise - data, i.e. minus our velocity)."""
    from diffusers import FlowMatchEulerDiscreteScheduler

    steps = 7

    def velocity(x, tau):  # a nonlinear field, so the step sizes matter
        return torch.sin(3 * x) * (1 + tau.view(-1, 1)) - x

    x0 = torch.randn(3, 16, generator=torch.Generator().manual_seed(1))
    ours = flow.euler_sample(velocity, x0, steps=steps, shift=shift)

    sched = FlowMatchEulerDiscreteScheduler(shift=shift)
    sched.set_timesteps(sigmas=np.linspace(1.0, 0.0, steps + 1)[:-1].tolist())
    x = x0.clone()
    for t in sched.timesteps:
        tau = (1 - t / 1000.0).expand(x.shape[0])
        torch.testing.assert_close(flow.wan_timestep(tau), t.expand(x.shape[0]))
        x = sched.step(-velocity(x, tau), t, x).prev_sample
    torch.testing.assert_close(ours, x, rtol=1e-5, atol=1e-5)


def test_shift_keeps_the_ends_and_moves_time_towards_noise():
    tau = torch.linspace(0, 1, 11)
    shifted = flow.shift_tau(tau, 5.0)
    assert shifted[0] == 0 and shifted[-1] == 1
    assert torch.all(shifted[1:-1] < tau[1:-1]) and torch.all(shifted[1:] > shifted[:-1])
    assert torch.equal(flow.shift_tau(tau, 1.0), tau)


def test_straight_path_is_sampled_exactly():
    x0, x1 = torch.randn(2, 5), torch.randn(2, 5)
    out = flow.euler_sample(lambda x, tau: x1 - x0, x0, steps=3, shift=3.0)
    torch.testing.assert_close(out, x1)


def test_masked_mse_counts_only_valid_frames():
    g = torch.Generator().manual_seed(2)
    pred, target = torch.randn(2, 4, 3, 2, 2, generator=g), torch.randn(2, 4, 3, 2, 2, generator=g)
    mask = torch.tensor([[True, False, True], [False, False, True]])
    brute = torch.cat([((pred[b, :, f] - target[b, :, f]) ** 2).flatten()
                       for b in range(2) for f in range(3) if mask[b, f]]).mean()
    torch.testing.assert_close(flow.masked_mse(pred, target, mask), brute)
    target2 = target.clone()
    target2[0, :, 1] += 100.0  # a masked frame
    torch.testing.assert_close(flow.masked_mse(pred, target2, mask), brute)


def test_weighted_masked_mse_is_the_weighted_mean_over_valid_frames():
    g = torch.Generator().manual_seed(3)
    pred, target = torch.randn(2, 4, 3, 2, 2, generator=g), torch.randn(2, 4, 3, 2, 2, generator=g)
    weight = torch.rand(2, 1, 3, 2, 2, generator=g) + 0.5
    mask = torch.tensor([[True, False, True], [False, True, True]])
    num = den = 0.0
    for b in range(2):
        for f in range(3):
            if mask[b, f]:
                num += float((weight[b, 0, f] * (pred[b, :, f] - target[b, :, f]) ** 2).sum())
                den += float(weight[b, 0, f].sum()) * 4
    torch.testing.assert_close(flow.masked_mse(pred, target, mask, weight), torch.tensor(num / den))


def test_focus_weight_marks_what_changed_dilated():
    ref = torch.zeros(1, 4, 1, 9, 9)
    fut = torch.zeros(1, 4, 2, 9, 9)
    fut[0, 2, 1, 4, 4] = 0.5  # one pixel of one channel changes in the second future frame
    fut[0, 0, 0, 0, 0] = 0.1  # below the threshold
    w = flow.focus_weight(ref, fut, weight=3.0, threshold=0.2, dilation=1)
    assert w.shape == (1, 1, 2, 9, 9)
    assert torch.all(w[0, 0, 0] == 1.0)
    expected = torch.ones(9, 9)
    expected[3:6, 3:6] = 4.0  # the pixel and its 8 neighbours
    torch.testing.assert_close(w[0, 0, 1], expected)
