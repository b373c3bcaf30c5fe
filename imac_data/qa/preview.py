"""Preview: every stream of one built episode side by side, as one mp4 (``imac qa preview``).

The episode is read through ``LeRobotDataset`` (what a training job sees); each frame is a
mosaic with one row per stream kind (rgb, depth decoded to metres and coloured, motion, r2s,
s2g) and one column per camera, labelled. Frames are read, composed and encoded one at a time,
and the file is renamed into place when complete."""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from imac_data import lerobot_compat as lr
from imac_data.core.depth import depth_codec_of
from imac_data.dataset.videos import VideoEncoding, encode_video
from imac_data.errors import InputError
from imac_data.layout import DEPTH_PREFIX, IMAGE_PREFIX, MOTION, R2S, S2G, info_path
from imac_data.metadata import dataset_info, unchecked_imac_block

__all__ = ["ROWS", "PreviewLayout", "preview_layout", "compose", "write_preview"]

# (row label, feature-key prefix), top to bottom.
ROWS = (("rgb", IMAGE_PREFIX), ("depth", DEPTH_PREFIX), ("motion", MOTION + "."), ("contact r2s", R2S + "."),
        ("contact s2g", S2G + "."))
LABEL_PX = 14  # height of the label strip above each tile


@dataclass(frozen=True)
class PreviewLayout:
    cameras: tuple[str, ...]  # columns
    rows: tuple[tuple[str, str], ...]  # (label, prefix) of the kinds present
    tile_hw: tuple[int, int]  # every tile's image size

    @property
    def size_hw(self) -> tuple[int, int]:
        """Mosaic size, rounded up to even sides (yuv420p)."""
        h = LABEL_PX + len(self.rows) * (self.tile_hw[0] + LABEL_PX)
        w = len(self.cameras) * self.tile_hw[1]
        return h + h % 2, w + w % 2


def preview_layout(info: dict) -> PreviewLayout:
    """The mosaic of a dataset, from its ``meta/info.json`` dict (:func:`imac_data.metadata.dataset_info`)."""
    features = info.get("features", {})
    videos = [k for k, f in features.items() if f.get("dtype") == "video"]
    cameras = tuple(k[len(ROWS[0][1]):] for k in videos if k.startswith(ROWS[0][1]))
    if not cameras:
        raise InputError("the dataset has no observation.images.* video streams to preview")
    rows = tuple((label, prefix) for label, prefix in ROWS
                 if any(f"{prefix}{cam}" in features for cam in cameras))
    augment = unchecked_imac_block(info).get("augment", {})
    if "height" in augment and "width" in augment:
        tile_hw = (int(augment["height"]), int(augment["width"]))
    else:  # no added streams: the first camera's own size
        tile_hw = tuple(int(s) for s in features[f"{ROWS[0][1]}{cameras[0]}"]["shape"][:2])
    return PreviewLayout(cameras, rows, tile_hw)


def _to_uint8_hwc(frame) -> np.ndarray:
    """LeRobot's float ``(3, H, W)`` in [0, 1] -> uint8 ``(H, W, 3)``."""
    x = frame.detach().cpu().numpy() if hasattr(frame, "detach") else np.asarray(frame)
    return np.clip(np.rint(np.moveaxis(x, 0, -1) * 255.0), 0, 255).astype(np.uint8)


def _depth_tile(frame, codec, depth_max: float) -> np.ndarray:
    metres = codec.decode(frame, channel_axis=-3)
    metres = metres.detach().cpu().numpy() if hasattr(metres, "detach") else np.asarray(metres)
    levels = np.clip(metres / depth_max * 255.0, 0, 255).astype(np.uint8)
    rgb = cv2.cvtColor(cv2.applyColorMap(levels, cv2.COLORMAP_TURBO), cv2.COLOR_BGR2RGB)
    rgb[~(metres > 0)] = 0  # invalid depth stays black
    return rgb


def _label(img: np.ndarray, text: str, x: int, y: int, width: int) -> None:
    """White text in the label strip whose top-left corner is (x, y), cut to ``width`` pixels."""
    font, scale = cv2.FONT_HERSHEY_SIMPLEX, 0.35
    while text and cv2.getTextSize(text, font, scale, 1)[0][0] > width - 4:
        text = text[:-1]
    cv2.putText(img, text, (x + 2, y + LABEL_PX - 4), font, scale, (255, 255, 255), 1, cv2.LINE_AA)


def compose(item: dict, layout: PreviewLayout, *, codec=None, depth_max: float = 2.0) -> np.ndarray:
    """One mosaic frame ``(H, W, 3)`` uint8 from one ``LeRobotDataset`` item: a header strip
    with the camera names, then per row a strip with the stream kind and the row's tiles."""
    th, tw = layout.tile_hw
    out = np.zeros((*layout.size_hw, 3), dtype=np.uint8)
    for c, cam in enumerate(layout.cameras):
        _label(out, cam, c * tw, 0, tw)
    for r, (label, prefix) in enumerate(layout.rows):
        y = LABEL_PX + r * (th + LABEL_PX)
        text = f"{label} ({prefix}*)" + (f", 0-{depth_max:g} m" if prefix == DEPTH_PREFIX else "")
        _label(out, text, 0, y, out.shape[1])
        for c, cam in enumerate(layout.cameras):
            key = f"{prefix}{cam}"
            if key not in item:
                continue
            tile = _depth_tile(item[key], codec, depth_max) if prefix == DEPTH_PREFIX else _to_uint8_hwc(item[key])
            if tile.shape[:2] != (th, tw):
                tile = cv2.resize(tile, (tw, th), interpolation=cv2.INTER_AREA)
            out[y + LABEL_PX:y + LABEL_PX + th, c * tw:(c + 1) * tw] = tile
    return out


def _read_info(root: Path) -> dict:
    path = info_path(root)
    if not path.is_file():
        raise InputError(f"{root}: not a LeRobot dataset (no meta/info.json)")
    return dataset_info(root)


def write_preview(root: str | Path, episode: int, out: str | Path | None = None, *, depth_max: float = 2.0,
                  overwrite: bool = False, progress: bool = True) -> Path:
    """Write the mosaic mp4 of episode ``episode`` of the dataset at ``root``; returns its path
    (default ``./{root name}_episode_{episode}.mp4``)."""
    root = Path(root)
    info = _read_info(root)
    total = int(info.get("total_episodes", 0))
    if not 0 <= episode < total:
        raise InputError(f"{root}: episode {episode} does not exist (the dataset has episodes 0..{total - 1})")
    if not depth_max > 0:
        raise InputError(f"--depth-max must be > 0 metres, got {depth_max}")
    out = Path(out) if out is not None else Path.cwd() / f"{root.name}_episode_{episode}.mp4"
    if out.suffix.lower() != ".mp4":
        raise InputError(f"{out}: the preview is an mp4; give a path ending in .mp4")
    if out.exists() and not overwrite:
        raise InputError(f"{out} already exists (pass --overwrite to replace it)")
    if out.resolve().is_relative_to(root.resolve()):
        raise InputError(f"{out}: write the preview outside the dataset {root}")
    layout = preview_layout(info)
    codec = depth_codec_of(info) if any(p == DEPTH_PREFIX for _, p in layout.rows) else None

    ds = lr.LeRobotDataset(f"local/{root.name}", root=root, episodes=[episode])

    def frames() -> Iterator[np.ndarray]:
        from tqdm import tqdm

        for i in tqdm(range(len(ds)), desc=f"preview episode {episode}", disable=not progress, unit="frame"):
            yield compose(ds[i], layout, codec=codec, depth_max=depth_max)

    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(suffix=".mp4", prefix=f".{out.stem}.", dir=out.parent)
    os.close(fd)
    try:
        encode_video(tmp, frames(), fps=int(round(info["fps"])),
                     encoding=VideoEncoding(codec="libx264", pix_fmt="yuv420p", crf=20, qp=None, preset="veryfast"))
        os.replace(tmp, out)
    finally:
        Path(tmp).unlink(missing_ok=True)
    return out
