"""The action-vector baseline's injection path works: on a target that depends only on the
actions (an analytic oracle), a small world model in ``action-vector`` mode learns it, and the
same model in ``none`` mode, which cannot see the actions, does not. The ranking benchmark
relies on this to call a low action-vector score a property of the baseline, not a bug."""

import torch

from imac_model.config import BackboneConfig, ConditioningConfig, FlowConfig, ModelSpec, SmallDiTConfig
from imac_model.data.batch import ChunkBatch
from imac_model.models.world_model import WorldModel

H, D, SIDE = 2, 2, 8


def target_brightness(actions: torch.Tensor) -> torch.Tensor:
    """Frame k of the future is a uniform grey of brightness 0.5 + 0.4 a_k[0]: only the actions decide it."""
    return 0.5 + 0.4 * actions[..., 0]


def batch_of(actions: torch.Tensor) -> ChunkBatch:
    B = actions.shape[0]
    future = target_brightness(actions)[:, :, None, None, None].expand(B, H, 3, 2 * SIDE, SIDE).clone()
    return ChunkBatch(reference=torch.full((B, 3, 2 * SIDE, SIDE), 0.5), actions=actions, future=future)


def train(mode: str, steps: int = 250) -> WorldModel:
    torch.manual_seed(0)
    spec = ModelSpec(backbone=BackboneConfig(kind="small", small=SmallDiTConfig(unshuffle=2, patch=2, dim=32, depth=2,
                                                                                heads=2, context_dim=16)),
                     conditioning=ConditioningConfig(mode=mode, action_hidden=32), flow=FlowConfig(sample_steps=8),
                     views=("cam",), view_height=SIDE, view_width=SIDE, chunk=H, action_dim=D, fps=10.0,
                     action_mean=(0.0,) * D, action_std=(1.0,) * D)
    model = WorldModel(spec)
    opt = torch.optim.AdamW(model.parameters(), lr=3e-3)
    g = torch.Generator().manual_seed(1)
    for _ in range(steps):
        loss = model(batch_of(torch.rand(16, H, D, generator=g) * 2 - 1), generator=g).loss
        opt.zero_grad()
        loss.backward()
        opt.step()
    return model.eval()


def brightness_correlation(model: WorldModel) -> float:
    """Pearson r between the generated frames' brightness and the targets', over 24 frames."""
    actions = torch.rand(12, H, D, generator=torch.Generator().manual_seed(2)) * 2 - 1
    frames = model.sample(batch_of(actions), generator=torch.Generator().manual_seed(3)).frames  # (B, H, 3, 2S, S)
    generated = frames[..., :SIDE, :].mean(dim=(-1, -2, -3)).flatten()
    return float(torch.corrcoef(torch.stack([generated, target_brightness(actions).flatten()]))[0, 1])


def test_action_vector_mode_learns_a_target_that_only_the_actions_decide():
    torch.set_num_threads(1)
    seen, blind = brightness_correlation(train("action-vector")), brightness_correlation(train("none"))
    assert seen > 0.9, seen  # read off the actions
    assert abs(blind) < 0.5, blind  # the same model without them can only guess
