"""Small number summaries shared by the report's builder, findings and figures."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np


def stats(values: Sequence[float] | np.ndarray) -> dict[str, float] | None:
    """``{n, rms, p50, p90, p99, max}`` of non-negative values (px), None when empty."""
    v = np.asarray(values, dtype=float).reshape(-1)
    if v.size == 0:
        return None
    return {
        "n": int(v.size),
        "rms": float(np.sqrt(np.mean(v**2))),
        "p50": float(np.median(v)),
        "p90": float(np.percentile(v, 90)),
        "p99": float(np.percentile(v, 99)),
        "max": float(v.max()),
    }


def _nice_ceil(x: float) -> float:
    """Smallest of 1, 2, 2.5, 5 x 10^k that is >= x."""
    k = math.floor(math.log10(x))
    for m in (1.0, 2.0, 2.5, 5.0, 10.0):
        if m * 10**k >= x * (1 - 1e-12):
            return float(m * 10**k)
    return float(10 ** (k + 1))


def histogram_edges_px(values: np.ndarray, bins: int = 40) -> np.ndarray:
    """Shared bin edges (px) of the per-camera reprojection histograms: 0 to a round number
    near 3x the 90th percentile; larger values land in the last bin."""
    v = np.asarray(values, dtype=float)
    top = _nice_ceil(max(3.0 * float(np.percentile(v, 90)), 0.2) if v.size else 1.0)
    return np.linspace(0.0, top, bins + 1)


def median_or_none(values: list[float | None]) -> float | None:
    """Median of the values that are not None; None when there are none."""
    vals = [v for v in values if v is not None]
    return float(np.median(vals)) if vals else None


def fmt(x: float | None, digits: int = 2) -> str:
    """``x`` with ``digits`` decimals, ``n/a`` for None (findings' messages, figure titles)."""
    return "n/a" if x is None else f"{x:.{digits}f}"


# a change in percent of its prior only where the prior is a base: not about zero (a distortion
# coefficient's prior is often 0 or ~1e-3) and not outgrown by the change (beyond 100 % the
# prior was about zero for this parameter: 'p1 +830.13 %' says less than 'p1 +0.0093')
PCT_MIN_PRIOR = 1e-3
PCT_MAX = 100.0


def percent_of_prior(prior: float | None, change: float) -> float | None:
    """``change`` in percent of ``|prior|``, None where the prior is no base for it
    (:data:`PCT_MIN_PRIOR`, :data:`PCT_MAX`)."""
    if prior is None or abs(prior) < PCT_MIN_PRIOR or abs(change) > PCT_MAX / 100.0 * abs(prior):
        return None
    return 100.0 * change / abs(prior)


def change_text(prior: float | None, change: float, unit: str = "") -> str:
    """A refined parameter's change for a reader: '+4.80 %' of its prior, or the absolute
    '+0.0093' ('+12.3 px' with ``unit``) where :func:`percent_of_prior` finds no base."""
    pct = percent_of_prior(prior, change)
    return (f"{pct:+.2f} %" if pct is not None
            else f"{change:+.3g}{' ' + unit if unit else ''}")
