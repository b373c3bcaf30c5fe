"""Pictures of a sampled chunk: per future frame the generated mosaic, the recorded one and the
control images the model was given, labelled; as an mp4 or a still (first, middle and last
future frame)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch

from imac_data.dataset.videos import VideoEncoding, encode_video
from imac_model.data import mosaic
from imac_model.pipelines.sampling import ChunkSample

__all__ = ["label", "frame_panel", "write_mp4", "write_png"]

LABEL_COLOUR = (255, 255, 255)


def _u8(x: torch.Tensor) -> np.ndarray:
    """(3, H, W) in [0, 1] -> (H, W, 3) uint8."""
    return (x.clamp(0, 1) * 255).round().byte().permute(1, 2, 0).numpy()


def label(img: np.ndarray, text: str, *, scale: float | None = None) -> np.ndarray:
    """``text`` written on the top-left of ``img`` (H, W, 3) uint8, white with a black outline.
    The font grows with the image height (``scale``: fixed instead) and shrinks to fit the
    width (a one-view mosaic is narrow); below a legible size the text is cut with '~'."""
    font, img = cv2.FONT_HERSHEY_SIMPLEX, np.ascontiguousarray(img)
    scale = scale or max(img.shape[0] / 400, 0.35)
    room = img.shape[1] - 8
    width = cv2.getTextSize(text, font, scale, 1)[0][0]
    if width > room:
        scale = max(0.95 * scale * room / width, 0.25)  # text width is not quite linear in the scale
        while len(text) > 1 and cv2.getTextSize(text, font, scale, 1)[0][0] > room:
            text = text[:-2] + "~"
    y = 4 + cv2.getTextSize("Ag", font, scale, 1)[0][1]
    cv2.putText(img, text, (4, y), font, scale, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(img, text, (4, y), font, scale, LABEL_COLOUR, 1, cv2.LINE_AA)
    return img


def _cell(x: torch.Tensor, text: str, scale: int) -> np.ndarray:
    """A panel enlarged ``scale`` times (nearest pixel), then labelled at that size."""
    img = _u8(x)
    if scale > 1:
        img = img.repeat(scale, axis=0).repeat(scale, axis=1)
    return label(img, text)


def _controls_block(controls: dict[str, torch.Tensor], k: int, height: int, scale: int) -> np.ndarray | None:
    if not controls:
        return None
    rows = [_cell(torch.cat(c[k].unbind(0), dim=-1), s, scale) for s, c in controls.items()]
    block = np.concatenate(rows, axis=0)
    if block.shape[0] < height:
        block = np.concatenate([block, np.zeros((height - block.shape[0], *block.shape[1:]), np.uint8)], axis=0)
    return block


def frame_panel(s: ChunkSample, k: int, scale: int = 1) -> np.ndarray:
    """One video frame: generated | recorded | controls of future frame ``k``, enlarged ``scale`` times."""
    gen = _cell(s.generated[k], f"generated t+{k + 1}", scale)
    rec = _cell(s.recorded[k], "recorded" + ("" if s.valid[k] else " (padded)"), scale)
    parts = [gen, rec]
    ctrl = _controls_block(s.controls, k, gen.shape[0], scale)
    height = max(p.shape[0] for p in parts + ([ctrl] if ctrl is not None else []))
    if ctrl is not None:
        parts.append(ctrl)
    parts = [np.concatenate([p, np.zeros((height - p.shape[0], *p.shape[1:]), np.uint8)]) if p.shape[0] < height
             else p for p in parts]
    return np.concatenate(parts, axis=1)


def _even(img: np.ndarray) -> np.ndarray:
    return img[: img.shape[0] // 2 * 2, : img.shape[1] // 2 * 2]  # yuv420p needs even sides


def write_mp4(s: ChunkSample, path: Path, fps: float, scale: int = 2) -> Path:
    frames = np.stack([_even(frame_panel(s, k, scale)) for k in range(len(s.generated))])
    return encode_video(path, frames, fps=max(int(round(fps)), 1),
                        encoding=VideoEncoding(codec="libx264", pix_fmt="yuv420p", crf=18, qp=None))


def write_png(s: ChunkSample, path: Path, scale: int = 2) -> Path:
    H = len(s.generated)
    rows = []
    for k in sorted({0, H // 2 - 1, H - 1}):
        row = [_cell(s.generated[k], f"generated t+{k + 1}", scale), _cell(s.recorded[k], f"recorded t+{k + 1}", scale)]
        if "motion" in s.controls:
            row.append(_cell(mosaic.controls(s.controls["motion"][k]), "motion image", scale))
        rows.append(np.concatenate(row, axis=1))
    img = _even(np.concatenate(rows, axis=0))
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_PNG_COMPRESSION, 9])
    return path
