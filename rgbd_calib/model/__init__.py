"""What is calibrated, and its files: the board, the rig, the dataset folder, the results
(``extrinsics.yaml``), an earlier output folder read back, the thesis's pose-graph CSVs.
Imports only :mod:`rgbd_calib.core`. The file forms: docs/formats.md.
"""
