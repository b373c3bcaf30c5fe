"""The trainer's data source on a LeRobot dataset (:mod:`.sources`): chunks decoded through
:class:`~imac_model.data.chunks.ChunkDataset` (held-out episodes apart), contact images of a rollout
rebuilt by the renderer (:class:`~imac_model.pipelines.online_controls.OnlineControls`)."""

from __future__ import annotations

import torch

from imac_data.errors import InputError
from imac_data.metadata import dataset_info
from imac_model.config import ModelSpec, RunConfig
from imac_model.data.batch import ChunkBatch
from imac_model.data.chunks import ChunkDataset, action_stats, open_metadata, resolve_layout, split_episodes
from imac_model.models.backbones.build import spatial_multiple, temporal_factor
from imac_model.modes import REBUILT_STREAMS
from imac_model.pipelines.online_controls import OnlineControls


def model_spec(run: RunConfig, meta) -> tuple[ModelSpec, object]:
    """The resolved model of a run on a dataset (checks the dataset against the run)."""
    layout = resolve_layout(dataset_info(meta), run.data, run.conditioning.streams,
                            spatial_multiple=spatial_multiple(run.backbone),
                            temporal_factor=temporal_factor(run.backbone), mode=run.conditioning.mode)
    mean, std = action_stats(meta)
    spec = ModelSpec(backbone=run.backbone, conditioning=run.conditioning, flow=run.flow, views=layout.views,
                     view_height=layout.view_hw[0], view_width=layout.view_hw[1], chunk=layout.chunk,
                     action_dim=layout.action_dim, fps=layout.fps, dataset=run.data.dataset,
                     action_mean=tuple(mean), action_std=tuple(std))
    return spec, layout


class DatasetSource:
    def __init__(self, run: RunConfig):
        self.run = run
        self.meta = open_metadata(run.data)
        self.spec, self.layout = model_spec(run, self.meta)
        self.train_episodes, self.held_episodes = split_episodes(self.meta.total_episodes,
                                                                 run.data.held_out_episodes)
        self.online = None

    def _chunks(self, episodes: list[int]) -> ChunkDataset:
        d = self.run.data
        return ChunkDataset(d.dataset, self.layout, root=d.root, episodes=episodes, cache=d.cache,
                            cache_dir=d.cache_dir, video_backend=d.video_backend)

    def load(self, device: torch.device, progress: bool) -> None:
        d, rc = self.run.data, self.run.rollout
        self.train_set = self._chunks(self.train_episodes)
        self.held_set = self._chunks(self.held_episodes) if self.held_episodes else None
        if len(self.train_set) == 0:
            raise InputError(f"data: no training chunks (episodes {self.train_episodes})")
        if d.cache == "memory":
            for chunks in (self.train_set, self.held_set):
                if chunks is not None:
                    chunks.preload(num_workers=d.num_workers, progress=progress)
        if rc.chunks > 1 and any(s in self.spec.conditioning.streams for s in REBUILT_STREAMS):
            self.online = OnlineControls.from_dataset(
                self.train_set.lerobot.root, self.spec, info=dataset_info(self.meta), resolution=rc.resolution,
                max_walk_distance=rc.max_walk_distance, device=device if rc.device == "auto" else torch.device(rc.device))
            self.online.rig.renderer, self.online.rig.gripper  # noqa: B018 - built before the clock starts
        self.n_train, self.n_held = len(self.train_set), len(self.held_set) if self.held_set is not None else 0

    def train_batch(self, items: list[int]) -> ChunkBatch:
        return self.train_set.batch(items)

    def held_batch(self, items: list[int]) -> ChunkBatch:
        return self.held_set.batch(items)

    def clips(self, length: int) -> list[list[int]]:
        return self.train_set.clips(length)

    def rollout_inputs(self, clip_items: list[list[int]], contact_streams: tuple[str, ...]) -> dict:
        return {"online": self.online}


def decode_to_cache(run: RunConfig, workers: int = 1) -> None:
    """Decode ``run``'s training and held-out chunks into its chunk cache (``data.cache_dir``), as its training
    would first: runs of other modes on the same data then read them from there."""
    torch.set_num_threads(1)
    run = run.replace(**{"rollout.chunks": 1, "data.num_workers": workers, "data.cache": "memory"})
    DatasetSource(run).load(torch.device("cpu"), progress=False)


__all__ = ["DatasetSource", "decode_to_cache", "model_spec"]
