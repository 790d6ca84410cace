"""What every finding rule shares: a finding's form, a rule's signature, the severities
(:mod:`.findings` runs the rules)."""

from __future__ import annotations

import re
from collections.abc import Callable
from typing import Any

Finding = dict[str, Any]
Rule = Callable[[dict[str, Any], list[Finding]], list[Finding]]
SEVERITY_ORDER = {"error": 0, "warning": 1, "info": 2}
# advice that asks for nothing ("Nothing to do; ...", "Nothing to do here ...")
NOTHING_TO_DO = re.compile(r"\s*nothing to do\b", re.IGNORECASE)


def finding(severity: str, code: str, cameras: list[str], message: str, advice: str) -> Finding:
    """One ``warnings[]`` entry."""
    return {
        "severity": severity,
        "code": code,
        "cameras": cameras,
        "message": message,
        "advice": advice,
    }


def cameras_of(found: list[Finding], code: str) -> set[str]:
    return {c for w in found if w["code"] == code for c in w["cameras"]}


def actionable(found: Finding) -> bool:
    """Whether a finding asks the reader to do something: its advice is neither empty nor
    'Nothing to do ...' (an info that only explains the result is not a next step)."""
    advice = (found.get("advice") or "").strip()
    return bool(advice) and not NOTHING_TO_DO.match(advice)


# findings that advise the next recording (more views, other board poses) rather than say
# that a part of this result is off: within a severity they rank after those that do
NEXT_RECORDING = frozenset({
    "few_views", "lens_coverage", "scratch_coverage", "board_coverage", "board_distance",
    "board_tilt", "dropped_views", "pair_fitness", "intrinsics_unsupported", "weak_link"})


def ranked_actionable(found: list[Finding]) -> list[Finding]:
    """The actionable findings by their effect on the result: errors, then warnings, then
    infos; within a severity, those that say a part of this result is off (a camera, the
    fused cloud, the board, the timing) before advice for the next recording
    (:data:`NEXT_RECORDING`), then in the rules' order."""
    return sorted((f for f in found if actionable(f)),
                  key=lambda f: (SEVERITY_ORDER.get(f.get("severity"), len(SEVERITY_ORDER)),
                                 f.get("code") in NEXT_RECORDING))
