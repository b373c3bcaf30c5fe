"""The one place in ``imac_model`` that reads an imac dataset's metadata (``meta/info.json``):
the contact chunk and its reference rule, the depth codec, the cameras in view order, and the
feature keys of each stream (``docs/dataset-format.md``). A change of that block's layout is
adapted here."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from imac_data.core.cameras import Camera
from imac_data.core.depth import depth_codec_of
from imac_data.errors import InputError
from imac_data.layout import ACTION, IMAGE_PREFIX, STATE, SUCCESS_COLUMN, control_key, depth_key, image_key

__all__ = ["ACTION", "STATE", "SUCCESS_COLUMN", "contact_chunk_size", "reference_rule", "depth_codec", "cameras",
           "camera_names", "stream_key", "missing_features", "feature_dim", "fps"]


def _imac(info: Mapping[str, Any]) -> Mapping[str, Any]:
    block = info.get("imac") if isinstance(info, Mapping) else None
    if not isinstance(block, Mapping):
        raise InputError("meta/info.json has no 'imac' block: this dataset was not built by imac_data "
                         "(imac build)")
    return block


def contact_chunk_size(info: Mapping[str, Any]) -> int | None:
    """H of the dataset's contact images (None when it has none)."""
    contact = _imac(info).get("contact")
    return None if not contact else int(contact["chunk_size"])


def reference_rule(info: Mapping[str, Any]) -> str | None:
    contact = _imac(info).get("contact")
    return None if not contact else contact.get("reference_rule")


def depth_codec(info: Mapping[str, Any]):
    """The :class:`imac_data.core.depth.DepthCodec` of the depth streams."""
    return depth_codec_of(info)


def cameras(info: Mapping[str, Any]) -> dict:
    """``{name: imac_data.core.cameras.Camera}`` at the cameras' recorded resolution."""
    cams = _imac(info).get("cameras")
    if not cams:
        raise InputError("meta/info.json imac.cameras: missing (the dataset records no camera calibration)")
    return {name: Camera(name=name, **c) for name, c in cams.items()}


def camera_names(info: Mapping[str, Any]) -> tuple[str, ...]:
    """Camera names in view order: fixed (head) cameras first, then mounted ones with 'left'
    before 'right' (each group by name)."""
    cams = _imac(info).get("cameras")
    if cams:
        def key(item):
            name, c = item
            mounted = "link" in c
            side = 0 if "left" in name else 1 if "right" in name else 2
            return (mounted, side, name)

        return tuple(name for name, _ in sorted(cams.items(), key=key))
    # no calibration block: derive from the RGB features (same rule, by name only)
    names = [k.removeprefix(IMAGE_PREFIX) for k in info.get("features", {}) if k.startswith(IMAGE_PREFIX)]
    return tuple(sorted(names, key=lambda n: ("wrist" in n, 0 if "left" in n else 1 if "right" in n else 2, n)))


def stream_key(stream: str, camera: str) -> str:
    """Feature key of a stream for one camera: ``rgb``, ``depth`` or a control stream
    (``motion``, ``contact_s2g``, ``contact_r2s``)."""
    if stream == "rgb":
        return image_key(camera)
    if stream == "depth":
        return depth_key(camera)
    return control_key(stream, camera)


def missing_features(info: Mapping[str, Any], streams: Sequence[str], views: Sequence[str]) -> list[str]:
    """Feature keys the model needs (``streams`` x ``views``) that the dataset lacks."""
    features = info.get("features", {})
    return [stream_key(s, v) for s in streams for v in views if stream_key(s, v) not in features]


def feature_dim(info: Mapping[str, Any], key: str) -> int:
    try:
        shape = info["features"][key]["shape"]
    except KeyError:
        raise InputError(f"meta/info.json: the dataset has no feature {key!r}") from None
    return int(shape[0])


def fps(info: Mapping[str, Any]) -> float:
    return float(info["fps"])
