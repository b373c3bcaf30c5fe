"""Building datasets: the one staged flow, the HDF5/simulator and LeRobot sources, ``augment``,
and the workers. ``python -m imac_data.build`` is the main job (``imac build``)."""
