"""RGB-D -> relative camera poses and the fused cloud; the only layer that imports open3d and
kiss-icp: the depth noise model (:mod:`.noise`), static clouds, the depth scale and voxel levels
(:mod:`.clouds`), what a registration's correspondences say about its pose (:mod:`.information`),
pair registration (:mod:`.registration`: colored/geometric ICP, robust registration, global
alignment) and the depth stage over a whole rig (:mod:`.stage`). Imports core, model and
solve's types; never the detector.
"""
