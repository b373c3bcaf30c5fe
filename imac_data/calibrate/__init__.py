"""Camera poses from the robot itself: the rendered robot's silhouette pulled onto the robot's
pixels in the recordings (``imac qa refine``; ``docs/calibration.md``). One module per part:
the pose update (``pose``), frames and robot pixels (``frames``), the objective
(``objective``), the optimisers (``config``, ``optimise``), the report (``report``) and the
command's inputs and outputs (``refine``)."""
