"""Evaluation of the world model (issue 17).

* :mod:`imac_model.evaluate.closed_loop`: closed-loop policy evaluation inside the world
  model, from a real dataset's start frames; the generated episodes as a LeRobot dataset.
* :mod:`imac_model.evaluate.policies`: policies as callables (observation -> action chunk),
  LeRobot's ``select_action`` queue semantics, the LeRobot policy adapter.
* :mod:`imac_model.evaluate.open_loop`: multi-chunk rollouts of recorded actions against the
  recording, per-chunk metrics, action sensitivity.
* :mod:`imac_model.evaluate.statistics`: world-model vs real success over policies or
  checkpoints with repeated groups (Pearson, Spearman, Kendall tau-b, SIMPLER's MMRV,
  episode bootstrap intervals, the scatter plot).
* :mod:`imac_model.evaluate.video_metrics`: MSE, PSNR, SSIM, FID and FVD between
  generated and recorded future videos, per view, mosaic and task, with the protocol.
* :mod:`imac_model.evaluate.success`: success judges behind one interface (a learned
  classifier trained on a dataset's ``imac/success`` labels, CSV labels, external callables).
* :mod:`imac_model.cli.evaluate`: ``imac-model evaluate`` (closed-loop,
  video-metrics, label, correlate).

Submodules are imported on use; importing this package loads none of them.
"""
