"""A linear-time ``datasets.Features`` constructor for wide LeRobot metadata.

HF ``datasets`` 4.x builds a ``Features`` in time quadratic in its number of columns: its
``__init__`` re-assigns every column through ``__setitem__``, and each assignment
recomputes the "requires decoding" flag of *all* columns. A built iMaC dataset's
``meta/episodes`` parquet has 343 columns (per-feature stats of 18 video streams), and
``datasets`` constructs ``Features`` hundreds of times per load, so every
``LeRobotDatasetMetadata`` / ``LeRobotDataset`` load of it took 0.85 s instead of 0.16 s
(on the demo dataset).

:func:`use_linear_features` replaces ``Features.__init__`` with one that does the same work once per
column: the same values (old-style ``[feature]`` lists become ``List(feature)``) and the
same decoding flags, so nothing read or written changes (``tests/test_dataset.py``
compares it with the original on a built dataset's schemas). The build calls it
before it writes (:mod:`imac_data.build.staging`, the workers); it replaces only the
implementation it was checked against (``datasets`` 4.x) and leaves any other alone.
"""

from __future__ import annotations

__all__ = ["use_linear_features", "installed", "original_init"]

_ORIGINAL = None


def _linear_init(*args, **kwargs):
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


def use_linear_features() -> bool:
    """Use the linear constructor (idempotent). False when this ``datasets`` is not 4.x."""
    global _ORIGINAL
    import datasets
    from datasets.features.features import Features

    if _ORIGINAL is not None:
        return True
    if not str(datasets.__version__).startswith("4."):
        return False
    _ORIGINAL = Features.__init__
    Features.__init__ = _linear_init
    return True


def installed() -> bool:
    return _ORIGINAL is not None


def original_init():
    """``datasets``' own ``Features.__init__`` (the oracle of the tests), or None."""
    return _ORIGINAL
