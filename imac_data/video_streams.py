"""Moved: video streams are part of the dataset package (:mod:`imac_data.dataset`).

* settings, writers, stats: :mod:`imac_data.dataset.videos`
* adding streams to a dataset: :mod:`imac_data.dataset.streams`
* staged copies of a dataset: :mod:`imac_data.dataset.files`

This module re-exports the names it used to define, for existing imports.
"""

from imac_data.dataset.files import staged_dataset
from imac_data.dataset.streams import StreamWriter, add_video_stream, add_video_streams
from imac_data.dataset.videos import VideoEncoding, encode_video, encoder_versions, read_video_frames

__all__ = ["VideoEncoding", "StreamWriter", "add_video_stream", "add_video_streams", "encode_video",
           "encoder_versions", "read_video_frames", "staged_dataset"]
