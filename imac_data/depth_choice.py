"""Which depth source a recipe's ``depth:`` section asks for, built once per worker.

=============  ===============================================================================
``recorded``   the source's own depth: the HDF5 episodes' ``/observations/images_depth`` (uint16
               millimetres), or a LeRobot source's depth feature (``depth.feature``, in
               ``depth.format``: millimetres, metres or our colour codec; read by
               :class:`imac_data.lerobot_reader.LeRobotEpisodeReader`)
``da3``        Depth Anything 3 (:class:`~imac_data.depth_sources.DepthAnything3`): all views of a
               timestep together, posed (the head camera from calibration, the wrists from FK),
               metric. With fewer than three cameras its scale fit is undetermined, so DA3's
               monocular metric model (:class:`~imac_data.depth_sources.DepthAnything3Metric`,
               ``depth.monocular_model``) is used instead. Which one ran is recorded in
               ``info["imac"]["depth"]["source"]``.
``none``       no depth: the motion streams only (:class:`~imac_data.depth_sources.NoDepth`)
=============  ===============================================================================

``depth.model`` / ``depth.monocular_model`` name a local weights directory (relative to the
recipe) or a Hugging Face model id; a directory that does not exist is an error before any
work starts (:func:`check_depth_inputs`).
"""

from __future__ import annotations

from pathlib import Path

from imac_data.errors import InputError

__all__ = ["check_depth_inputs", "make_depth_source", "uses_monocular"]


def uses_monocular(num_cameras: int) -> bool:
    """DA3's multi-view scale fit needs three posed views; fewer use the monocular metric model."""
    return num_cameras < 3


def _model(section, recipe_file: str, monocular: bool) -> str:
    from imac_data.depth_sources import DEFAULT_DA3_METRIC_MODEL, DEFAULT_DA3_MODEL, _looks_like_hub_id

    value = section.monocular_model if monocular else section.model
    field = "depth.monocular_model" if monocular else "depth.model"
    if value is None:
        return DEFAULT_DA3_METRIC_MODEL if monocular else DEFAULT_DA3_MODEL
    import os

    path = Path(os.path.expandvars(os.path.expanduser(value)))
    if not path.is_absolute() and recipe_file:
        local = Path(recipe_file).parent / path
        if local.exists() or not _looks_like_hub_id(value):
            path = local
    if path.exists():
        return str(path)
    if _looks_like_hub_id(value) and not value.startswith(("/", ".")):
        return value
    raise InputError(f"{recipe_file or '<recipe>'}: {field}: the Depth Anything 3 model directory {path} does not "
                     "exist (give a directory holding config.json and model.safetensors, or a Hugging Face "
                     "model id such as depth-anything/DA3-BASE)")


def check_depth_inputs(section, recipe_file: str, num_cameras: int) -> str | None:
    """Fail early on a ``da3`` model directory that is not there; returns the model the
    build will load (None unless ``da3``)."""
    if section.source != "da3":
        return None
    return _model(section, recipe_file, uses_monocular(num_cameras))


def make_depth_source(section, recipe_file: str, num_cameras: int, *, local_files_only: bool = False):
    """The :class:`~imac_data.depth_sources.DepthSource` of a recipe's ``depth:`` section for a
    rig of ``num_cameras`` cameras."""
    from imac_data.depth_sources import DepthAnything3, DepthAnything3Metric, NoDepth, RecordedDepth

    if section.source == "none":
        return NoDepth()
    if section.source == "recorded":
        return RecordedDepth()
    model = _model(section, recipe_file, uses_monocular(num_cameras))
    cls = DepthAnything3Metric if uses_monocular(num_cameras) else DepthAnything3
    return cls(model, device=section.device, batch_size=section.batch_size, process_res=section.process_res,
               local_files_only=local_files_only)
