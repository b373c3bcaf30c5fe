"""Where the trainer's chunks come from. A data source gives the loop:

* ``spec``: the model it trains (the run's model sections, the data's views, size, chunk and actions);
* ``n_train`` / ``n_held`` and ``train_batch(items)`` / ``held_batch(items)``: chunks by position;
* ``clips(R)``: runs of R consecutive training chunks of one episode (training-time rollout);
* ``rollout_inputs(clip_items, contact_streams)``: how a rollout rebuilds chunk r > 1's contact images;
* ``load(device, progress)``: decode or move what the steps read, before the clock starts.

Two are registered: ``dataset`` (:mod:`.dataset_source`, the LeRobot dataset; contact images rebuilt by
the renderer) and ``pack`` (:mod:`.pack_source`, a tensor pack; contact images rebuilt from the pack's
geometry). The registry names modules, imported when chosen: the dataset source imports LeRobot and
MuJoCo, which the GPU machine lacks."""

from __future__ import annotations

import importlib

from imac_model.config import RunConfig

SOURCES = {"dataset": "imac_model.training.dataset_source:DatasetSource",
           "pack": "imac_model.training.pack_source:PackSource"}


def source_kind(run: RunConfig) -> str:
    """``pack`` when ``data.pack`` names one, else ``dataset``."""
    return "pack" if run.data.pack else "dataset"


def open_source(run: RunConfig):
    """The data source ``run`` reads (its spec resolved and checked; nothing decoded yet)."""
    module, name = SOURCES[source_kind(run)].split(":")
    return getattr(importlib.import_module(module), name)(run)


__all__ = ["SOURCES", "open_source", "source_kind"]
