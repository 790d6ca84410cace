"""Variance components of a pose graph of relative poses: each group of factors (the priors
holding the cameras, the depth pairs) weighed by a variance factor from its own residuals."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import TypeVar

import numpy as np

from ..core.config import BundleConfig
from .bundle import bundle_adjust
from .bundle_problem import BundleProblem, RelativePose

R = TypeVar("R")
Fit = tuple[np.ndarray, np.ndarray]  # a group's whitened chi-squares and redundancy numbers
MIN_GROUP_REDUNDANCY = 1.0  # of a variance component: below it, its factor is not estimated


def updated_factor(factor: float, chi2: np.ndarray, redundancy: np.ndarray) -> float:
    """One step of variance-component estimation for a group solved at variance factor
    ``factor`` with per-factor whitened ``chi2`` and ``redundancy`` numbers: ``factor`` times
    its chi-square over its redundancy, never below 1; ``factor`` itself when the group
    carries less than :data:`MIN_GROUP_REDUNDANCY` of the redundancy."""
    r = float(np.sum(redundancy))
    if r < MIN_GROUP_REDUNDANCY:
        return factor
    return max(1.0, factor * float(np.sum(chi2)) / r)


def estimate_factors(solve: Callable[[dict[str, float]], tuple[R, dict[str, Fit]]],
                     start: dict[str, float], max_iterations: int = 20,
                     tolerance: float = 1e-3) -> tuple[R, dict[str, float]]:
    """Variance-component estimation (Helmert; Foerstner 1979) around any solve:
    ``solve(factors)`` solves with each group's covariance times its factor and returns the
    result and, per group, its factors' whitened chi-squares and redundancy numbers; each
    group's factor is then multiplied by its chi-square over its redundancy
    (:func:`updated_factor`, never below its ``start``) and the solve repeated, until every
    factor changes by less than ``tolerance`` (relative) or after ``max_iterations`` solves
    (1: the plain solve). Returns the result solved with the returned factors."""
    factors = dict(start)
    n_solves = max(1, max_iterations)
    for solve_index in range(n_solves):
        res, fits = solve(factors)
        new = {g: max(start[g], updated_factor(factors[g], *fits[g])) for g in factors}
        if solve_index == n_solves - 1 or all(abs(new[g] / factors[g] - 1.0) < tolerance
                                               for g in factors):
            break  # the result was solved with ``factors``
        factors = new
    return res, factors


def solve_variance_components(K: dict[str, np.ndarray], reference: str,
                              T_init: dict[str, np.ndarray],
                              groups: dict[str, list[RelativePose]], max_iterations: int = 20,
                              tolerance: float = 1e-3):
    """The pose graph of ``groups`` of relative poses (e.g. ``initial``: the priors holding
    each camera to its start, ``pairs``: the depth pairs) with ``reference`` held, each group's
    covariance scaled by a variance factor estimated from its own residuals: ``(result,
    factors)`` with ``result`` the :class:`BundleResult` at the final factors (its marginals
    include them) and ``factors`` group -> factor.

    Variance-component estimation (:func:`estimate_factors`, every factor from 1): at the
    solution, a group's factor is multiplied by ``sum_g e^T W e / r_g``, its chi-square over
    its redundancy ``r_g = n_g - tr(A_g Sigma A_g^T)`` (the bundle's
    :func:`~rgbd_calib.solve.bundle.relative_pose_fit`), and the graph is solved again,
    until every factor changes by less than ``tolerance`` (relative) or after
    ``max_iterations`` solves (1: the plain solve). A factor is never below 1 (a group is
    never trusted beyond its model) and is left as it is for a group carrying less than
    :data:`MIN_GROUP_REDUNDANCY` of the redundancy (nothing to estimate it from). A
    systematic error of the pairs (colored ICP's, docs/depth.md "refine (issue 14)") shows
    as their disagreement with the priors and the other pairs, and weighs them down by
    it."""

    def solve(factors: dict[str, float]):
        flat = [replace(r, information=r.information / factors[g])
                for g, rs in groups.items() for r in rs]
        res = bundle_adjust(BundleProblem([], K, reference, T_init, {}, BundleConfig(),
                                          relative_poses=flat))
        fit = np.array(res.relative_pose_fit).reshape(-1, 2)
        chi2_f, redundancy = fit[:, 0], fit[:, 1]
        fits, start = {}, 0
        for g, rs in groups.items():
            part = slice(start, start + len(rs))
            start += len(rs)
            fits[g] = (chi2_f[part], redundancy[part])
        return res, fits

    return estimate_factors(solve, dict.fromkeys(groups, 1.0), max_iterations, tolerance)
