"""Every on-disk edit of a LeRobot v3.0 dataset: atomic files, the ``imac`` block, video
streams and columns, the base features, merging, the output's protection, the card, and
validation. Each edit is staged: new files are written beside their destination and moved
into place when complete, ``meta/info.json`` last."""
