"""Images -> marker corners (cv2, numba): ArUco and ChArUco detection (:mod:`.markers`), the
unbiased edge-fit corner model (:mod:`.edge_fit`, its numba twin :mod:`.edge_fit_jit`), the
corner-bias analysis of real photos (:mod:`.corner_bias`) and the detection of a whole dataset
with its cache (:mod:`.run`). Imports :mod:`rgbd_calib.core` and :mod:`rgbd_calib.model`.
"""
