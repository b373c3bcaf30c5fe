"""Depth as video streams: ``observation.depth.{cam}``, colour-coded metric depth.

The frames are :meth:`~imac_data.core.depth.DepthCodec.encode_uint8` colours, written with our
own encoder settings (bit-exact RGB by default, :meth:`VideoEncoding.lossless_rgb`); the
codec, encoder settings, depth source and per-camera intrinsics are recorded in
the ``imac`` block's ``depth`` (``meta/imac/info.json``), and each feature's ``info`` block
carries ``imac.depth_codec`` and ``imac.encoding`` too (they survive ``aggregate_datasets``,
which leaves the block out). Decode a loaded frame with
``depth_codec_of(ds.meta).decode(item[key], channel_axis=-3)``.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from imac_data.core.cameras import rescale_intrinsics
from imac_data.core.depth import DepthCodec, _as_numpy_depth
from imac_data.core.metric_depth import resize_depth
from imac_data.dataset.info import read_info
from imac_data.dataset.streams import StreamWriter
from imac_data.dataset.videos import VideoEncoding, encoder_versions
from imac_data.errors import InputError
from imac_data.layout import depth_key, depth_map_key
from imac_data.metadata import unchecked_imac_block

__all__ = ["add_depth_streams", "depth_info_extra", "depth_imac_block", "depth_map_imac_block"]


def depth_info_extra(codec: DepthCodec) -> dict:
    """What each depth feature's ``info`` block carries besides the video info."""
    return {"imac.content": "depth", "imac.depth_codec": codec.to_dict()}


def depth_imac_block(features: Mapping[str, dict], cameras, calibration: Mapping[str, dict], codec: DepthCodec,
                     encoding, source: Mapping[str, Any] | None, existing: Mapping | None = None) -> dict:
    """``{"depth": {...}}`` for ``info["imac"]``: codec, encoding, encoder versions, source,
    and per camera the stream key, size and the intrinsics at that size."""
    streams = dict(existing.get("streams", {})) if existing else {}
    for cam in cameras:
        key = depth_key(cam)
        h, w = features[key]["shape"][:2]
        entry: dict[str, Any] = {"key": key, "height": h, "width": w, "K": None}
        if cam in calibration:
            c = calibration[cam]
            entry["K"] = rescale_intrinsics(np.asarray(c["K"]), (c["height"], c["width"]), (h, w)).tolist()
        streams[cam] = entry
    return {"depth": {
        "codec": codec.to_dict(),
        "encoding": encoding.to_dict(),
        "encoder_versions": encoder_versions(),
        "source": dict(source) if source is not None else {"kind": "unspecified"},
        "streams": streams,
        "decode": "DepthCodec.from_dict(codec).decode(frame, channel_axis=-3) on LeRobot's float (3, H, W) "
                  "colours -> metres, 0 = invalid",
    }}


def depth_map_imac_block(cameras, params, encoding) -> dict:
    """``imac.depth.depth_maps``: where each camera's LeRobot depth map is, its quantiser and
    encoding (the same in each feature's ``info``), and how code 0 reads."""
    return {"keys": {cam: depth_map_key(cam) for cam in cameras}, "quantiser": params.info(),
            "encoding": encoding.to_dict(),
            "decode": "the same metres as observation.depth (size, intrinsics: imac.depth.streams); LeRobot 0.6 "
                      "decodes it itself; code 0 = invalid depth (LeRobot reads it as video.depth_min)"}


def add_depth_streams(root, episodes, *, cameras=None, codec: DepthCodec | None = None, encoding=None,
                      size=None, source: Mapping[str, Any] | None = None, chunk_frames: int = 32,
                      progress: bool = False) -> dict[str, dict]:
    """Store metric depth as the video features ``observation.depth.{cam}`` of the
    LeRobot dataset at ``root``.

    ``episodes`` yields, in episode order, ``{cam: depth}`` with ``depth`` float metres
    ``(T, H, W)`` (numpy or torch; 0 / NaN / inf = invalid, negative = :class:`InputError`),
    ``T`` = the episode's length. Depth must be registered to the camera image (same
    field of view, any resolution of the same aspect ratio). ``cameras`` defaults to the
    dataset's calibrated cameras (``info["imac"]["cameras"]``). ``size``: stored
    ``(h, w)`` for all cameras or ``{cam: (h, w)}`` (default: the input's); depth is
    resized with :func:`~imac_data.core.metric_depth.resize_depth` and the intrinsics recorded for the
    stream are the calibration's rescaled with :func:`~imac_data.core.cameras.rescale_intrinsics`.
    ``codec`` defaults to the ``manipulation`` preset, ``encoding`` to
    :meth:`VideoEncoding.lossless_rgb` (bit-exact colours, chosen by measurement:
    ``benchmarks/depth_fidelity.py``). ``source`` describes where the depth came from (e.g.
    ``DepthSource.describe()``) and is recorded. Returns the feature dicts written.
    """
    from tqdm.auto import tqdm

    root = Path(root)
    info = read_info(root)
    calib = unchecked_imac_block(info).get("cameras", {})
    if cameras is None:
        cameras = sorted(calib)
        if not cameras:
            raise InputError(f"{root}: no calibrated cameras in info.json imac.cameras; pass cameras=[...]")
    cameras = list(cameras)
    if not cameras or len(set(cameras)) != len(cameras):
        raise InputError(f"add_depth_streams: cameras must be distinct names, got {cameras}")
    codec = DepthCodec.preset() if codec is None else codec
    if not isinstance(codec, DepthCodec):
        raise InputError(f"add_depth_streams: codec must be a DepthCodec, got {type(codec).__name__}")
    encoding = VideoEncoding.lossless_rgb() if encoding is None else encoding
    existing = unchecked_imac_block(info).get("depth")
    if existing and existing.get("codec") != codec.to_dict():
        raise InputError(f"{root}: already has depth streams with codec {existing.get('codec')}; "
                         "all depth streams of a dataset must share one codec")
    if isinstance(chunk_frames, bool) or not isinstance(chunk_frames, int) or chunk_frames < 1:
        raise InputError(f"add_depth_streams: chunk_frames must be a positive integer, got {chunk_frames!r}")
    if size is None or isinstance(size, Mapping):
        sizes = dict(size or {})
        unknown = sorted(set(sizes) - set(cameras))
        if unknown:
            raise InputError(f"add_depth_streams: size given for unknown camera(s) {unknown}")
    else:
        sizes = {cam: size for cam in cameras}
    for cam, hw in sizes.items():
        if (not isinstance(hw, (tuple, list)) or len(hw) != 2
                or not all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v > 0 for v in hw)):
            raise InputError(f"add_depth_streams: size for {cam!r} must be (height, width) > 0, got {hw!r}")
    keys = {cam: depth_key(cam) for cam in cameras}

    def frames(ep: int, cam: str, depth):
        name = f"episode {ep} camera {cam!r}"
        depth = _as_numpy_depth(depth, name)
        in_hw = depth.shape[1:]
        if cam in calib:
            ch, cw = calib[cam]["height"], calib[cam]["width"]
            if abs(in_hw[0] / in_hw[1] - ch / cw) > 0.01 * ch / cw:
                raise InputError(f"{name}: depth is {in_hw[0]}x{in_hw[1]} but the camera is calibrated at "
                                 f"{ch}x{cw} (another aspect ratio); depth must be registered to the camera image")
        out_hw = tuple(int(v) for v in sizes.get(cam, in_hw))
        for start in range(0, depth.shape[0], chunk_frames):
            d = resize_depth(depth[start:start + chunk_frames], out_hw, name=name)
            yield codec.encode_uint8(d, name=name)

    extra = depth_info_extra(codec)
    with StreamWriter(root, [keys[c] for c in cameras], encoding, info_extra={keys[c]: extra for c in cameras},
                      imac_info=lambda f: depth_imac_block(f, cameras, calib, codec, encoding, source, existing)
                      ) as writer:
        for ep, item in enumerate(tqdm(episodes, desc="encode depth", unit="ep", disable=not progress)):
            if not isinstance(item, Mapping):
                raise InputError(f"episode {ep}: expected {{camera: depth}}, got {type(item).__name__}")
            if set(item) != set(cameras):
                raise InputError(f"episode {ep}: depth for cameras {sorted(item)}, expected {sorted(cameras)}")
            writer.begin_episode(ep)
            for cam in cameras:
                for batch in frames(ep, cam, item[cam]):
                    writer.write({keys[cam]: batch})
            writer.end_episode()
        return writer.commit()
