"""The tensor pack: a run's decoded training and held-out chunks in one LZMA-compressed ``.npz`` with the
model's spec, what the trainer reads on a machine that has torch and numpy and nothing else of ours
(the GPU machine: no LeRobot, MuJoCo, Open3D or diffusers). The control rows the mosaic duplicates
are stored once, and so is a reference frame that is the previous chunk's last future frame.
:func:`export_pack` writes one from ``ChunkDataset`` items; :class:`Pack` reads it onto a device."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np
import torch

from imac_data.errors import InputError
from imac_model.config import ModelSpec, parse
from imac_model.data.batch import ChunkBatch

SPEC_KEY = "spec_json"
REFERENCE_FOLLOWS = "reference_follows"  # see _shared_references
GEOMETRY_KEY = "geometry_json"  # the contact geometry's settings (imac_model.pipelines.packed_contact)


def pack_arrays(items: list[dict], held_out: list[bool], spec: ModelSpec,
                geometry: dict[str, np.ndarray] | None = None) -> dict[str, np.ndarray]:
    """Chunk items (``ChunkDataset`` items, every control stream) -> a pack's arrays; ``held_out``
    flags the held-out episodes' items. Controls keep their top row (the mosaic duplicates it).
    ``geometry``: the items' contact geometry (:mod:`imac_model.pipelines.packed_contact`), so the
    pack's trainer can rebuild contact images from its own references."""
    h = spec.view_height
    arrays = {
        "reference": np.stack([it["reference"].numpy() for it in items]),
        "future": np.stack([it["future"].numpy() for it in items]),
        "future_valid": np.stack([it["future_valid"].numpy() for it in items]),
        "actions": np.stack([it["actions"].numpy() for it in items]).astype(np.float32),
        "episode_index": np.array([int(it["episode_index"]) for it in items]),
        "held_out": np.asarray(held_out, dtype=bool),
        SPEC_KEY: np.array(json.dumps(spec.to_dict())),
    }
    for key in [k for k in items[0] if k.startswith("control.")]:  # every stream the items carry, derived ones too
        arrays[key] = np.stack([it[key][:, :, :h].numpy() for it in items])
    arrays.update(geometry or {})
    return _shared_references(arrays)


def _shared_references(arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Keep only the references that are not the previous chunk's last future frame (a chunk of an
    episode usually starts where the one before it ended): ``reference_follows`` flags the others,
    which :class:`Pack` takes back from ``future``. At 4 chunks an episode three quarters of the references
    go: 1.6 MB of a loan's 64 MiB."""
    ref, future, episode = arrays["reference"], arrays["future"], arrays["episode_index"]
    follows = np.zeros(len(ref), dtype=bool)
    if len(ref) > 1:
        follows[1:] = (episode[1:] == episode[:-1]) & (ref[1:] == future[:-1, -1]).reshape(len(ref) - 1, -1).all(1)
    return {**arrays, "reference": ref[~follows], REFERENCE_FOLLOWS: follows}


def _references(arrays: dict[str, np.ndarray]) -> np.ndarray:
    """Every chunk's reference frame back from :func:`_shared_references`' form (or a pack without it)."""
    if REFERENCE_FOLLOWS not in arrays:
        return arrays["reference"]
    follows = np.asarray(arrays[REFERENCE_FOLLOWS], dtype=bool)
    stored, future = arrays["reference"], arrays["future"]
    if len(stored) != int((~follows).sum()) or (len(follows) and follows[0]):
        raise InputError(f"pack: {len(stored)} stored reference frames for {int((~follows).sum())} chunks that "
                         f"need one; the pack is damaged")
    ref = np.empty((len(follows), *stored.shape[1:]), dtype=stored.dtype)
    ref[~follows] = stored
    ref[follows] = future[np.flatnonzero(follows) - 1, -1]
    return ref


def export_pack(items: list[dict], held_out: list[bool], spec: ModelSpec, path: str | Path,
                geometry: dict[str, np.ndarray] | None = None) -> Path:
    """:func:`pack_arrays` written as one ``.npz``, atomically."""
    return write_pack(pack_arrays(items, held_out, spec, geometry), path)


def write_pack(arrays: dict[str, np.ndarray], path: str | Path) -> Path:
    """A pack's arrays as one ``.npz`` whose members are LZMA-compressed, written atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp.npz")
    # an .npz whose members are LZMA-compressed: about 0.6 of deflate's size, which decides how many rollouts a GPU
    # loan's 64 MiB carry holds; np.load reads it as any .npz
    with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_LZMA) as zf:
        for name, array in arrays.items():
            with zf.open(f"{name}.npy", "w", force_zip64=True) as f:
                np.lib.format.write_array(f, np.asanyarray(array), allow_pickle=False)
    tmp.replace(path)
    return path


class Pack:
    """A pack's tensors on one device (uint8 frames, float actions) and its spec."""

    def __init__(self, path: str | Path, device: torch.device | str = "cpu"):
        with np.load(path) as data:
            self._load({k: data[k] for k in data.files}, device)

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], device: torch.device | str = "cpu") -> Pack:
        """A pack held in memory (:func:`pack_arrays`), never written."""
        pack = cls.__new__(cls)
        pack._load(arrays, device)
        return pack

    def _load(self, arrays: dict[str, np.ndarray], device) -> None:
        self.spec = parse(ModelSpec, json.loads(str(arrays[SPEC_KEY])), "")
        arrays = {**arrays, "reference": _references(arrays)}
        self.tensors = {k: torch.from_numpy(np.asarray(v)).to(device) for k, v in arrays.items()
                        if k not in (SPEC_KEY, REFERENCE_FOLLOWS, GEOMETRY_KEY)}
        # the contact geometry's settings (packs written before 2026-11-29 have none)
        self.geometry = json.loads(str(arrays[GEOMETRY_KEY])) if GEOMETRY_KEY in arrays else None
        held = self.tensors.pop("held_out").bool()
        self.train = torch.nonzero(~held).flatten()
        self.heldout = torch.nonzero(held).flatten()
        # each chunk's episode's first chunk (the pack keeps an episode's chunks together, in time order)
        episode = self.tensors["episode_index"]
        begins = torch.ones_like(episode, dtype=torch.bool)
        begins[1:] = episode[1:] != episode[:-1]
        position = torch.arange(len(episode), device=episode.device)
        self.first_chunk = torch.cummax(torch.where(begins, position, 0), dim=0).values

    def to(self, device: torch.device | str) -> Pack:
        """The pack's tensors moved to ``device`` (in place; returns the pack)."""
        self.tensors = {k: v.to(device) for k, v in self.tensors.items()}
        self.train, self.heldout, self.first_chunk = (t.to(device) for t in (self.train, self.heldout, self.first_chunk))
        return self

    def clips(self, length: int) -> torch.Tensor:
        """``(n, length)`` indices of every run of ``length`` consecutive training chunks of one
        episode (the pack keeps each episode's chunks in time order, as ``ChunkDataset.clips``)."""
        episode = self.tensors["episode_index"][self.train]
        starts = torch.arange(max(len(self.train) - length + 1, 0), device=episode.device)
        same = torch.stack([episode[starts + r] == episode[starts] for r in range(length)]).all(dim=0)
        first = starts[same]
        return self.train[first[:, None] + torch.arange(length, device=first.device)]

    def batch(self, index: torch.Tensor, streams: tuple[str, ...]) -> ChunkBatch:
        """Float mosaics in [0, 1], controls duplicated back into both rows; each chunk's
        episode's first frame."""
        t = self.tensors
        controls = {s: torch.cat([t[f"control.{s}"][index]] * 2, dim=-2).float() / 255.0 for s in streams}
        return ChunkBatch(reference=t["reference"][index].float() / 255.0, actions=t["actions"][index],
                          controls=controls, future=t["future"][index].float() / 255.0,
                          future_valid=t["future_valid"][index],
                          first_frame=t["reference"][self.first_chunk[index]].float() / 255.0)


__all__ = ["GEOMETRY_KEY", "Pack", "SPEC_KEY", "export_pack", "pack_arrays", "write_pack"]
