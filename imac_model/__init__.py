"""imac_model: the action-conditioned video world model (iMaC), trained on imac datasets.

Modules, one concept each (diffusers-like: models, schedulers and pipelines apart):

* ``config``       typed run / model configs, validated, saved with every checkpoint
* ``dataset_meta`` the one reader of a dataset's ``meta/info.json`` ``imac`` block
* ``mosaic``       views <-> the six-panel mosaic; resize and K rescale
* ``batch``        ``ChunkBatch``: the tensors the model consumes
* ``data``         chunks of a LeRobot dataset (``delta_timestamps``), checked against a run
* ``backbones``    the backbone interface; a small CPU video DiT; Wan2.2-TI2V via diffusers
* ``controls``     control-image injection (paper eq. 2) and the action-vector baseline
* ``flow``         flow matching (tau = 0 noise, 1 data), Euler sampler, one-step estimate
* ``world_model``  backbone + conditioning + flow: loss, sampling, decode
* ``checkpoint``   safetensors checkpoints with their ModelSpec
* ``train``, ``sample``  the CLIs
"""

__version__ = "0.1.0"
