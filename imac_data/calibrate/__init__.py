"""Calibration from the robot itself: refine camera poses by aligning the rendered robot
with the robot's pixels in the recorded frames (the algorithm of ``qa refine``).

Every recording already holds a calibration target: the robot, at joint angles we know.
Rendered (URDF + FK, :mod:`imac_data.render`) through a slightly wrong camera, its
silhouette misses the robot's pixels; this package moves the camera until they agree.
Per camera, one rigid 6-DoF pose is refined: a fixed camera's ``T_world_cam`` or a mounted
(wrist) camera's ``T_link_cam``, optionally with its focal length (``fx`` and ``fy`` scaled
together, principal point kept). FK is known, so the cameras are independent problems.

One module per concept:

* :mod:`.pose`: the pose update in the camera's own axes, and the pose change per axis;
* :mod:`.frames`: which frames (robot well in view, configurations far apart), where the
  robot's pixels come from (simulator, a segmenter's masks, the built-in edge cue), and
  reading them from raw episodes or a LeRobot dataset;
* :mod:`.objective`: the distance-field edge term and the soft silhouette IoU, exact and
  differentiable; :func:`silhouette_agreement`, the report's measure;
* :mod:`.config`, :mod:`.optimise`: :class:`RefineConfig`; coarse to fine, gradient
  (autograd through the soft silhouette, L-BFGS in a trust region) or derivative-free;
* :mod:`.report`: the report (per camera IoU, outline distance, pose change) and the
  before/after overlays.

Functions here work on arrays and tensors; the command (inputs, the rig, files) is
:mod:`imac_data.refine`.
"""

from imac_data.calibrate.config import METHODS, RefineConfig
from imac_data.calibrate.frames import (PIXEL_SOURCES, CameraFrames, DatasetFrames, EpisodeFrames, RobotPixels,
                                        choose_frames, image_edges, open_frames, select_frames)
from imac_data.calibrate.objective import distance_field, edge_distance, silhouette_agreement
from imac_data.calibrate.optimise import CameraFit, refine_camera, refine_camera_edges
from imac_data.calibrate.pose import AXES, apply_update, pose_change, se3_exp

__all__ = ["METHODS", "RefineConfig", "PIXEL_SOURCES", "CameraFrames", "DatasetFrames", "EpisodeFrames",
           "RobotPixels", "open_frames", "choose_frames", "image_edges", "select_frames", "distance_field",
           "edge_distance", "silhouette_agreement", "CameraFit", "refine_camera", "refine_camera_edges", "AXES",
           "apply_update", "pose_change", "se3_exp"]
