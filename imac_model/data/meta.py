"""What ``imac_model`` reads of an imac dataset's metadata (``meta/info.json`` and the ``imac``
block, ``meta/imac/info.json``): the contact chunk and its reference rule, the depth codec, the
cameras in view order, and the feature keys of each stream (``docs/dataset-format.md``). Every
function takes ``ds.meta``, the dataset's root or its :func:`imac_data.metadata.dataset_info` dict,
and reads the ``imac`` block through :mod:`imac_data.metadata`, the one reader; the augment
settings are :meth:`imac_data.recipes.AugmentSettings.from_info`."""

from __future__ import annotations

from collections.abc import Sequence

from imac_data.core.cameras import Camera
from imac_data.core.depth import depth_codec_of
from imac_data.errors import InputError
from imac_data.layout import ACTION, IMAGE_PREFIX, STATE, SUCCESS_COLUMN, control_key, depth_key, image_key
from imac_data.metadata import dataset_info, imac_block

__all__ = ["ACTION", "STATE", "SUCCESS_COLUMN", "contact_chunk_size", "reference_rule", "depth_codec", "cameras",
           "camera_names", "stream_key", "missing_features", "feature_dim", "fps", "state_names", "depth_entry"]


def contact_chunk_size(meta) -> int | None:
    """H of the dataset's contact images (None when it has none)."""
    contact = imac_block(meta).get("contact")
    return None if not contact else int(contact["chunk_size"])


def reference_rule(meta) -> str | None:
    contact = imac_block(meta).get("contact")
    return None if not contact else contact.get("reference_rule")


def depth_codec(meta):
    """The :class:`imac_data.core.depth.DepthCodec` of the depth streams."""
    return depth_codec_of(meta)


def cameras(meta) -> dict:
    """``{name: imac_data.core.cameras.Camera}`` at the cameras' recorded resolution."""
    cams = imac_block(meta).get("cameras")
    if not cams:
        raise InputError("meta/info.json imac.cameras: missing (the dataset records no camera calibration)")
    return {name: Camera(name=name, **c) for name, c in cams.items()}


def camera_names(meta) -> tuple[str, ...]:
    """Camera names in view order: fixed (head) cameras first, then mounted ones with 'left'
    before 'right' (each group by name)."""
    info = dataset_info(meta)
    cams = imac_block(info).get("cameras")
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


def missing_features(meta, streams: Sequence[str], views: Sequence[str]) -> list[str]:
    """Feature keys the model needs (``streams`` x ``views``) that the dataset lacks."""
    features = dataset_info(meta).get("features", {})
    return [stream_key(s, v) for s in streams for v in views if stream_key(s, v) not in features]


def feature_dim(meta, key: str) -> int:
    try:
        shape = dataset_info(meta)["features"][key]["shape"]
    except KeyError:
        raise InputError(f"meta/info.json: the dataset has no feature {key!r}") from None
    return int(shape[0])


def fps(meta) -> float:
    return float(dataset_info(meta)["fps"])


def state_names(meta) -> tuple[str, ...] | None:
    """The joint vector's entry names the robot block records (None when it records none)."""
    names = imac_block(meta, require=("robot",))["robot"].get("state_names")
    return None if not names else tuple(names)


def depth_entry(meta) -> dict:
    """``{"depth": ...}``: the dataset's depth entry (codec and streams) to copy into a dataset
    whose depth rows use the same codec; ``{}`` when it has none."""
    block = imac_block(meta)
    return {"depth": block["depth"]} if "depth" in block else {}
