"""Generate a future chunk for a dataset episode and show it beside the recording:
``imac-model sample --checkpoint runs/x --episode 8 [--chunk 3] [--out sample.mp4]``.

``--chunks N`` rolls out N chunks autoregressively (:func:`imac_model.pipelines.rollout.sample_rollout`):
each next reference is the last generated frame, and the motion and contact images are
rebuilt online from the generated depth and the recorded actions at every chunk boundary
(:mod:`imac_model.pipelines.online_controls`).

The mp4 shows, per future frame, the generated mosaic, the recorded mosaic and the
control images the model was given (one row per stream, views side by side).
``--png`` also writes a still: rows = future frames (first, middle, last), columns =
generated | recorded | motion image (for the docs).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from imac_data.errors import InputError
from imac_data.metadata import dataset_info
from imac_model.config import DataConfig, ModelSpec, RolloutConfig, parse
from imac_model.data import mosaic
from imac_model.data.batch import ChunkBatch
from imac_model.data.chunks import ChunkDataset, open_metadata, resolve_layout
from imac_model.models.backbones.build import spatial_multiple, temporal_factor
from imac_model.pipelines.online_controls import OnlineControls
from imac_model.pipelines.rollout import sample_rollout


@dataclass
class ChunkSample:
    generated: torch.Tensor  # (H, 3, 2h, V w) in [0, 1]
    recorded: torch.Tensor  # (H, 3, 2h, V w)
    controls: dict[str, torch.Tensor]  # stream -> (H, V, 3, h, w) per view
    valid: torch.Tensor  # (H,) bool
    reference: torch.Tensor  # (3, 2h, V w): the frame the chunk starts from
    episode: int
    reference_frame: int


def open_chunks(spec: ModelSpec, dataset: str, root: str | None, episodes=None) -> ChunkDataset:
    """The chunks of ``dataset`` laid out for ``spec`` (checked against it)."""
    data = DataConfig(dataset=dataset, root=root, view_height=spec.view_height, view_width=spec.view_width,
                      chunk=spec.chunk, views=spec.views, cache="none")
    meta = open_metadata(data)
    layout = resolve_layout(dataset_info(meta), data, spec.conditioning.streams,
                            spatial_multiple=spatial_multiple(spec.backbone),
                            temporal_factor=temporal_factor(spec.backbone), mode=spec.conditioning.mode)
    if episodes is not None:
        bad = [e for e in episodes if not 0 <= e < meta.total_episodes]
        if bad:
            raise InputError(f"--episode {bad[0]}: the dataset has episodes 0..{meta.total_episodes - 1}")
    return ChunkDataset(dataset, layout, root=root, episodes=episodes, cache="none")


def sample_chunk(model, chunks: ChunkDataset, episode: int, chunk: int = 0, *, steps: int | None = None,
                 seed: int = 0) -> ChunkSample:
    items = chunks.episode_chunks(episode)
    if not 0 <= chunk < len(items):
        raise InputError(f"--chunk {chunk}: episode {episode} has chunks 0..{len(items) - 1}")
    batch: ChunkBatch = chunks.batch([items[chunk]])
    device = next(model.parameters()).device
    out = model.sample(batch.to(device), steps=steps, generator=torch.Generator().manual_seed(seed))
    V = len(model.spec.views)
    return ChunkSample(generated=out.frames[0].cpu(), recorded=batch.future[0],
                       controls={s: mosaic.control_views(c[0], V) for s, c in batch.controls.items()},
                       valid=batch.valid_mask()[0], reference=batch.reference[0], episode=episode, reference_frame=int(batch.frame_index[0]))


def online_controls_for(spec: ModelSpec, chunks: ChunkDataset, run: dict | None = None):
    """The dataset's :class:`~imac_model.pipelines.online_controls.OnlineControls` for a model (None for a
    model without control streams), with the run's ``rollout`` settings."""
    if not spec.conditioning.streams:
        return None
    rc = parse(RolloutConfig, (run or {}).get("rollout") or {}, "rollout")
    return OnlineControls.from_dataset(chunks.lerobot.root, spec, info=dataset_info(chunks.lerobot.meta),
                                       resolution=rc.resolution, max_walk_distance=rc.max_walk_distance)


def sample_rollout_chunks(model, chunks: ChunkDataset, episode: int, chunk: int, n: int, online, *,
                          steps: int | None = None, seed: int = 0, recorded_states: bool = False
                          ) -> tuple[ChunkSample, list[ChunkSample], list[float]]:
    """Roll out ``n`` chunks of ``episode`` from chunk ``chunk``'s recorded reference
    (:func:`imac_model.pipelines.rollout.sample_rollout`): the first chunk gets the dataset's controls,
    every later one controls rebuilt online from the generated depth and the recorded actions,
    with the robot state at each boundary = the last commanded configuration (or the recorded
    state with ``recorded_states``). Returns the whole rollout as one :class:`ChunkSample`
    (n x H frames), one per chunk, and the share of invalid generated depth per rebuild."""
    items = chunks.episode_chunks(episode)
    if chunk < 0 or chunk + n > len(items):
        raise InputError(f"--chunk {chunk} --chunks {n}: episode {episode} has chunks 0..{len(items) - 1}")
    batches = [chunks.batch([items[chunk + i]]) for i in range(n)]
    device = next(model.parameters()).device
    first = batches[0].to(device)
    actions = torch.stack([b.actions for b in batches], dim=1).to(device)
    states = None
    if recorded_states:
        if any(b.state is None for b in batches):
            raise InputError("--recorded-states: the dataset has no observation.state")
        states = torch.stack([b.state for b in batches], dim=1)
    out = sample_rollout(model, first, actions, online, states=states, steps=steps, seed=seed)
    V = len(model.spec.views)
    per_chunk = []
    for i, b in enumerate(batches):
        per_chunk.append(ChunkSample(
            generated=out.frames[0, i].cpu(), recorded=b.future[0],
            controls={s: mosaic.control_views(c[0].cpu(), V) for s, c in out.controls[i].items()},
            valid=b.valid_mask()[0], reference=out.references[i][0].cpu(), episode=episode,
            reference_frame=int(b.frame_index[0])))
    whole = ChunkSample(generated=torch.cat([c.generated for c in per_chunk]),
                        recorded=torch.cat([c.recorded for c in per_chunk]),
                        controls={s: torch.cat([c.controls[s] for c in per_chunk]) for s in per_chunk[0].controls},
                        valid=torch.cat([c.valid for c in per_chunk]), reference=per_chunk[0].reference,
                        episode=episode, reference_frame=per_chunk[0].reference_frame)
    return whole, per_chunk, out.invalid_depth


def robot_region_errors(s: ChunkSample) -> dict[str, float]:
    """Pixel MSE against the recording over the valid future frames: the whole mosaic, and
    the RGB row inside the future robot (where the motion images are not black), for the
    generated frames and for a baseline that copies the reference frame. A model that puts
    the robot where the motion images say beats the copy inside the robot."""
    V = s.controls["motion"].shape[1] if "motion" in s.controls else None
    out = {"mse": float(((s.generated - s.recorded) ** 2)[s.valid].mean()),
           "mse_copy_reference": float(((s.reference - s.recorded) ** 2)[s.valid].mean())}
    if V is None:
        return out
    h = s.recorded.shape[-2] // 2
    robot = mosaic.controls(s.controls["motion"]).amax(dim=1)[:, :h] > 0.02  # (H, h, V w)
    robot = robot & s.valid[:, None, None]
    if robot.any():
        rgb = lambda x: x[..., :h, :]  # noqa: E731
        err = lambda a: float((((rgb(a) - rgb(s.recorded)) ** 2).mean(dim=1))[robot].mean())  # noqa: E731
        out["mse_robot"] = err(s.generated)
        out["mse_robot_copy_reference"] = err(s.reference.expand_as(s.recorded))
    return out


def summary_of(e: dict) -> str:
    robot = (f"; inside the future robot {e['mse_robot']:.4f} (copying the reference: "
             f"{e['mse_robot_copy_reference']:.4f})" if "mse_robot" in e else "")
    return f"pixel MSE vs recorded {e['mse']:.4f} (copying the reference: {e['mse_copy_reference']:.4f}){robot}"


def evaluate_episodes(model, chunks: ChunkDataset, episodes, *, steps=None, seed: int = 0, progress: bool = True):
    """Mean :func:`robot_region_errors` over every chunk of ``episodes``."""
    from tqdm.auto import tqdm

    jobs = [(e, c) for e in episodes for c in range(len(chunks.episode_chunks(e)))]
    rows = [robot_region_errors(sample_chunk(model, chunks, e, c, steps=steps, seed=seed))
            for e, c in tqdm(jobs, desc="sampling chunks", disable=not progress)]
    keys = set.intersection(*(set(r) for r in rows))
    return {k: float(np.mean([r[k] for r in rows])) for k in sorted(keys)} | {"chunks": len(rows)}
