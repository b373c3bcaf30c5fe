"""Closed-loop policy evaluation inside the world model (paper section 4.1).

A policy sees the latest generated frame and the robot state and supplies actions (LeRobot's
``select_action`` queue semantics); the world model generates the next chunk from them, with
its controls rebuilt online; the chunk's last frame is the next reference. Starts, seeds and
horizons come from a real dataset's episodes, so every policy meets the same starts and noise.
The generated episodes are written as a LeRobot dataset (:class:`GeneratedDatasetWriter`),
judged by any :class:`~imac_model.evaluate.success.SuccessJudge`. ``docs/evaluation.md`` has
the protocol and the dataset's columns."""

from __future__ import annotations

import math
import sys
from collections import deque
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from imac_data.build.staging import staged_output
from imac_data.dataset.columns import add_episode_columns
from imac_data.dataset.episodes import EpisodeWriter
from imac_data.dataset.info import update_imac_info
from imac_data.dataset.output import check_output, refuse_overlap
from imac_data.errors import InputError
from imac_data.layout import ACTION, EPISODE_COLUMNS, SIM_COLUMNS, SUCCESS_COLUMN, control_key, depth_key, image_key
from imac_model.data import meta as dataset_meta
from imac_model.data import mosaic
from imac_model.data.batch import ChunkBatch, unit_frames
from imac_model.evaluate.policies import (
    STATE_KEY,
    ActionQueue,
    check_task,
    make_observation,
    policy_name,
    recorded_actions_policy,
)
from imac_model.evaluate.success import EpisodeFrames
from imac_model.pipelines.rollout import sample_rollout

SOURCE = "world_model"


# --------------------------------------------------------------------------- starts

SIM_SEED = SIM_COLUMNS[1]  # meta/episodes: a simulated episode's start seed


@dataclass(frozen=True)
class Start:
    """Where a closed-loop episode starts: a real episode's recorded frame and state."""

    episode: int  # the source dataset's episode index
    frame: int  # the reference frame within it
    reference: torch.Tensor  # (3, 2h, V w) float in [0, 1]
    state: torch.Tensor  # (D,)
    chunks: int  # horizon, in world-model chunks of H frames
    seed: int
    task: str
    recorded_actions: torch.Tensor  # (T - frame, D): the episode's recorded actions from the start frame
    sim_seed: int | None = None  # a simulated episode's start seed (its reset(seed)): policies are told it


def episode_starts(chunks, episodes: Sequence[int], *, seed: int = 0, horizon_chunks: int | None = None
                   ) -> list[Start]:
    """One :class:`Start` per episode of ``chunks`` (:class:`imac_model.data.chunks.ChunkDataset`):
    its first chunk's reference frame and state; ``horizon_chunks`` (default: enough chunks to
    cover the recorded episode); seed ``seed + episode``."""
    meta = chunks.lerobot.meta
    if not chunks.has_state:
        raise InputError(f"{chunks.lerobot.root}: the dataset has no observation.state; a closed loop needs the "
                         "start state")
    if horizon_chunks is not None and horizon_chunks < 1:
        raise InputError(f"horizon: must be >= 1 chunk, got {horizon_chunks}")
    H = chunks.layout.chunk
    out = []
    for e in episodes:
        if not 0 <= e < meta.total_episodes:
            raise InputError(f"episode {e}: the dataset has episodes 0..{meta.total_episodes - 1}")
        items = chunks.episode_chunks(e)
        if not items:
            raise InputError(f"episode {e}: not among the loaded episodes")
        item = chunks[items[0]]
        _, _, frame = chunks.index[items[0]]
        lo, hi = int(meta.episodes["dataset_from_index"][e]), int(meta.episodes["dataset_to_index"][e])
        actions = torch.stack([torch.as_tensor(a, dtype=torch.float32)
                               for a in chunks.lerobot.hf_dataset.select(range(lo + frame, hi))["action"]])
        n = horizon_chunks if horizon_chunks is not None else max(1, math.ceil((hi - lo - 1 - frame) / H))
        tasks = meta.episodes["tasks"][e]
        sim_seed = meta.episodes[SIM_SEED][e] if SIM_SEED in meta.episodes.column_names else None
        ref = item["reference"]
        out.append(Start(episode=int(e), frame=int(frame),
                         reference=unit_frames(ref),
                         state=item["state"].float(), chunks=int(n), seed=int(seed) + int(e),
                         task=tasks[0] if tasks else "", recorded_actions=actions,
                         sim_seed=None if sim_seed is None else int(sim_seed)))
    return out


# --------------------------------------------------------------------------- one episode


def observation_of(frame: torch.Tensor, state: torch.Tensor, views: Sequence[str], task: str = "",
                   online=None) -> dict:
    """A policy's observation (:func:`~imac_model.evaluate.policies.make_observation`) of a
    mosaic frame ``(3, 2h, V w)``: each view's RGB and, with ``online``
    (:class:`OnlineControls`, which knows the depth codec), its decoded depth in metres."""
    rgb, _ = mosaic.split(frame, len(views))
    depth = None if online is None else online.reference_depth(frame[None])[0][0]
    return make_observation(rgb, depth, state, views, task)


@dataclass
class ChunkRecord:
    """What one world-model chunk of a closed-loop episode produced."""

    index: int
    reference: torch.Tensor  # (3, 2h, V w): the frame the chunk started from
    state: torch.Tensor  # (D,): the state there
    actions: torch.Tensor  # (H, D) executed
    frames: torch.Tensor  # (H, 3, 2h, V w) generated, in [0, 1]
    configurations: torch.Tensor  # (H, D) commanded configurations phi(state, actions)
    controls: dict[str, torch.Tensor]  # stream -> (H, V, 3, h, w) the controls the model was given
    invalid_depth: float | None  # share of invalid predicted depth pixels of the reference (None: not decoded)


@torch.no_grad()
def rollout_episode(model, online, policy, start: Start, *, steps: int | None = None,
                    views: Sequence[str] | None = None, intervene=None, scene=None) -> Iterator[ChunkRecord]:
    """Run ``policy`` in the world model from ``start`` for ``start.chunks`` chunks (see the
    module docstring), yielding each chunk as it is generated. ``policy``: a callable or an
    :class:`ActionQueue`. ``intervene(reference, n) -> reference``, at each later chunk
    boundary ``n`` before the policy looks, may replace the frame the world model goes on from
    (an intervention test: the policy should act on what it is shown). ``scene(n) -> frame``
    ``(3, 2h, V w)`` gives the frame whose depth chunk ``n``'s contact images are rebuilt from,
    instead of its reference (a diagnosis: the recorded frame where the model's is generated)."""
    base = getattr(model, "module", model)
    spec = base.spec
    views = tuple(views or spec.views)
    if online is None:
        raise InputError("closed loop: the dataset's OnlineControls are needed (the next state is phi(q, actions))")
    queue = policy if isinstance(policy, ActionQueue) else ActionQueue(policy, spec.action_dim)
    queue.reset(start.sim_seed)
    device = next(base.parameters()).device
    reference = start.reference[None].to(device)
    start_frame = reference  # the first frame a model conditioned on it keeps (conditioning.first_frame)
    q = start.state[None].float()
    H = spec.chunk
    for n in range(start.chunks):
        if intervene is not None and n > 0:
            reference = intervene(reference, n).to(device)
        actions = queue.take(observation_of(reference[0].cpu(), q[0], views, start.task, online), H)[None]  # (1, H, D)
        first = ChunkBatch(reference=reference, actions=actions.to(device), state=q.to(device),
                           first_frame=start_frame)
        out = sample_rollout(base, first, actions[:, None].to(device), online, q0=q.to(device), steps=steps,
                             seed=start.seed + n, first_controls="online",
                             include_reference_step=(n == 0 and start.frame == 0),
                             scene=None if scene is None else scene(n)[None].to(device))
        configurations = online.configurations(q, actions)  # (1, H, D)
        frames = out.frames[0, 0].clamp(0, 1)
        yield ChunkRecord(index=n, reference=reference[0].cpu(), state=q[0].cpu(), actions=actions[0].cpu(),
                          frames=frames.cpu(), configurations=configurations[0].cpu(),
                          controls={s: mosaic.control_views(c[0], len(views)).cpu() for s, c in out.controls[0].items()},
                          invalid_depth=out.invalid_depth[0] if out.invalid_depth else None)
        reference = frames[-1:].to(device)
        q = configurations[:, -1]


# --------------------------------------------------------------------------- the dataset of generated episodes


def _u8(x: torch.Tensor) -> np.ndarray:
    """(n, 3, h, w) in [0, 1] -> (n, h, w, 3) uint8."""
    return (x.clamp(0, 1) * 255).round().to(torch.uint8).permute(0, 2, 3, 1).contiguous().numpy()


def generated_features(spec, state_names: Sequence[str] | None = None) -> dict:
    """LeRobot features of a dataset of generated episodes for a model of ``spec``."""
    h, w = spec.view_height, spec.view_width
    video = {"dtype": "video", "shape": (h, w, 3), "names": ["height", "width", "channels"]}
    names = list(state_names) if state_names and len(state_names) == spec.action_dim else None
    features = {STATE_KEY: {"dtype": "float32", "shape": (spec.action_dim,), "names": names},
                ACTION: {"dtype": "float32", "shape": (spec.action_dim,), "names": names}}
    for v in spec.views:
        features[image_key(v)] = dict(video)
    for v in spec.views:
        features[depth_key(v)] = dict(video)
    for s in spec.conditioning.streams:
        for v in spec.views:
            features[control_key(s, v)] = dict(video)
    return features


# a built dataset's episode columns, and where each generated episode started
GENERATED_COLUMNS = {**{k: "bool_" if k == SUCCESS_COLUMN else "string" for k in EPISODE_COLUMNS},
                     "imac/start_episode": "int64", "imac/start_frame": "int64", "imac/seed": "int64",
                     "imac/invalid_depth": "float64"}


class GeneratedDatasetWriter:
    """Generated episodes -> a LeRobot dataset at ``root``, through the builds' own staged flow
    (:func:`~imac_data.build.staging.staged_output`: the output's lock, an existing output
    replaced only when it is a dataset and ``overwrite`` is given, staging siblings deleted only
    when they are ours). :meth:`finish` moves it into place; :meth:`abort` leaves ``root`` as it
    was. See the module docstring."""

    def __init__(self, root: str | Path, repo_id: str, spec, *, state_names: Sequence[str] | None = None,
                 overwrite: bool = False):
        self.root = Path(root)
        # not an imac dataset (no rig): the builds' validation does not apply
        self._output = staged_output(self.root, overwrite=overwrite, validate=False, what="--output")
        self.staging = self._output.__enter__().dataset
        self.spec = spec
        self.views = tuple(spec.views)
        self.streams = tuple(spec.conditioning.streams)
        self.writer = EpisodeWriter(self.staging, repo_id, fps=int(round(spec.fps)),
                                    features=generated_features(spec, state_names))
        self.rows: list[dict] = []
        self._pending: dict | None = None

    def _rows(self, frames: torch.Tensor, states: torch.Tensor, actions: torch.Tensor,
              controls: Mapping[str, torch.Tensor] | None) -> dict:
        rgb, depth = mosaic.split(frames, len(self.views))  # (n, V, 3, h, w)
        out = {STATE_KEY: states.float().numpy(), ACTION: actions.float().numpy()}
        for i, v in enumerate(self.views):
            out[image_key(v)] = _u8(rgb[:, i])
            out[depth_key(v)] = _u8(depth[:, i])
        n = len(frames)
        for s in self.streams:
            for i, v in enumerate(self.views):
                c = controls[s][:, i] if controls is not None else torch.zeros(n, 3, *rgb.shape[-2:])
                out[control_key(s, v)] = _u8(c)
        return out

    def begin_episode(self, start: Start, columns: Mapping) -> None:
        self.writer.begin_episode(1 + start.chunks * self.spec.chunk, task=start.task)
        self.rows.append(dict(columns))
        self._pending = {"frame": start.reference[None], "state": start.state[None], "controls": None}

    def add_chunk(self, record: ChunkRecord) -> None:
        """Frames ``nH .. nH + H - 1`` (their actions are now known); the chunk's last frame waits
        for the next chunk's first action."""
        p = self._pending
        H = len(record.frames)
        frames = torch.cat([p["frame"], record.frames[:-1]])
        states = torch.cat([p["state"], record.configurations[:-1]])
        if p["controls"] is None:
            controls = {s: torch.cat([torch.zeros_like(c[:1]), c[:-1]]) for s, c in record.controls.items()}
        else:
            controls = {s: torch.cat([p["controls"][s], c[:-1]]) for s, c in record.controls.items()}
        self.writer.add_frames(self._rows(frames, states, record.actions, controls if self.streams else None))
        self._pending = {"frame": record.frames[H - 1:], "state": record.configurations[H - 1:],
                         "controls": {s: c[H - 1:] for s, c in record.controls.items()},
                         "action": record.actions[H - 1:]}

    def end_episode(self, columns: Mapping | None = None) -> None:
        p = self._pending
        self.writer.add_frames(self._rows(p["frame"], p["state"], p["action"], p["controls"] if self.streams else None))
        self.writer.end_episode()
        if columns:
            self.rows[-1].update(columns)
        self._pending = None

    def finish(self, info_block: Mapping | None = None) -> Path:
        import pyarrow as pa

        self.writer.finish()
        add_episode_columns(self.staging, self.rows, {k: getattr(pa, t)() for k, t in GENERATED_COLUMNS.items()})
        if info_block:
            update_imac_info(self.staging, info_block)
        self._output.__exit__(None, None, None)  # swap into place, release the lock
        return self.root

    def abort(self) -> None:
        """Drop the staged dataset (called while handling the error that stopped the run)."""
        error = sys.exc_info()
        if error[0] is None:
            error = (InputError, InputError("closed loop aborted"), None)
        try:
            self.writer.abort()
        finally:
            self._output.__exit__(*error)


# --------------------------------------------------------------------------- a whole evaluation


@dataclass(frozen=True)
class ClosedLoopConfig:
    """One closed-loop evaluation: which starts, how long, how sampled, how judged."""

    episodes: tuple[int, ...]  # start episodes of the source dataset
    horizon_chunks: int | None = None  # None: as many chunks as cover each recorded episode
    sampler_steps: int | None = None  # None: the model's flow.sample_steps
    seed: int = 0  # episode e's chunk n draws its noise from seed + e + n
    judge_frames: int = 4  # last frames per view the success judge sees

    def __post_init__(self) -> None:
        object.__setattr__(self, "episodes", tuple(int(e) for e in self.episodes))
        if not self.episodes:
            raise InputError("closed loop: no start episodes")
        if len(set(self.episodes)) != len(self.episodes):
            raise InputError(f"closed loop: start episodes repeat: {list(self.episodes)}")
        if self.horizon_chunks is not None and self.horizon_chunks < 1:
            raise InputError(f"closed loop: horizon_chunks must be >= 1, got {self.horizon_chunks}")
        if self.sampler_steps is not None and self.sampler_steps < 1:
            raise InputError(f"closed loop: sampler_steps must be >= 1, got {self.sampler_steps}")
        if self.judge_frames < 1:
            raise InputError(f"closed loop: judge_frames must be >= 1, got {self.judge_frames}")


@dataclass
class ClosedLoopResult:
    root: Path
    protocol: dict
    episodes: list[dict] = field(default_factory=list)

    def to_dict(self) -> dict:
        judged = [e["success"] for e in self.episodes if e["success"] is not None]
        return {"protocol": self.protocol, "dataset": str(self.root), "episodes": self.episodes,
                "success_rate": (float(np.mean(judged)) if judged else None), "judged_episodes": len(judged)}


def judged_frames(index: int, last: Sequence[tuple[torch.Tensor, torch.Tensor]], views: Sequence[str], task: str,
                  online) -> EpisodeFrames:
    """What a judge sees of a generated episode: its last ``(mosaic frame, configuration)``
    pairs as RGB, decoded depth and states per view."""
    frames = torch.stack([f for f, _ in last])
    rgb, _ = mosaic.split(frames, len(views))
    depth, _ = online.reference_depth(frames)
    keys = [image_key(v) for v in views]
    return EpisodeFrames(index, {k: rgb[:, j] for j, k in enumerate(keys)}, task,
                         depth={k: depth[:, j] for j, k in enumerate(keys)},
                         states=torch.stack([q for _, q in last]))


def check_policy(policy, spec, state_dim: int | None) -> None:
    """Refuse a policy that declares a mismatch with the world model before any work."""
    check = getattr(policy, "check", None)
    if callable(check):
        check(views=spec.views, action_dim=spec.action_dim, state_dim=state_dim)


def run_closed_loop(model, chunks, online, policy, output: str | Path, *, config: ClosedLoopConfig,
                    repo_id: str = "local/closed_loop", judge=None, checkpoint: str = "", overwrite: bool = False,
                    progress: bool = True) -> ClosedLoopResult:
    """Evaluate ``policy`` from each start episode of ``chunks`` (the source dataset) in
    ``model``; write the generated episodes as a LeRobot dataset at ``output``; judge them
    with ``judge`` (a :class:`SuccessJudge`, or None). ``policy``: a policy callable, or
    ``"recorded"`` (each start episode's own recorded actions)."""
    from tqdm.auto import tqdm

    spec = model.spec
    output = Path(output)
    meta = chunks.lerobot.meta
    refuse_overlap(output, {"source dataset": Path(chunks.lerobot.root),
                            "world-model checkpoint": Path(checkpoint) if checkpoint else None}, what="--output")
    check_output(output, overwrite=overwrite, what="--output")  # before any work; the writer checks again, locked
    state_feature = meta.features.get(STATE_KEY)
    state_dim = int(state_feature["shape"][0]) if state_feature else None
    if state_dim is not None and state_dim != spec.action_dim:
        raise InputError(f"{chunks.lerobot.root}: observation.state is {state_dim}-D but actions are "
                         f"{spec.action_dim}-D; the closed loop feeds the commanded configuration back as the state")
    if policy != "recorded":
        check_policy(policy, spec, state_dim)
    starts = episode_starts(chunks, config.episodes, seed=config.seed, horizon_chunks=config.horizon_chunks)
    for start in starts if policy != "recorded" else ():
        check_task(policy, start.task, f"the task of start episode {start.episode}")
    names = (state_feature or {}).get("names")
    name = "recorded" if policy == "recorded" else policy_name(policy)
    protocol = {
        "frames_per_episode": [1 + s.chunks * spec.chunk for s in starts],
        "chunk_frames": spec.chunk,
        "resolution": {"view": [spec.view_height, spec.view_width], "mosaic": list(spec.mosaic_hw)},
        "views": list(spec.views),
        "samples": len(starts),
        "sampler_steps": config.sampler_steps or spec.flow.sample_steps,
        "guidance": spec.conditioning.guidance,
        "seed": config.seed,
        "seed_rule": "episode e, chunk n: noise from seed + e + n",
        "horizon_chunks": [s.chunks for s in starts],
        "start_episodes": [s.episode for s in starts],
        "start_frames": [s.frame for s in starts],
        "source_dataset": {"repo_id": chunks.lerobot.repo_id, "root": str(chunks.lerobot.root)},
        "checkpoint": checkpoint,
        "conditioning_mode": spec.conditioning.mode,
        "policy": name,
        "judge": None if judge is None else getattr(judge, "name", type(judge).__name__),
        "judge_frames": config.judge_frames,
        "controls": "rebuilt online from the policy's actions and the predicted depth (imac_model.pipelines.online_controls)",
        "next_state": "the last commanded configuration",
    }
    writer = GeneratedDatasetWriter(output, repo_id, spec, state_names=names, overwrite=overwrite)
    result = ClosedLoopResult(root=output, protocol=protocol)
    verdicts = []
    try:
        for i, start in enumerate(tqdm(starts, desc="closed-loop episodes", disable=not progress)):
            p = recorded_actions_policy(start.recorded_actions) if policy == "recorded" else policy
            queue = ActionQueue(p, spec.action_dim)
            writer.begin_episode(start, {"imac/source": SOURCE, "imac/policy_name": name,
                                         "imac/checkpoint": checkpoint, SUCCESS_COLUMN: None,
                                         "imac/start_episode": start.episode, "imac/start_frame": start.frame,
                                         "imac/seed": start.seed, "imac/invalid_depth": None})
            last = deque(maxlen=config.judge_frames)
            invalid = []
            for record in rollout_episode(model, online, queue, start, steps=config.sampler_steps):
                writer.add_chunk(record)
                last.extend(zip(record.frames.unbind(0), record.configurations.unbind(0)))
                if record.invalid_depth is not None:
                    invalid.append(record.invalid_depth)
            invalid_mean = float(np.mean(invalid)) if invalid else None
            writer.end_episode({"imac/invalid_depth": invalid_mean})
            verdicts.append(judged_frames(i, last, spec.views, start.task, online))
            result.episodes.append({"episode_index": i, "start_episode": start.episode, "start_frame": start.frame,
                                    "seed": start.seed, "frames": 1 + start.chunks * spec.chunk,
                                    "chunks": start.chunks, "policy_calls": queue.calls,
                                    "invalid_depth": invalid_mean, "success": None, "task": start.task})
        if judge is not None:
            success = [bool(s) for s in judge.judge(verdicts)]
            for row, ep, s in zip(writer.rows, result.episodes, success):
                row[SUCCESS_COLUMN] = ep["success"] = s
        writer.finish({"closed_loop": protocol, **dataset_meta.depth_entry(meta)})
    except BaseException:
        writer.abort()
        raise
    return result


__all__ = ["ChunkRecord", "ClosedLoopConfig", "ClosedLoopResult", "GeneratedDatasetWriter", "Start",
           "episode_starts", "generated_features", "judged_frames", "observation_of", "rollout_episode",
           "run_closed_loop"]
