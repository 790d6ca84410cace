"""What every finding rule shares: a finding's form, a rule's signature, the severities
(:mod:`.findings` runs the rules)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

Finding = dict[str, Any]
Rule = Callable[[dict[str, Any], list[Finding]], list[Finding]]
SEVERITY_ORDER = {"error": 0, "warning": 1, "info": 2}


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
