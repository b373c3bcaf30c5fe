"""imac_data: LeRobot datasets with action-derived control videos (motion, depth, contact).

The layers, data flowing one way (``docs/architecture.md``): ``core`` (arrays and tensors:
cameras, robot, render, rig, depth codec, contact) -> ``sources`` (episodes from HDF5, LeRobot
datasets, the simulator; depth sources) -> ``augment`` (the per-chunk pipeline) -> ``dataset``
(every on-disk edit, validation) -> ``build`` (the staged flow) -> ``cli``.

The public surface is below; importing this package loads none of it until it is used.
"""

import importlib

__version__ = "0.1.0"

_API = {  # name -> the module that defines it
    "Rig": "imac_data.core.rig",
    "DepthCodec": "imac_data.core.depth",
    "depth_codec_of": "imac_data.core.depth",
    "chunk_timestamps": "imac_data.metadata",
    "stream_keys": "imac_data.layout",
    "load_recipe": "imac_data.recipes",
    "Recipe": "imac_data.recipes",
    "BuildRequest": "imac_data.build.staging",
    "build_dataset": "imac_data.build.flow",
    "validate_dataset": "imac_data.dataset.validate",
}

__all__ = ["__version__", *_API]


def __getattr__(name: str):
    if name in _API:
        return getattr(importlib.import_module(_API[name]), name)
    raise AttributeError(f"module 'imac_data' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(__all__)
