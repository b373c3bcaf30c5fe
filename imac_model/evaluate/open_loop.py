"""Open-loop evaluation of a world model on held-out episodes: multi-chunk rollouts against
the recording, and an action-sensitivity check.

* :func:`rollout_videos`: from recorded reference frames of held-out episodes, roll out N
  chunks with the recorded actions (:func:`imac_model.pipelines.rollout.sample_rollout`: chunk 1 with
  the dataset's controls, every later chunk from the last generated frame, controls rebuilt
  online from the generated depth, robot state = last commanded configuration, as a closed
  loop would). Returns generated and recorded mosaics as uint8.
* :func:`per_chunk_metrics`: MSE / PSNR / SSIM (:func:`~imac_model.evaluate.video_metrics.
  compute_video_metrics`) of each chunk index of the rollouts, on the RGB views and their
  mosaic; the error growth per chunk follows from it.
* :func:`action_sensitivity`: the same reference frame and noise with two action sequences,
  the recorded one and one with a smooth joint offset (:func:`perturb_actions`). A model that
  follows the actions changes its future where the robot differs. Measured as the mean
  absolute difference of the two generated RGB rows inside the region where the two motion
  images differ (the robot moved there) and outside the union of both robots (the scene,
  which should not change), and their ratio. Both sequences' controls are built online from
  the recorded reference (:meth:`OnlineControls.controls`), so both go through one pipeline.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import torch

from imac_data.errors import InputError
from imac_model.data import mosaic
from imac_model.data.batch import ChunkBatch
from imac_model.evaluate.video_metrics import VideoMetricsConfig, compute_video_metrics
from imac_model.pipelines.rollout import sample_rollout

ROBOT_THRESHOLD = 0.02  # a motion-image pixel brighter than this (any channel) shows the robot
DIFFERENCE_THRESHOLD = 0.1  # two motion images differ at a pixel where a channel differs by more than this


def _u8(x: torch.Tensor) -> torch.Tensor:
    return (x.clamp(0, 1) * 255).round().to(torch.uint8)


def rollout_starts(dataset, episodes: Sequence[int], chunks: int, every: int) -> list[tuple[int, int]]:
    """``(episode, first chunk)`` of every ``chunks``-chunk rollout that starts at a multiple of
    ``every`` and whose future frames all lie inside the episode (no padding)."""
    starts = []
    for e in episodes:
        items = dataset.episode_chunks(e)
        for c in range(0, len(items) - chunks + 1, every):
            last = dataset[items[c + chunks - 1]]
            if bool(last["future_valid"].all()):
                starts.append((e, c))
    return starts


@dataclass
class RolloutVideos:
    generated: torch.Tensor  # (N, n_chunks * H, 3, 2h, V w) uint8
    recorded: torch.Tensor  # same
    reference: torch.Tensor  # (N, 3, 2h, V w) uint8: the recorded first reference
    starts: list[tuple[int, int]]
    invalid_depth: list[float]  # share of invalid generated depth per rebuilt boundary, per batch


@torch.no_grad()
def rollout_videos(model, dataset, starts: Sequence[tuple[int, int]], chunks: int, online, *,
                   steps: int | None = None, seed: int = 0, batch_size: int = 8, progress: bool = False
                   ) -> RolloutVideos:
    """Roll out ``chunks`` chunks from each start (see the module docstring)."""
    from tqdm.auto import tqdm

    gen, rec, refs, invalid = [], [], [], []
    for b0 in tqdm(range(0, len(starts), batch_size), desc="rollouts", disable=not progress):
        part = starts[b0:b0 + batch_size]
        batches = [dataset.batch([dataset.episode_chunks(e)[c + n] for e, c in part]) for n in range(chunks)]
        actions = torch.stack([b.actions for b in batches], dim=1)
        out = sample_rollout(model, batches[0], actions, online, steps=steps, seed=seed)
        gen.append(_u8(out.frames.flatten(1, 2)))
        rec.append(_u8(torch.cat([b.future for b in batches], dim=1)))
        refs.append(_u8(batches[0].reference))
        invalid += out.invalid_depth
    return RolloutVideos(torch.cat(gen), torch.cat(rec), torch.cat(refs), list(starts), invalid)


def per_chunk_metrics(generated: torch.Tensor, recorded: torch.Tensor, *, horizon: int, views: Sequence[str],
                      sampler_steps: int | None = None, seed: int | None = None) -> list[dict]:
    """:func:`compute_video_metrics` of each chunk index (frames ``n H .. (n + 1) H - 1``) on the
    RGB row: one result per chunk index."""
    V = len(views)
    n_chunks = generated.shape[1] // horizon
    out = []
    for n in range(n_chunks):
        sl = slice(n * horizon, (n + 1) * horizon)
        g_rgb, _ = mosaic.split(generated[:, sl], V)
        r_rgb, _ = mosaic.split(recorded[:, sl], V)
        result = compute_video_metrics({v: g_rgb[:, :, i] for i, v in enumerate(views)},
                                       {v: r_rgb[:, :, i] for i, v in enumerate(views)},
                                       sampler_steps=sampler_steps, seed=seed,
                                       config=VideoMetricsConfig(metrics=("mse", "psnr", "ssim"), mosaic_rows=1),
                                       protocol_extra={"chunk": n + 1, "frames_of_rollout": [sl.start, sl.stop]})
        out.append(result)
    return out


def perturb_actions(actions: torch.Tensor, offsets: Mapping[int, float]) -> torch.Tensor:
    """``actions (..., H, D)`` with ``offsets[j]`` added to joint j, ramped linearly from
    ``offset / H`` at the first step to the full offset at the last (a smooth deviation from
    the recorded motion, starting where the robot is)."""
    H = actions.shape[-2]
    ramp = torch.arange(1, H + 1, dtype=actions.dtype, device=actions.device) / H
    out = actions.clone()
    for j, off in offsets.items():
        if not 0 <= j < actions.shape[-1]:
            raise InputError(f"perturb_actions: joint index {j} out of range for {actions.shape[-1]}-D actions")
        out[..., j] = out[..., j] + off * ramp
    return out


@dataclass
class Sensitivity:
    inside: float  # mean |gen_A - gen_B| (RGB row, [0, 1]) where the two motion images differ
    outside: float  # ... outside both robots
    ratio: float | None  # inside / outside (None when both are 0: the futures are identical)
    region_share: float  # share of RGB pixels where the robot differs
    samples: int
    example: dict  # one sample's images (uint8) for a figure


@torch.no_grad()
def action_sensitivity(model, dataset, starts: Sequence[tuple[int, int]], online, *, offsets: Mapping[int, float],
                       steps: int | None = None, seed: int = 0, batch_size: int = 8) -> Sensitivity:
    """See the module docstring. ``online`` renders both action sequences' controls (and the
    motion masks, for every conditioning mode)."""
    V = len(model.spec.views)
    streams = tuple(model.streams)
    inside_sum = outside_sum = 0.0
    inside_n = outside_n = region_n = total_n = 0
    example = {}
    for b0 in range(0, len(starts), batch_size):
        part = starts[b0:b0 + batch_size]
        batch = dataset.batch([dataset.episode_chunks(e)[c] for e, c in part])
        a = batch.actions
        b = perturb_actions(a, offsets)
        q0 = batch.state
        if q0 is None:
            raise InputError("action sensitivity needs the dataset's observation.state")
        gens, motions = [], []
        for acts in (a, b):
            # every stream (also the motion images of a mode without controls, for the masks)
            ctl = online.controls(batch.reference, q0, acts)
            first = ChunkBatch(reference=batch.reference, actions=acts,
                               controls={s: ctl.controls[s] for s in streams}, state=q0,
                               first_frame=batch.first_frame)
            out = sample_rollout(model, first, acts[:, None], online, q0=q0, steps=steps, seed=seed)
            gens.append(out.frames[:, 0])
            motions.append(mosaic.control_views(ctl.controls["motion"], V))
        h = batch.reference.shape[-2] // 2
        g_a, g_b = (mosaic.split(g, V)[0] for g in gens)  # (B, H, V, 3, h, w)
        diff = (g_a - g_b).abs().mean(dim=-3)  # (B, H, V, h, w)
        m_a, m_b = motions
        robot = (m_a.amax(dim=-3) > ROBOT_THRESHOLD) | (m_b.amax(dim=-3) > ROBOT_THRESHOLD)
        differs = (m_a - m_b).abs().amax(dim=-3) > DIFFERENCE_THRESHOLD
        inside_sum += float(diff[differs].sum())
        inside_n += int(differs.sum())
        outside_sum += float(diff[~robot].sum())
        outside_n += int((~robot).sum())
        region_n += int(differs.sum())
        total_n += differs.numel()
        if not example:
            k = a.shape[1] - 1  # the last frame: the largest deviation
            example = {"generated_a": _u8(gens[0][0, k, :, :h]), "generated_b": _u8(gens[1][0, k, :, :h]),
                       "motion_a": _u8(mosaic.controls(m_a[0, k])[:, :h]),
                       "motion_b": _u8(mosaic.controls(m_b[0, k])[:, :h]),
                       "difference": _u8(torch.cat(list(diff[0, k]), dim=-1) * 4),
                       "region": torch.cat(list(differs[0, k]), dim=-1), "start": list(part[0])}
    inside = inside_sum / max(inside_n, 1)
    outside = outside_sum / max(outside_n, 1)
    ratio = None if inside == 0 and outside == 0 else (inside / outside if outside > 0 else float("inf"))
    return Sensitivity(inside=inside, outside=outside, ratio=ratio, region_share=region_n / max(total_n, 1),
                       samples=len(starts), example=example)


def copy_reference_mse(reference: torch.Tensor, recorded: torch.Tensor, horizon: int, num_views: int) -> list[float]:
    """Per chunk index, the RGB-row MSE of a baseline that repeats the recorded first reference."""
    ref_rgb, _ = mosaic.split(reference.float() / 255, num_views)
    rec_rgb, _ = mosaic.split(recorded.float() / 255, num_views)
    err = ((rec_rgb - ref_rgb[:, None]) ** 2).mean(dim=(2, 3, 4, 5))  # (N, T)
    return [float(err[:, n * horizon:(n + 1) * horizon].mean()) for n in range(err.shape[1] // horizon)]


def summarise(metrics: list[dict], key: str = "mosaic") -> list[dict]:
    """``[{mse, psnr, ssim}]`` per chunk index from :func:`per_chunk_metrics`'s pooled block."""
    return [{m: r["pooled"][key][m] for m in ("mse", "psnr", "ssim")} for r in metrics]


def growth(values: Sequence[float]) -> list[float]:
    """Each chunk's value relative to the first chunk's."""
    first = values[0]
    return [float(v / first) if first else float("nan") for v in values]


__all__ = ["rollout_starts", "rollout_videos", "per_chunk_metrics", "perturb_actions", "action_sensitivity",
           "Sensitivity", "RolloutVideos", "copy_reference_mse", "summarise", "growth"]
