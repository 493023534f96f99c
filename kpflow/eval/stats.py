"""Statistics of success rates shared by the experiments."""

from __future__ import annotations

import math
from collections import Counter


def wilson_interval(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """Wilson score interval for a binomial proportion (Wilson 1927): the 95% interval for ``z = 1.96``."""
    if n == 0:
        return 0.0, 1.0
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return max(0.0, centre - half), min(1.0, centre + half)


def success_summary(trials: list[dict]) -> dict:
    """``trials``, ``successes``, ``success`` (rate), ``ci`` (95% Wilson) and ``failures`` (reason -> count) of trials
    that each have ``success`` and ``failure``."""
    n, k = len(trials), sum(t["success"] for t in trials)
    return {
        "trials": n,
        "successes": k,
        "success": k / n if n else float("nan"),
        "ci": wilson_interval(k, n),
        "failures": dict(Counter(t["failure"] for t in trials if not t["success"])),
    }


def rate_cell(successes: int, trials: int, ci: tuple[float, float]) -> str:
    """``k/n = p% [lo, hi]``: a success rate and its interval in one table cell."""
    rate = 100 * successes / trials if trials else float("nan")
    return f"{successes}/{trials} = {rate:.0f}% [{100 * ci[0]:.0f}, {100 * ci[1]:.0f}]"


def success_cells(summary: dict) -> str:
    """``k/n = p% [lo, hi] | reasons`` of a :func:`success_summary`: two cells of a markdown table row."""
    reasons = ", ".join(f"{r}: {c}" for r, c in sorted(summary["failures"].items())) or "-"
    return f"{rate_cell(summary['successes'], summary['trials'], summary['ci'])} | {reasons}"
