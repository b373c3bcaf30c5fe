"""imac_model: the action-conditioned video world model (iMaC), trained on imac datasets.

Layers, as diffusers keeps them apart (``docs/architecture.md``): ``config`` -> ``data``
(LeRobot chunks, the six-panel mosaic) -> ``models`` (backbones, control injection, the
world model, checkpoints) and ``schedulers`` (flow matching) -> ``pipelines`` (rollouts,
controls rebuilt online, sampling) -> ``training`` -> ``evaluate`` -> ``experiments`` ->
``cli``.

The public surface is below; importing this package loads none of it until it is used.
"""

import importlib

__version__ = "0.1.0"

_API = {  # name -> the module that defines it
    "RunConfig": "imac_model.config",
    "ModelSpec": "imac_model.config",
    "load_run_config": "imac_model.config",
    "ChunkBatch": "imac_model.data.batch",
    "ChunkDataset": "imac_model.data.chunks",
    "WorldModel": "imac_model.models.world_model",
    "load_world_model": "imac_model.models.checkpoint",
    "OnlineControls": "imac_model.pipelines.online_controls",
    "sample_rollout": "imac_model.pipelines.rollout",
    "train": "imac_model.training.train",
}

__all__ = ["__version__", *_API]


def __getattr__(name: str):
    if name in _API:
        return getattr(importlib.import_module(_API[name]), name)
    raise AttributeError(f"module 'imac_model' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(__all__)
