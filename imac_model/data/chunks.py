"""Training chunks from an imac LeRobot dataset, through ``LeRobotDataset`` and
``delta_timestamps``.

One item = one chunk starting at a contact-chunk boundary (the dataset's reference
rule: chunk c has reference frame ``cH`` and future frames ``cH+1 .. cH+H``):

* the reference frame and the H future frames, RGB and colour depth, every view,
  resized to the model's view size and laid out as six-panel mosaics;
* the three control streams of the H future frames, duplicated vertically;
* a derived stream (``scene_warp``, :mod:`imac_model.data.scene_warp`), made from the item's reference,
  state and actions, and kept beside the cache of decoded items;
* the actions ``a_{cH} .. a_{cH+H-1}``, the state at the reference, the episode's
  success label.

A batch (:meth:`ChunkDataset.batch`) also carries each chunk's ``first_frame``, the reference
of its episode's first chunk (frame 0), for a model conditioned on it.

The last chunk of an episode may run past its end: LeRobot pads those frames (it
repeats the edge frame and flags it in ``<key>_is_pad``); ``future_valid`` carries the
flag so that padded frames are never trained on.

:func:`resolve_layout` checks a dataset against a run before anything is decoded:
the streams the conditioning mode needs, the chunk length (must equal the dataset's
contact chunk, whose controls were built for exactly that reference), and a view
size the backbone can patchify. Errors name the missing keys or the config field.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from imac_data import lerobot_compat as lr
from imac_data.errors import InputError
from imac_data.layout import INFO, info_path
from imac_model.config import DataConfig
from imac_model.data import meta as dataset_meta
from imac_model.data import mosaic
from imac_model.data.batch import collate
from imac_model.data.scene_warp import SceneWarp
from imac_model.modes import CONTROL_STREAMS, DERIVED_STREAMS, SCENE_WARP


@dataclass(frozen=True)
class ChunkLayout:
    """What a dataset item holds, resolved from the dataset and the run's config."""

    views: tuple[str, ...]
    view_hw: tuple[int, int]
    chunk: int  # H future frames
    streams: tuple[str, ...]  # control streams loaded (e.g. ("motion",))
    action_dim: int
    fps: float


def open_metadata(data: DataConfig):
    """LeRobot's metadata of the run's dataset (reads ``meta/`` only)."""
    if not data.dataset:
        raise InputError("data.dataset: name the dataset to train on (e.g. --dataset local/aloha_sim_transfer_cube)")
    try:
        return lr.LeRobotDatasetMetadata(data.dataset, root=data.root)
    except Exception as e:  # LeRobot raises hub/HTTP/OS errors for a missing local dataset
        where = data.root or f"$HF_LEROBOT_HOME/{data.dataset}"
        # no local dataset there makes LeRobot ask the hub: say that first, the network error after it
        missing = f" (there is no {INFO} there, so LeRobot tried the hub)" if data.root and not \
            info_path(data.root).is_file() else ""
        raise InputError(f"data.dataset: cannot open LeRobot dataset {data.dataset!r} at {where}{missing}: "
                         f"{type(e).__name__}: {e}") from None


def resolve_layout(info: dict, data: DataConfig, streams: Sequence[str], *, spatial_multiple: int,
                   temporal_factor: int, mode: str = "") -> ChunkLayout:
    """Check the dataset against the run and resolve views, view size and chunk length."""
    views = tuple(data.views) if data.views else dataset_meta.camera_names(info)
    if not views:
        raise InputError("the dataset has no camera streams (observation.images.*)")
    needed = ("rgb", "depth") + tuple(s for s in streams if s not in DERIVED_STREAMS)
    missing = dataset_meta.missing_features(info, needed, views)
    if missing:
        raise InputError(f"the dataset lacks streams that conditioning mode {mode!r} needs: {missing}; build it "
                         f"with python -m imac_data.build (which adds depth, motion and contact streams) or choose "
                         f"another conditioning.mode")
    if dataset_meta.ACTION not in info.get("features", {}):
        raise InputError("the dataset has no 'action' feature")
    H = dataset_meta.contact_chunk_size(info)
    if H is None and data.chunk is None:
        raise InputError("data.chunk: the dataset records no contact chunk size (meta/info.json imac.contact); "
                         "set data.chunk")
    if H is not None and data.chunk is not None and data.chunk != H:
        raise InputError(f"data.chunk: {data.chunk} future frames per chunk, but the dataset's contact chunk is {H} "
                         f"(its contact images are built from a reference every {H} frames: "
                         f"{dataset_meta.reference_rule(info)}); set data.chunk to {H} or leave it unset")
    chunk = data.chunk if H is None else H
    if chunk % temporal_factor:
        raise InputError(f"data.chunk: {chunk} future frames cannot be encoded by this backbone, which compresses "
                         f"time by {temporal_factor} (chunks of 1 + {temporal_factor}k frames)")
    shapes = {v: tuple(info["features"][dataset_meta.stream_key("rgb", v)]["shape"][:2]) for v in views}
    first = shapes[views[0]]
    for v, hw in shapes.items():
        if abs(hw[1] / hw[0] - first[1] / first[0]) > 0.02:
            raise InputError(f"camera {v} ({hw[0]}x{hw[1]}) has another aspect ratio than {views[0]} "
                             f"({first[0]}x{first[1]}); the mosaic needs equal view sizes")
    view_hw = mosaic.view_size(first, data.view_height, data.view_width, multiple=spatial_multiple,
                               num_views=len(views))
    return ChunkLayout(views=views, view_hw=view_hw, chunk=chunk, streams=tuple(streams),
                       action_dim=dataset_meta.feature_dim(info, dataset_meta.ACTION), fps=dataset_meta.fps(info))


def chunk_starts(length: int, chunk: int) -> list[int]:
    """Reference frames of an episode's chunks: 0, H, 2H, ... while a future frame exists."""
    return list(range(0, max(length - 1, 0), chunk))


def split_episodes(num_episodes: int, held_out: Sequence[int]) -> tuple[list[int], list[int]]:
    bad = [e for e in held_out if e >= num_episodes]
    if bad:
        raise InputError(f"data.held_out_episodes: {bad} do not exist (the dataset has {num_episodes} episodes)")
    held = sorted(set(held_out))
    return [e for e in range(num_episodes) if e not in held], held


def _frames(x: torch.Tensor) -> torch.Tensor:
    """LeRobot squeezes a single queried timestamp: put the time axis back."""
    return x[None] if x.ndim == 3 else x


def _to_uint8(x: torch.Tensor) -> torch.Tensor:
    return (x.clamp(0, 1) * 255.0).round().to(torch.uint8)


class ChunkDataset(Dataset):
    """Chunks of the given episodes of a LeRobot dataset (all episodes by default)."""

    def __init__(self, repo_id: str, layout: ChunkLayout, *, root=None, episodes: Sequence[int] | None = None,
                 cache: str = "memory", cache_dir=None, video_backend: str | None = None):
        self.layout = layout
        # derived streams are made from the decoded items, which are cached without them (so that runs with and
        # without them share the decoding)
        self.derived = tuple(s for s in layout.streams if s in DERIVED_STREAMS)
        layout = self.decoded_layout = replace(layout, streams=tuple(s for s in layout.streams
                                                                     if s not in DERIVED_STREAMS))
        H, fps = layout.chunk, layout.fps
        frames = [k / fps for k in range(H + 1)]
        delta = {dataset_meta.ACTION: [k / fps for k in range(H)]}
        for v in layout.views:
            delta[dataset_meta.stream_key("rgb", v)] = frames
            delta[dataset_meta.stream_key("depth", v)] = frames
            for s in layout.streams:
                delta[dataset_meta.stream_key(s, v)] = frames[1:]
        self.lerobot = lr.LeRobotDataset(repo_id, root=root, delta_timestamps=delta, video_backend=video_backend)
        meta = self.lerobot.meta
        self.has_state = dataset_meta.STATE in meta.features
        eps = list(range(meta.total_episodes)) if episodes is None else list(episodes)
        starts = meta.episodes["dataset_from_index"]
        lengths = meta.episodes["length"]
        success = (meta.episodes[dataset_meta.SUCCESS_COLUMN] if dataset_meta.SUCCESS_COLUMN in
                   meta.episodes.column_names else [None] * meta.total_episodes)
        self.index: list[tuple[int, int, int]] = []  # (absolute row, episode, reference frame)
        self.success: dict[int, bool | None] = {}
        for e in eps:
            self.success[e] = None if success[e] is None else bool(success[e])
            self.index += [(int(starts[e]) + r, e, r) for r in chunk_starts(int(lengths[e]), H)]
        if self.derived and not self.has_state:
            raise InputError(f"{repo_id}: stream(s) {list(self.derived)} are made from each chunk's reference state, "
                             f"and the dataset has no {dataset_meta.STATE!r}")
        self.scene_warp = (SceneWarp.from_dataset(meta, self.lerobot.root, layout.views, layout.view_hw)
                           if SCENE_WARP in self.derived else None)
        self._derived: dict[int, dict] = {}
        self.first_item = {e: i for i, (_, e, r) in enumerate(self.index) if r == 0}  # episode -> its chunk 0
        self._first_frames: dict[int, torch.Tensor] = {}
        self.cache: dict[int, dict] | None = {} if cache == "memory" else None
        self.cache_file = None
        if self.cache is not None and cache_dir is not None:
            self.cache_file = Path(cache_dir) / f"chunks-{self._fingerprint()}.pt"
            # a run with every control stream leaves a cache that runs with fewer streams reuse
            full = Path(cache_dir) / f"chunks-{self._fingerprint(CONTROL_STREAMS)}.pt"
            if self.cache_file.is_file():
                self.cache = torch.load(self.cache_file, weights_only=True)
            elif full.is_file() and set(layout.streams) < set(CONTROL_STREAMS):
                drop = {f"control.{s}" for s in CONTROL_STREAMS if s not in layout.streams}
                self.cache = {i: {k: v for k, v in item.items() if k not in drop}
                              for i, item in torch.load(full, weights_only=True).items()}

    def _fingerprint(self, streams: Sequence[str] | None = None) -> str:
        """What the cached items depend on: the dataset's files and the layout (with
        ``streams`` instead of the layout's own, if given)."""
        root = Path(self.lerobot.root)
        files = sorted(p for p in (root / "meta").rglob("*") if p.is_file())
        layout = self.decoded_layout if streams is None else replace(self.decoded_layout, streams=tuple(streams))
        h = hashlib.sha256(repr((asdict(layout), self.index)).encode())
        for p in files:
            h.update(p.name.encode())
            h.update(p.read_bytes())
        return h.hexdigest()[:16]

    def __len__(self) -> int:
        return len(self.index)

    def __getitem__(self, i: int) -> dict:
        if self.cache is not None and i in self.cache:
            item = self.cache[i]
        else:
            item = self._load(i)
            if self.cache is not None:
                self.cache[i] = item
        return self._with_derived(i, item) if self.derived else item

    def _with_derived(self, i: int, item: dict) -> dict:
        """``item`` with its derived streams (kept beside the cache, which holds decoded items)."""
        if i not in self._derived:
            warp = self.scene_warp.images(item["reference"][None].float() / 255.0, item["state"][None],
                                          item["actions"][None])[0]
            extra = {f"control.{SCENE_WARP}": _to_uint8(mosaic.controls(warp))}
            if self.cache is None:
                return {**item, **extra}
            self._derived[i] = extra
        return {**item, **self._derived[i]}

    def _load(self, i: int) -> dict:
        row, episode, frame = self.index[i]
        raw = self.lerobot[row]
        L = self.decoded_layout
        rgb = torch.stack([mosaic.resize_frames(raw[dataset_meta.stream_key("rgb", v)], L.view_hw)
                           for v in L.views], dim=1)
        depth = torch.stack([mosaic.resize_frames(raw[dataset_meta.stream_key("depth", v)], L.view_hw, kind="depth")
                             for v in L.views], dim=1)
        frames = _to_uint8(mosaic.assemble(rgb, depth))  # (1 + H, 3, 2h, V w)
        pad = raw[f"{dataset_meta.stream_key('rgb', L.views[0])}_is_pad"][1:]
        item = {
            "reference": frames[0],
            "future": frames[1:],
            "future_valid": ~pad,
            "actions": raw[dataset_meta.ACTION].float().reshape(L.chunk, -1),
            "episode_index": torch.tensor(episode),
            "frame_index": torch.tensor(frame),
        }
        for s in L.streams:
            views = torch.stack([mosaic.resize_frames(_frames(raw[dataset_meta.stream_key(s, v)]), L.view_hw)
                                 for v in L.views], dim=1)
            item[f"control.{s}"] = _to_uint8(mosaic.controls(views))
        if self.has_state:
            state = raw[dataset_meta.STATE]
            item["state"] = (state[0] if state.ndim == 2 else state).float()
        if self.success[episode] is not None:
            item["success"] = torch.tensor(self.success[episode])
        return item

    def preload(self, *, num_workers: int = 0, progress: bool = True) -> None:
        """Decode every chunk into the memory cache (in ``num_workers`` processes)."""
        if self.cache is None:
            return
        from torch.utils.data import DataLoader, Subset
        from tqdm.auto import tqdm

        todo = [i for i in range(len(self)) if i not in self.cache]
        if not todo:
            self._preload_derived(progress)
            return
        loader = DataLoader(Subset(_Uncached(self), todo), batch_size=None, num_workers=num_workers,
                            worker_init_fn=lr.open_videos_anew)
        for i, item in zip(todo, tqdm(loader, total=len(todo), desc="decoding chunks", disable=not progress,
                                      unit="chunk")):
            self.cache[i] = item
        if self.cache_file is not None:
            self.cache_file.parent.mkdir(parents=True, exist_ok=True)
            tmp = self.cache_file.with_suffix(f".{os.getpid()}.tmp")  # processes of one run may write it at once
            torch.save(self.cache, tmp)
            os.replace(tmp, self.cache_file)
        self._preload_derived(progress)

    def _preload_derived(self, progress: bool) -> None:
        from tqdm.auto import tqdm

        if self.derived:
            for i in tqdm(range(len(self)), desc=f"deriving {', '.join(self.derived)}", disable=not progress,
                          unit="chunk"):
                self[i]

    def episode_chunks(self, episode: int) -> list[int]:
        """Item indices of one episode's chunks, in time order."""
        return [i for i, (_, e, _) in enumerate(self.index) if e == episode]

    def clips(self, length: int) -> list[tuple[int, ...]]:
        """Every run of ``length`` consecutive chunks of one episode (item indices, time
        order): the training items of a training-time rollout over ``length`` chunks."""
        by_episode: dict[int, list[int]] = {}
        for i, (_, e, _) in enumerate(self.index):
            by_episode.setdefault(e, []).append(i)
        return [tuple(items[c:c + length]) for e, items in by_episode.items()
                for c in range(len(items) - length + 1)]

    def batch(self, indices: Sequence[int]):
        """A :class:`~imac_model.data.batch.ChunkBatch` of the given items, each with its
        episode's first frame."""
        items = [dict(self[i], first_frame=self.first_frame(self.index[i][1])) for i in indices]
        return collate(items)

    def first_frame(self, episode: int) -> torch.Tensor:
        """The episode's first frame ``(3, 2h, V w)`` uint8: its first chunk's reference (kept, so
        that a dataset without the chunk cache decodes that chunk once)."""
        if episode not in self._first_frames:
            self._first_frames[episode] = self[self.first_item[episode]]["reference"]
        return self._first_frames[episode]


class _Uncached(Dataset):
    """The dataset without its cache (so worker processes do not fill copies of it)."""

    def __init__(self, ds: ChunkDataset):
        self.ds = ds

    def __len__(self):
        return len(self.ds)

    def __getitem__(self, i):
        return self.ds._load(i)


def action_stats(meta) -> tuple[list[float], list[float]]:
    """Mean and std of the dataset's actions (LeRobot's ``meta/stats.json``)."""
    stats = meta.stats.get(dataset_meta.ACTION, {}) if meta.stats else {}
    if "mean" not in stats or "std" not in stats:
        return [], []
    return np.asarray(stats["mean"], dtype=float).tolist(), np.asarray(stats["std"], dtype=float).tolist()
