"""Every on-disk edit of a LeRobot v3.0 dataset, in one package (built on ``lerobot.datasets``).

* :mod:`~imac_data.dataset.files`    atomic file writes, staged copies of a dataset
* :mod:`~imac_data.dataset.info`     the versioned ``imac`` block of ``meta/info.json``, stats order
* :mod:`~imac_data.dataset.videos`   video encoding settings, streaming mp4 writers, image stats
* :mod:`~imac_data.dataset.streams`  adding video streams to a dataset
* :mod:`~imac_data.dataset.columns`  adding per-frame and per-episode columns
* :mod:`~imac_data.dataset.episodes` writing a dataset episode by episode, chunk by chunk
* :mod:`~imac_data.dataset.merge`    merging built datasets of one rig (keeps the ``imac`` block)
* :mod:`~imac_data.dataset.validate` checking a built dataset (``python -m imac_data.validate``)
* :mod:`~imac_data.dataset.hf_features` a linear-time ``datasets.Features`` constructor (wide metadata)

Every edit is staged: new files are written next to their destination and moved into
place with ``os.replace`` / ``os.rename`` only when complete, ``meta/info.json`` last (it
is what makes LeRobot see a new feature); on error the dataset is left as it was.
"""

from imac_data.dataset.hf_features import install as _install_linear_features

_install_linear_features()  # datasets 4.x builds Features in quadratic time (see hf_features)
