"""The trainer's data source on a tensor pack (:mod:`.sources`, :mod:`imac_model.data.pack`): what
the GPU machine trains from with torch and numpy alone. The model is the run's (its ``backbone``,
``conditioning`` and ``flow`` sections) on the pack's data (views, size, chunk, actions); the pack's
held-out chunks are the held-out set. A rollout's contact images are painted from each chunk's own
reference with the pack's geometry (:class:`~imac_model.pipelines.packed_contact.PackedContact`)."""

from __future__ import annotations

import dataclasses

import torch

from imac_data.errors import InputError
from imac_model.config import RunConfig
from imac_model.data.batch import ChunkBatch
from imac_model.data.pack import Pack
from imac_model.modes import CONTACT_STREAMS
from imac_model.pipelines.packed_contact import PackedContact


class PackSource:
    def __init__(self, run: RunConfig):
        self.run = run
        self.pack = Pack(run.data.pack)
        self.spec = dataclasses.replace(self.pack.spec, backbone=run.backbone, conditioning=run.conditioning,
                                        flow=run.flow)
        self.streams = self.spec.conditioning.streams
        missing = [s for s in self.streams if f"control.{s}" not in self.pack.tensors]
        if missing:
            have = sorted(k[len("control."):] for k in self.pack.tensors if k.startswith("control."))
            raise InputError(f"data.pack: {run.data.pack} carries no {missing} stream(s) (it has {have})")
        self.painter = None
        self.n_train, self.n_held = len(self.pack.train), len(self.pack.heldout)

    def load(self, device: torch.device, progress: bool) -> None:
        self.pack.to(device)
        rc = self.run.rollout
        if rc.chunks > 1 and rc.contact == "rebuilt" and any(s in CONTACT_STREAMS for s in self.streams):
            self.painter = PackedContact.from_pack(self.pack)
            if tuple(self.painter.views) != tuple(self.spec.views):
                raise InputError(f"data.pack: its contact geometry is of views {list(self.painter.views)}, its "
                                 f"model's {list(self.spec.views)}")

    def _index(self, of: torch.Tensor, items: list[int]) -> torch.Tensor:
        return of[torch.as_tensor(items, dtype=torch.long, device=of.device)]

    def train_batch(self, items: list[int]) -> ChunkBatch:
        return self.pack.batch(self._index(self.pack.train, items), self.streams)

    def held_batch(self, items: list[int]) -> ChunkBatch:
        return self.pack.batch(self._index(self.pack.heldout, items), self.streams)

    def clips(self, length: int) -> list[list[int]]:
        # the pack's clips index its chunks; the loop draws training positions
        return torch.searchsorted(self.pack.train, self.pack.clips(length)).tolist()

    def rollout_inputs(self, clip_items: list[list[int]], contact_streams: tuple[str, ...]) -> dict:
        if self.painter is None:
            return {}
        index = self._index(self.pack.train, clip_items)  # (B, R) chunks of the pack
        return {"rebuild": lambda r, reference: self.painter.controls(reference, index[:, r], contact_streams)}


__all__ = ["PackSource"]
