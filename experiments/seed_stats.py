"""The seed-level statistics of `irdepth_experiments.claims`: the paired t-interval over seeds,
Holm's correction, and the power of the test (the effect it detects, the seeds an effect needs),
from the noncentral t distribution."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy import optimize, stats

ALPHA = 0.05
POWER = 0.8
MAX_SEEDS = 1000
"""seeds_needed above this is reported as None (not detectable at any practical budget)."""


def power(effect: float, sd: float, seeds: int, alpha: float = ALPHA) -> float:
    """Power of the two-sided paired t-test at `seeds` seeds for a true `effect` when the
    per-seed differences have standard deviation `sd`."""
    df = seeds - 1
    crit = stats.t.ppf(1 - alpha / 2, df)
    nc = effect / (sd / math.sqrt(seeds))
    # P(T < -crit | nc) as P(T > crit | -nc): scipy's nct.cdf is NaN in parts of the far tail
    return float(stats.nct.sf(crit, df, nc) + stats.nct.sf(crit, df, -nc))


def detectable_effect(sd: float, seeds: int, alpha: float = ALPHA, target: float = POWER) -> float:
    """The smallest effect the two-sided t-test at `seeds` seeds finds with power `target`
    (noncentral t; about (t_{1-a/2} + t_{power}) * sd / sqrt(seeds), larger at few seeds).
    inf below 2 seeds or without a standard deviation; 0 when sd == 0."""
    if seeds < 2 or not np.isfinite(sd):
        return math.inf
    if sd == 0:
        return 0.0
    se = sd / math.sqrt(seeds)
    # power reaches 1 by a noncentrality of 20 at any df >= 1 (scipy's nct is NaN far above)
    nc = optimize.brentq(lambda x: power(x * se, sd, seeds, alpha) - target, 0.0, 20.0)
    return float(nc * se)


def seeds_needed(effect: float, sd: float, alpha: float = ALPHA, target: float = POWER) -> int | None:
    """The fewest seeds (>= 2) at which the t-test detects `effect` with power `target` when
    the per-seed differences have standard deviation `sd`; None for effect <= 0, an unknown sd,
    or more than `MAX_SEEDS`."""
    if not effect > 0 or not np.isfinite(sd):
        return None
    if sd == 0:
        return 2
    lo, hi = 2, 2
    while power(effect, sd, hi, alpha) < target:
        if hi >= MAX_SEEDS:
            return None
        lo, hi = hi, min(2 * hi, MAX_SEEDS)
    while lo < hi:  # power grows with seeds: the first n with enough power
        mid = (lo + hi) // 2
        if power(effect, sd, mid, alpha) >= target:
            hi = mid
        else:
            lo = mid + 1
    return hi


def seed_level(differences: np.ndarray, alpha: float = ALPHA) -> dict:
    """Paired t inference over per-seed differences (S,).

    Returns:
      {'effect': mean, 'sd': their standard deviation (ddof 1), 'low', 'high': the two-sided
      (1 - alpha) t-interval (df = S - 1), 'p': two-sided p of effect == 0, 'seeds': S}.
      With one seed: sd, p NaN and the interval (-inf, inf). With identical differences: a
      zero-width interval and p 0 (1 when they are all 0).
    """
    d = np.asarray(differences, np.float64)
    n, effect = len(d), float(d.mean())
    if n < 2:
        return {"effect": effect, "sd": math.nan, "low": -math.inf, "high": math.inf,
                "p": math.nan, "seeds": n}
    sd = float(d.std(ddof=1))
    se = sd / math.sqrt(n)
    if se == 0:
        p = 1.0 if effect == 0 else 0.0
        half = 0.0
    else:
        p = float(2 * stats.t.sf(abs(effect) / se, n - 1))
        half = float(stats.t.ppf(1 - alpha / 2, n - 1) * se)
    return {"effect": effect, "sd": sd, "low": effect - half, "high": effect + half, "p": p, "seeds": n}


def holm(p_values: Sequence[float]) -> list[float]:
    """Holm's step-down adjusted p-values (same order; NaN stays NaN and is not counted)."""
    p = np.asarray(p_values, np.float64)
    out = np.full(len(p), np.nan)
    tested = np.flatnonzero(np.isfinite(p))
    m, running = len(tested), 0.0
    for rank, i in enumerate(tested[np.argsort(p[tested], kind="stable")]):
        running = max(running, min(1.0, (m - rank) * p[i]))
        out[i] = running
    return out.tolist()
