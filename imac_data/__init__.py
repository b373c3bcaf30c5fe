"""imac_data: LeRobot datasets with action-derived control videos (motion, depth, contact).

Modules, one concept each:

* ``cameras``     pinhole cameras, calibration files, projection (torch)
* ``robot``       URDF robot model, joint maps, batched forward kinematics
* ``mjcf_to_urdf`` export a MuJoCo model's robot to URDF
* ``aloha``       the simulated ALOHA rig of gym-aloha
* ``simulate``    scripted-policy recorder writing ALOHA HDF5 episodes
* ``aloha_hdf5``  the raw HDF5 episode format (read, validate, write)
* ``ingest``      raw episodes -> base LeRobot dataset
* ``motion``      the controller map phi: which configuration a motion image shows
* ``render``      the robot renderer (RGB, mask, z-depth, link id per view)
* ``depth``       the depth colour codec and depth streams
* ``depth_sources`` recorded depth, Depth Anything 3
* ``contact``     contact images (robot-to-scene, scene-to-gripper)
* ``video_streams`` add video streams to a LeRobot dataset
* ``augment``     the control streams of an episode; augmenting existing datasets
* ``recipes``, ``build`` the build's recipes and CLI
* ``qa``          calibration overlay; ``qa refine`` (``refine``) fixes a calibration
* ``calibrate``   camera poses from the robot's silhouette (the algorithm of ``qa refine``)
"""

import os

# MuJoCo picks its GL backend when it is first imported: default to headless EGL
# (Mesa on the CPU), so nothing needs a display.
os.environ.setdefault("MUJOCO_GL", "egl")

__version__ = "0.1.0"
