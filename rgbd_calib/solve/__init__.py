"""Corners -> extrinsics with uncertainty; the only layer that imports gtsam.

Per-view PnP (:mod:`.pose`), intrinsics from scratch (:mod:`.intrinsics_init`), the robust pose
graph (:mod:`.posegraph`, initialised by :mod:`.posegraph_init`), the bundle adjustment on the
corners (:mod:`.bundle`, its inputs and result :mod:`.bundle_problem`, its view factors
:mod:`.bundle_factors`), the self-calibration ladder's decisions (:mod:`.selfcal`) and its
solves (:mod:`.ladder`) and the has-a-camera-moved inference (:mod:`.moved`). Imports the
layers below (core, model, detect's result types).
"""
