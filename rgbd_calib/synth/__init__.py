"""Synthetic rigs with ground truth, rendered in the dataset folder form: the renderer
(:mod:`.render` and its modules) and the ray casting (:mod:`.scene`, compiled in
:mod:`.scene_jit`). Imports core and model only: a render never depends on the detector or the
solver it is used to test.
"""
