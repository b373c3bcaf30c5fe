"""imac_data: LeRobot datasets with action-derived control videos (motion, depth, contact).

Modules, one concept each:

* ``rig``         robot + cameras + controller (+ renderer, gripper surface), from a recipe or a dataset
* ``cameras``     pinhole cameras, calibration files, projection, pixel rays (torch)
* ``robot``       URDF robot model, joint maps with affine entries, batched forward kinematics
* ``urdf_summary`` a URDF's joints, limits, mimics, visuals; a recipe robot: block
* ``robot_files`` the robot description (URDF + meshes) packaged into a dataset
* ``mjcf_to_urdf`` export a MuJoCo model's robot to URDF
* ``aloha``       the simulated ALOHA rig of gym-aloha
* ``simulate``    scripted-policy recorder writing ALOHA HDF5 episodes
* ``aloha_hdf5``  the raw HDF5 episode format (read chunk by chunk, validate, write)
* ``motion``      the controller map phi: which configuration a motion image shows
* ``render``      the robot renderer (RGB, mask, z-depth, link id per view)
* ``depth``       the depth colour codec
* ``depth_sources`` recorded depth, Depth Anything 3
* ``nearest``     exact nearest distances, certified distances over pixel tiles
* ``clouds``      the reference scene cloud and the gripper surface samples that contact compares
* ``contact``     contact images (robot-to-scene, scene-to-gripper)
* ``pipeline``    the streamed episode pipeline and its stage timings
* ``ingest``      raw episodes -> base LeRobot dataset
* ``dataset``     every on-disk edit of a LeRobot dataset (streams, columns, imac block, merge, validate)
* ``recipes``, ``build``, ``workers`` the build's recipes, CLI, worker pinning
* ``safety``      the user's inputs are never written: overlap checks between output and inputs
* ``augment``     adding the streams to an existing dataset
* ``validate``    ``python -m imac_data.validate``
* ``qa``          calibration overlay; ``preview``: an mp4 mosaic of a built episode; ``qa refine`` (``refine``) fixes a calibration
* ``calibrate``   camera poses from the robot's silhouette (the algorithm of ``qa refine``; a package)
"""

import os

# MuJoCo picks its GL backend when it is first imported: default to headless EGL
# (Mesa on the CPU), so nothing needs a display.
os.environ.setdefault("MUJOCO_GL", "egl")

__version__ = "0.1.0"

if __import__("sys").argv[:1] == ["-m"]:  # `python -m imac_data.<command>` is starting (Python's argv while -m loads)
    from imac_data.cli import quiet_startup_interrupts

    quiet_startup_interrupts()
