"""The typed batch the world model consumes: tensors only, never files.

A :class:`ChunkBatch` is one chunk per sample, laid out as mosaics at the model's resolution,
float in [0, 1]: ``reference (B, 3, 2h, V w)``, ``controls {stream: (B, H, 3, 2h, V w)}``,
``actions (B, H, D)``, ``future (B, H, 3, 2h, V w)`` (None to sample), ``future_valid (B, H)``
and optionally ``state (B, D)``, ``success``, ``episode_index``, ``frame_index`` and
``first_frame (B, 3, 2h, V w)``, the episode's first recorded frame (a model with
``conditioning.first_frame`` needs it).
:mod:`imac_model.data.chunks` builds it from a dataset; a rollout from a generated reference and
controls rebuilt online."""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace

import torch


@dataclass
class ChunkBatch:
    reference: torch.Tensor
    actions: torch.Tensor
    controls: dict[str, torch.Tensor] = field(default_factory=dict)
    future: torch.Tensor | None = None
    future_valid: torch.Tensor | None = None
    state: torch.Tensor | None = None
    success: torch.Tensor | None = None
    episode_index: torch.Tensor | None = None
    frame_index: torch.Tensor | None = None
    first_frame: torch.Tensor | None = None

    def __len__(self) -> int:
        return self.reference.shape[0]

    @property
    def horizon(self) -> int:
        return self.actions.shape[1]

    def valid_mask(self) -> torch.Tensor:
        """``(B, H)`` future-frame validity (all True when not given)."""
        if self.future_valid is None:
            return torch.ones(self.actions.shape[:2], dtype=torch.bool, device=self.actions.device)
        return self.future_valid.bool()

    def to(self, device=None, dtype: torch.dtype | None = None) -> ChunkBatch:
        """Move every tensor to ``device``; floating tensors also to ``dtype`` if given."""

        def move(x):
            if x is None:
                return None
            if isinstance(x, dict):
                return {k: move(v) for k, v in x.items()}
            if dtype is not None and x.is_floating_point():
                return x.to(device=device, dtype=dtype)
            return x.to(device=device)

        return replace(self, **{f.name: move(getattr(self, f.name)) for f in fields(self)})

    def check(self, *, mosaic_hw: tuple[int, int], horizon: int, action_dim: int, streams: tuple[str, ...],
              first_frame: bool = False) -> None:
        """Raise ``ValueError`` naming the field whose shape does not fit the model."""
        B = len(self)

        def expect(name, x, shape):
            if x is not None and tuple(x.shape) != tuple(shape):
                raise ValueError(f"ChunkBatch.{name}: shape {tuple(x.shape)}, the model expects {tuple(shape)}")

        expect("reference", self.reference, (B, 3, *mosaic_hw))
        expect("actions", self.actions, (B, horizon, action_dim))
        expect("future", self.future, (B, horizon, 3, *mosaic_hw))
        expect("future_valid", self.future_valid, (B, horizon))
        if first_frame and self.first_frame is None:
            raise ValueError("ChunkBatch.first_frame: the model is conditioned on the episode's first frame "
                             "(conditioning.first_frame) and the batch has none")
        expect("first_frame", self.first_frame, (B, 3, *mosaic_hw))
        for s in streams:
            if s not in self.controls:
                raise ValueError(f"ChunkBatch.controls: stream {s!r} is missing (has {sorted(self.controls)})")
            expect(f"controls[{s!r}]", self.controls[s], (B, horizon, 3, *mosaic_hw))


def unit_frames(x: torch.Tensor) -> torch.Tensor:
    """Frames as float in [0, 1]: uint8 ones (a chunk cache's) scaled, float ones as they are."""
    return x.float() / 255.0 if x.dtype == torch.uint8 else x.float()


def collate(items: list[dict]) -> ChunkBatch:
    """Stack dataset items (:class:`imac_model.data.chunks.ChunkDataset`; frames as uint8 or
    float) into a float [0, 1] :class:`ChunkBatch`."""

    def frames(key):
        return unit_frames(torch.stack([it[key] for it in items]))

    def opt(key):
        return torch.stack([torch.as_tensor(it[key]) for it in items]) if key in items[0] else None

    streams = [k.split(".", 1)[1] for k in items[0] if k.startswith("control.")]
    return ChunkBatch(
        reference=frames("reference"),
        actions=torch.stack([it["actions"] for it in items]).float(),
        controls={s: frames(f"control.{s}") for s in streams},
        future=frames("future") if "future" in items[0] else None,
        future_valid=opt("future_valid"),
        state=opt("state"),
        success=opt("success"),
        episode_index=opt("episode_index"),
        frame_index=opt("frame_index"),
        first_frame=frames("first_frame") if "first_frame" in items[0] else None,
    )
