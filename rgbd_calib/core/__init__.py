"""Foundations: stdlib, numpy, scipy, pydantic and yaml only; imports nothing else of ours.

:mod:`.geometry` (rigid transforms ``T_a_b``), :mod:`.camera` (the one camera model), :mod:`.config`
(every setting, one pydantic model per stage), :mod:`.errors` (the error family),
:mod:`.progress`, :mod:`.interrupts`, :mod:`.parallel` (process pools, Dask), :mod:`.yamlio`,
:mod:`.ply`. Frames, units and covariance order: docs/conventions.md.
"""
