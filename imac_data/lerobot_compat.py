"""LeRobot in one place: every LeRobot name that imac_data and imac_model use comes from here.

Supported: LeRobot 0.4.4 (Python 3.11: the whole suite) and 0.5.1 to 0.6.x (Python 3.12+: CI runs the
LeRobot-facing tests under 0.6.1);
``docs/lerobot.md`` has the audit. Names load on first use (``lerobot_compat.LeRobotDataset``):
LeRobot's dataset modules take over a second to import, and most commands never need them.

The first use also makes HF ``datasets`` 4.x (both LeRobot lines pin ``datasets<5``) build a
``Features`` in linear time (:func:`use_linear_features`): its own constructor is quadratic in the
columns, and an iMaC dataset's ``meta/episodes`` table has 300-420 of them (the per-episode stats of
every stream), so each ``LeRobotDataset`` load took seconds; and a ``Features.copy`` without
``copy.deepcopy``'s generic walk, since ``datasets`` copies the whole table's features on every column access.
"""

from __future__ import annotations

import contextlib
import importlib
import inspect
from pathlib import Path
from typing import Any

from imac_data.console import scheduling_kept
from imac_data.errors import InputError

__all__ = ["NAMES", "default_root", "version", "create_dataset", "set_streaming_encoder",
           "close_writers", "video_backend", "convert_v21", "encode_image_dir", "use_linear_features",
           "open_videos_anew", "arrow_cache_in"]

# name -> the modules that define it, newest layout first
NAMES: dict[str, tuple[str, ...]] = {
    "HF_LEROBOT_HOME": ("lerobot.utils.constants",),
    "LeRobotDataset": ("lerobot.datasets.lerobot_dataset",),
    "LeRobotDatasetMetadata": (
        "lerobot.datasets.dataset_metadata",  # >= 0.5.1
        "lerobot.datasets.lerobot_dataset",  # 0.4.4
    ),
    # defined here from 0.5.1; 0.4.4 defines it in datasets.backward_compatibility and imports it here
    "BackwardCompatibilityError": ("lerobot.datasets.utils",),
    "aggregate_datasets": ("lerobot.datasets.aggregate",),
    "aggregate_stats": ("lerobot.datasets.compute_stats",),
    "get_feature_stats": ("lerobot.datasets.compute_stats",),
    "sample_indices": ("lerobot.datasets.compute_stats",),
    "auto_downsample_height_width": ("lerobot.datasets.compute_stats",),
    "DEFAULT_QUANTILES": ("lerobot.datasets.compute_stats",),
    "RunningQuantileStats": ("lerobot.datasets.compute_stats",),
    "serialize_dict": ("lerobot.datasets.utils",),
    "update_chunk_file_indices": ("lerobot.datasets.utils",),
    "decode_video_frames": ("lerobot.datasets.video_utils",),
    "encode_video_frames": ("lerobot.datasets.video_utils",),
    "remove_feature": ("lerobot.datasets.dataset_tools",),
    "delete_episodes": ("lerobot.datasets.dataset_tools",),
    "modify_features": ("lerobot.datasets.dataset_tools",),
    # the motor bus's normalisation, for the benchmarks' simulated LeRobot arms (benchmarks/so101_sim.py)
    "Motor": ("lerobot.motors.motors_bus",),
    "MotorCalibration": ("lerobot.motors.motors_bus",),
    "MotorNormMode": ("lerobot.motors.motors_bus",),
    "MotorsBus": ("lerobot.motors.motors_bus",),
    "convert_dataset": (
        "lerobot.scripts.convert_dataset_v21_to_v30",  # >= 0.5.1
        "lerobot.datasets.v30.convert_dataset_v21_to_v30",  # 0.4.4 and 0.5.0
    ),
}


def _find(name: str) -> tuple[Any, str]:
    """LeRobot's ``name`` and the module it came from (the first of ``NAMES[name]`` that has it)."""
    use_linear_features()
    tried = []
    for module in NAMES[name]:
        try:
            mod = importlib.import_module(module)
        except ModuleNotFoundError as e:
            if e.name is None or not module.startswith(e.name):  # a dependency missing inside LeRobot: say so
                raise
            tried.append(f"{module} (no such module)")
            continue
        if hasattr(mod, name):
            return getattr(mod, name), module
        tried.append(f"{module} (no {name})")
    raise ImportError(f"LeRobot {version()} has no {name}: tried {', '.join(tried)} (docs/lerobot.md lists the "
                      "supported versions)")


def __getattr__(name: str):
    if name in NAMES:
        value = globals()[name] = _find(name)[0]
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


# ---------------------------------------------------------------------------- datasets 4.x, linear

_ORIGINAL_FEATURES_INIT = None


def _linear_features_init(*args, **kwargs):
    """``datasets.Features.__init__`` doing its work once per column. Datasets 4.x's own re-assigns
    every column through ``__setitem__``, which recomputes the decoding flag of *all* columns each
    time (fixed in datasets 5.2). Same values (an old-style ``[feature]`` list becomes
    ``List(feature)``), same flags."""
    from datasets.features.features import List, _visit, require_decoding

    if not args:
        raise TypeError("descriptor '__init__' of 'Features' object needs an argument")
    self, *args = args
    dict.__init__(self, *args, **kwargs)

    def upgrade_old_list(feature):  # datasets < 4 wrote a sequence as [feature]
        if isinstance(feature, list):
            return List(_visit(feature[0], upgrade_old_list))
        return feature

    for name in list(dict.keys(self)):
        dict.__setitem__(self, name, _visit(dict.__getitem__(self, name), upgrade_old_list))
    self._column_requires_decoding = {name: require_decoding(f) for name, f in dict.items(self)}


def _copied(value):
    """A copy of a feature, or of one of its attributes, that shares nothing mutable with it: containers and
    feature objects are copied all the way down; strings, numbers and pyarrow types are immutable and shared."""
    if isinstance(value, dict):
        out = dict.__new__(type(value))  # Features too: its own __init__ and __setitem__ would redo the flags
        dict.update(out, {k: _copied(v) for k, v in dict.items(value)})
    elif isinstance(value, list):
        return [_copied(v) for v in value]
    elif hasattr(value, "__dataclass_fields__") and hasattr(value, "__dict__"):  # Value, List, Video, ...
        out = object.__new__(type(value))
    else:
        return value
    if hasattr(value, "__dict__"):  # Features' decoding flags, a feature's fields and caches
        out.__dict__.update({k: _copied(v) for k, v in value.__dict__.items()})
    return out


def _structural_features_copy(self):
    """``datasets.Features.copy`` without ``copy.deepcopy``'s generic walk (7 ms for a 416-column table, and
    ``Dataset.__getitem__`` of a column copies the table's features each time); equal to the deep copy and
    sharing nothing mutable with the original (tests/test_dataset.py)."""
    return _copied(self)


def use_linear_features() -> bool:
    """Give ``datasets`` 4.x the linear ``Features`` constructor and a structural ``Features.copy``
    (idempotent; tests/test_dataset.py checks both against the originals on a built dataset's schemas).
    False, and nothing changed, for any other ``datasets``."""
    global _ORIGINAL_FEATURES_INIT
    if _ORIGINAL_FEATURES_INIT is not None:
        return True
    import datasets
    from datasets.features.features import Features

    if not str(datasets.__version__).startswith("4."):
        return False
    _ORIGINAL_FEATURES_INIT = Features.__init__
    Features.__init__ = _linear_features_init
    Features.copy = _structural_features_copy
    return True


def original_features_init():
    """``datasets``' own ``Features.__init__`` once replaced (the tests' oracle), else None."""
    return _ORIGINAL_FEATURES_INIT


@contextlib.contextmanager
def arrow_cache_in(folder: Path):
    """LeRobot's parquet loads keep their Arrow copies in ``folder`` inside the block, not in the user's
    ``datasets`` cache (``~/.cache/huggingface/datasets``): for datasets about to be deleted, such as a build's
    shards, whose copies would be left there for good (docs/building.md, "Disk")."""
    import datasets.config  # here, not at the top: `datasets` takes about a second to import (module docstring)

    before = datasets.config.HF_DATASETS_CACHE  # read by every builder as it starts, so a swap takes effect
    datasets.config.HF_DATASETS_CACHE = Path(folder)
    try:
        yield
    finally:
        datasets.config.HF_DATASETS_CACHE = before


def version() -> str:
    """The installed LeRobot's version string."""
    from importlib.metadata import version as dist_version

    return dist_version("lerobot")


def _at_least(v: str, major: int, minor: int) -> bool:
    parts = [int(p) for p in v.split(".")[:2] if p.isdigit()]
    return tuple(parts) >= (major, minor)


def default_root(repo_id: str) -> Path:
    """Where LeRobot looks for ``repo_id``: ``$HF_LEROBOT_HOME/<repo_id>``."""
    return Path(_find("HF_LEROBOT_HOME")[0]) / repo_id


def create_dataset(repo_id: str, *, fps: int, features: dict, root: Path, robot_type: str | None, encoding):
    """An empty ``LeRobotDataset`` for writing, its camera encoder set to ``encoding`` (a
    :class:`~imac_data.dataset.videos.VideoEncoding`)."""
    cls = _find("LeRobotDataset")[0]
    kwargs: dict[str, Any] = dict(repo_id=repo_id, fps=int(fps), features=features, root=root,
                                  robot_type=robot_type, use_videos=True)
    params = inspect.signature(cls.create).parameters
    if "vcodec" in params:  # 0.4.4
        kwargs["vcodec"] = encoding.codec
    elif "rgb_encoder" in params:  # >= 0.5.1: the settings go into the first episode's video info
        config = importlib.import_module("lerobot.configs.video").RGBEncoderConfig
        kwargs["rgb_encoder"] = config(vcodec=encoding.codec, pix_fmt=encoding.pix_fmt, g=encoding.gop,
                                       crf=encoding.crf, preset=encoding.preset)
    return cls.create(**kwargs)


def _writer_of(ds):
    """The object that holds LeRobot's streaming-encoder slot and writers: the dataset
    (0.4.4) or its ``DatasetWriter`` (>= 0.5.1)."""
    if hasattr(ds, "_streaming_encoder"):  # 0.4.4
        return ds
    writer = getattr(ds, "writer", None)
    if writer is not None and hasattr(writer, "_streaming_encoder"):  # >= 0.5.1
        return writer
    raise RuntimeError(f"LeRobot {version()}: the dataset has no streaming-encoder slot (docs/lerobot.md)")


def set_streaming_encoder(ds, encoder) -> None:
    """Plug ``encoder`` into LeRobot's streaming-encoder slot (``add_frame`` feeds it)."""
    _writer_of(ds)._streaming_encoder = encoder


def close_writers(ds) -> None:
    """Stop LeRobot's writers of a dataset being written, without finishing it, so nothing
    writes into its root after the caller removes it."""
    holder = _writer_of(ds)
    if holder is ds:  # 0.4.4
        ds._close_writer()
    else:  # >= 0.5.1; its finalize() would run again at garbage collection
        holder.cancel_pending_videos()
        holder.close_writer()
        holder._finalized = True
    ds.meta._close_writer()


def video_backend(ds) -> str | None:
    """The video decoder a ``LeRobotDataset`` reads with (public in 0.4.4, private from 0.5.1)."""
    return getattr(ds, "video_backend", None) or getattr(ds, "_video_backend", None)


def open_videos_anew(_worker: int | None = None) -> None:
    """Give this process its own open video files: a DataLoader worker's ``worker_init_fn``.

    LeRobot (0.4.4 to 0.6.x) keeps each video's open file and decoder in a module-level cache
    (``video_utils._default_decoder_cache``); a forked worker inherits it, and reading through it moves the
    file offset the two processes share, which garbles the stream in both."""
    video_utils = importlib.import_module("lerobot.datasets.video_utils")
    video_utils._default_decoder_cache = type(video_utils._default_decoder_cache)()


def convert_v21(dataset_root: Path, repo_id: str) -> str:
    """Convert the v2.1 dataset at ``dataset_root`` to v3.0 in place with LeRobot's own
    converter; returns the converter's module (for the provenance record)."""
    convert, module = _find("convert_dataset")
    # the converter's ``root``: the dataset itself from 0.5.0, the folder that holds ``<repo_id>`` before
    root = dataset_root
    if not _at_least(version(), 0, 5):
        root = dataset_root.parents[len(Path(repo_id).parts) - 1]
        if root / repo_id != dataset_root:
            raise InputError(f"{dataset_root}: LeRobot {version()} converts <root>/{repo_id} only")
    convert(repo_id, root=str(root), push_to_hub=False, force_conversion=True)
    return module


def encode_image_dir(imgs_dir: Path, video_path: Path, fps: int, *, vcodec: str, overwrite: bool = False) -> None:
    """LeRobot's own PNG-folder encoder (``encode_video_frames``) with codec ``vcodec`` and LeRobot's
    other defaults: 0.4.4 takes ``vcodec=``, 0.5.1 on an ``RGBEncoderConfig`` (``video_encoder=``)."""
    encode = _find("encode_video_frames")[0]
    params = inspect.signature(encode).parameters
    with scheduling_kept():  # SVT-AV1 leaves a root caller real-time
        if "vcodec" in params:  # 0.4.4
            encode(imgs_dir, video_path, fps, vcodec=vcodec, overwrite=overwrite)
        else:  # >= 0.5.1
            config = importlib.import_module("lerobot.configs.video").RGBEncoderConfig
            encode(imgs_dir, video_path, fps, video_encoder=config(vcodec=vcodec), overwrite=overwrite)
