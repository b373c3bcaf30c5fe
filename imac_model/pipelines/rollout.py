"""Rollouts over consecutive chunks: training-time rollout (paper section 3.4) and long
autoregressive sampling, both with controls rebuilt online at every chunk boundary.

:func:`rollout_loss`: a clip of R consecutive chunks; chunk r > 1 starts from the last frame
of chunk r-1's one-step clean estimate (decoded, detached), its contact images rebuilt from
that frame's depth, its target the recorded future; the loss is the mean over chunks, and
each chunk's graph ends at its detached reference, so backward may run per chunk.
:func:`sample_rollout`: N chunks sampled with the Euler sampler, each from the last generated
frame. ``docs/world-model.md`` ("Training-time rollout") has the details."""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import torch

from imac_data.errors import InputError
from imac_model.data.batch import ChunkBatch
from imac_model.modes import REBUILT_STREAMS

if TYPE_CHECKING:  # the rig and its renderer are not needed to train from a pack (the GPU machine lacks them)
    from imac_model.pipelines.online_controls import OnlineControls


@dataclass
class RolloutOutput:
    loss: torch.Tensor  # (1/R) sum of the chunk losses (with a graph unless backward was given)
    chunk_losses: list[torch.Tensor]  # L_r, detached
    references: list[torch.Tensor]  # the reference mosaic each chunk was trained from (B, 3, 2h, V w)
    controls: list[dict[str, torch.Tensor]]  # the controls each chunk was given
    taus: list[torch.Tensor] = field(default_factory=list)
    noises: list[torch.Tensor] = field(default_factory=list)
    invalid_depth: list[float] = field(default_factory=list)  # per rebuilt chunk: share of invalid depth pixels


def _contact_active(streams: Sequence[str]) -> bool:
    return any(s in streams for s in REBUILT_STREAMS)


def last_frame(model, out) -> torch.Tensor:
    """The last future frame ``(B, 3, 2h, V w)`` of a training output's one-step clean
    estimate, decoded and detached: the next chunk's reference."""
    with torch.no_grad():
        frames = model.decode_future(out.reference_latent, out.clean_estimate.detach())
    return frames[:, -1].detach().clamp(0.0, 1.0).float()


def sampled_last_frame(model, batch: ChunkBatch, out, steps: int, generator: torch.Generator | None,
                       streams: Sequence[str], rows: tuple[int, int] = (0, 1), autocast=None) -> torch.Tensor:
    """The last frame ``(B, 3, 2h, V w)`` of ``steps`` Euler steps of the sampler on ``batch`` (the
    chunk a training output ``out`` came from): what a replay goes on from. The noise is drawn for the
    global batch and sliced to ``rows``, as :meth:`WorldModel.forward` draws its own."""
    r, n = rows
    shape = out.x_tau.shape
    gen_dev = generator.device if generator is not None else out.x_tau.device
    noise = torch.randn((shape[0] * n, *shape[1:]), generator=generator, device=gen_dev)[r::n]
    with torch.no_grad(), (autocast or contextlib.nullcontext)():
        frames = model.sample(batch, steps=steps, noise=noise.to(out.x_tau.device), streams=tuple(streams) or None).frames
    return frames[:, -1].detach().clamp(0.0, 1.0).float()


def rollout_loss(model, clip: Sequence[ChunkBatch], online: OnlineControls | None, *,
                 generator: torch.Generator | None = None, clean_reference: bool = False,
                 streams: Sequence[str] | None = None, commanded_state: bool = False,
                 backward: Callable[[torch.Tensor], None] | None = None,
                 taus: Sequence[torch.Tensor] | None = None, noises: Sequence[torch.Tensor] | None = None,
                 autocast=None, rows: tuple[int, int] = (0, 1),
                 loss_of: Callable | None = None, stored_contact: bool = False,
                 reference_steps: int = 0, rebuild: Callable | None = None) -> RolloutOutput:
    """The training-time rollout loss of a batch of clips: ``clip[r]`` is chunk r of every
    clip. See the module docstring. ``backward(loss_r / R)`` is called per chunk when given
    (then the returned loss is detached). ``taus``/``noises`` fix each chunk's draws (tests).
    ``rows``: the data-parallel slice of :meth:`WorldModel.forward`; ``loss_of(out)``: the
    chunk's loss to train on (default ``out.loss``; data-parallel training rebalances it).
    ``stored_contact``: chunk r > 1 keeps its recorded contact images and only its reference is
    the model's own. ``rebuild(r, reference)``: chunk r's contact controls and invalid-depth shares
    ``(dict, (B,))`` from its reference, instead of ``online`` (a machine without the renderer: the GPU
    preset's pack trainer, :class:`~imac_model.pipelines.packed_contact.PackedContact`).
    ``reference_steps`` k > 0: chunk r > 1 starts from the last frame of ``k`` sampler steps on chunk
    r-1's inputs (no gradient; noise drawn for the global batch, as the loss's) instead of the one-step
    estimate, whose noised input holds a share tau of the true future (docs/world-model.md)."""
    R = len(clip)
    if R < 1:
        raise InputError("rollout: a clip needs at least one chunk")
    base = getattr(model, "module", model)  # under DDP the world model is .module
    streams = tuple(base.active_streams(None if streams is None else tuple(streams)))
    rebuild_contact = _contact_active(streams) and not clean_reference and not stored_contact
    if rebuild_contact and online is None and rebuild is None:
        raise InputError("rollout: rebuilding contact images needs the dataset's OnlineControls")
    autocast = autocast or contextlib.nullcontext
    result = RolloutOutput(loss=torch.zeros(()), chunk_losses=[], references=[], controls=[])
    total = reference = q_prev = actions_prev = None
    for r, batch in enumerate(clip):
        q_ref = batch.state
        if r == 0 or clean_reference:
            chunk = batch
        else:
            controls = dict(batch.controls)
            if rebuild_contact and rebuild is not None:
                rebuilt_controls, invalid = rebuild(r, reference)
                controls.update(rebuilt_controls)
                result.invalid_depth.append(float(invalid.mean()))
            elif rebuild_contact:
                if q_ref is None or commanded_state:  # what a closed loop knows: the last command
                    if q_prev is None:
                        raise InputError("rollout: no reference state (observation.state) in the clip's first "
                                         "chunk; contact images cannot be rebuilt")
                    q_ref = online.configurations(q_prev, actions_prev)[:, -1].to(batch.actions)
                rebuilt = online.controls(reference, q_ref, batch.actions,
                                          streams=tuple(s for s in streams if s in REBUILT_STREAMS))
                controls.update(rebuilt.controls)
                result.invalid_depth.append(float(rebuilt.invalid_fraction.mean()))
            chunk = replace(batch, reference=reference, controls=controls)
        with autocast():
            out = model(chunk, generator=generator, streams=streams or None, rows=rows,
                        tau=None if taus is None else taus[r], noise=None if noises is None else noises[r])
        loss_r = (out.loss if loss_of is None else loss_of(out)) / R
        if backward is not None:
            backward(loss_r)
            loss_r = loss_r.detach()
        total = loss_r if total is None else total + loss_r
        result.chunk_losses.append(out.loss.detach())
        result.references.append(chunk.reference)
        result.controls.append(chunk.controls)
        result.taus.append(out.tau.detach())
        if r + 1 < R and not clean_reference:
            if reference_steps > 0:
                reference = sampled_last_frame(base, chunk, out, reference_steps, generator, streams, rows, autocast)
            else:
                reference = last_frame(base, out)
        q_prev, actions_prev = q_ref, batch.actions
    result.loss = total
    return result


# --------------------------------------------------------------------------- sampling


@dataclass
class SampledRollout:
    frames: torch.Tensor  # (B, N, H, 3, 2h, V w) generated future mosaics
    references: list[torch.Tensor]  # N references (B, 3, 2h, V w): the first given, then generated
    controls: list[dict[str, torch.Tensor]]  # per chunk, the controls the model was given
    states: list[torch.Tensor]  # per chunk, the reference state used (B, D)
    invalid_depth: list[float]  # per rebuilt chunk


@torch.no_grad()
def sample_rollout(model, first: ChunkBatch, actions: torch.Tensor, online: OnlineControls | None, *,
                   q0: torch.Tensor | None = None, states: torch.Tensor | None = None,
                   steps: int | None = None, seed: int = 0, first_controls: str = "given",
                   include_reference_step: bool = False, noise: Sequence[torch.Tensor] | None = None,
                   scene: torch.Tensor | None = None, progress: bool = False) -> SampledRollout:
    """Roll out ``N = actions.shape[1]`` chunks from ``first.reference``.

    ``actions (B, N, H, D)``: every chunk's actions; ``q0 (B, D)``: the state at the first
    reference (default ``first.state``); ``states (B, N, D)``: recorded reference states to use
    instead of the commanded ones (default: chunk n > 1 starts at chunk n-1's last commanded
    configuration, as in a closed loop). ``first_controls``: ``"given"`` uses ``first``'s
    controls for chunk 1 (recorded, e.g. a dataset's), ``"online"`` rebuilds them too (from the
    first reference's depth; ``include_reference_step`` when it is an episode's frame 0).
    Each chunk's noise is drawn from ``seed + n`` (or given in ``noise``), so two calls that
    differ only in their actions get the same noise. Every chunk keeps ``first.first_frame``.
    ``scene (B, 3, 2h, V w)``: the frame whose depth chunk 1's contact images are rebuilt from,
    instead of its reference (a diagnosis gives the recorded frame where the reference is generated).
    """
    from tqdm.auto import tqdm

    base = getattr(model, "module", model)
    streams = base.streams
    B, N = actions.shape[:2]
    if q0 is None:
        q0 = first.state
    needs_online = bool(streams) and (N > 1 or first_controls == "online")
    if needs_online and (online is None or q0 is None):
        raise InputError("sample_rollout: rebuilding controls needs OnlineControls and the first reference state")
    dev = first.reference.device
    reference, q_ref = first.reference, q0
    frames, refs, controls_used, states_used, invalid = [], [], [], [], []
    for n in tqdm(range(N), desc="rollout chunks", disable=not progress):
        a = actions[:, n].to(dev)
        if states is not None:
            q_ref = states[:, n]
        if n == 0 and first_controls == "given":
            controls = {s: first.controls[s] for s in streams}
            q_future = online.configurations(q_ref, a) if (online is not None and q_ref is not None) else None
        elif streams:
            rebuilt = online.controls(scene if (n == 0 and scene is not None) else reference, q_ref, a,
                                      streams=streams,
                                      include_reference_step=include_reference_step and n == 0)
            controls = rebuilt.controls
            q_future = rebuilt.configurations
            if rebuilt.invalid_fraction is not None:
                invalid.append(float(rebuilt.invalid_fraction.mean()))
        else:
            controls, q_future = {}, None
        batch = ChunkBatch(reference=reference, actions=a, controls=controls, first_frame=first.first_frame)
        if noise is not None:
            out = base.sample(batch, steps=steps, noise=noise[n])
        else:
            out = base.sample(batch, steps=steps, generator=torch.Generator().manual_seed(seed + n))
        frames.append(out.frames)
        refs.append(reference)
        controls_used.append(controls)
        states_used.append(q_ref)
        reference = out.frames[:, -1].clamp(0.0, 1.0)
        if q_future is not None:
            q_ref = q_future[:, -1].to(dev)
    return SampledRollout(frames=torch.stack(frames, dim=1), references=refs, controls=controls_used,
                          states=states_used, invalid_depth=invalid)
