"""Evaluation of the world model (issue 17): the building blocks that do not need the model.

* :mod:`imac_model.evaluate.statistics`: world-model vs real success over policies or
  checkpoints with repeated groups (Pearson, Spearman, Kendall tau-b, SIMPLER's MMRV,
  episode bootstrap intervals, the scatter plot).
* :mod:`imac_model.evaluate.video_metrics`: MSE, PSNR, SSIM, FID and FVD between
  generated and recorded future videos, per view, mosaic and task, with the protocol.
* :mod:`imac_model.evaluate.success`: success judges behind one interface (a learned
  classifier trained on a dataset's ``imac/success`` labels, CSV labels, external callables).

Submodules are imported on use; importing this package loads none of them.
"""
