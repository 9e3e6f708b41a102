"""Statistics of the seeded closed-loop study: confidence intervals by bootstrap, the
paper's two claims as paired tests over seeds, and the feedback mechanism as a
correlation with a cluster-bootstrap interval (frames of one drive are not independent:
whole drives are resampled).

numpy only (the sim does not need scipy): percentile bootstrap intervals, and the exact
sign-flip permutation test of a paired mean difference (all 2^n sign patterns up to
n = 16 seeds, a random 2^16 of them beyond).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from monoloc.core.errors import InvalidInputError


@dataclass(frozen=True)
class StatsConfig:
    """resamples: bootstrap draws; level: the intervals' coverage (0.95: a 95 % CI)."""

    resamples: int = 10_000
    level: float = 0.95


def bootstrap_mean_ci(
    values: np.ndarray, rng: np.random.Generator, config: StatsConfig = StatsConfig()
) -> dict:
    """Mean of (n,) values (NaN dropped) with its percentile-bootstrap interval:
    {"mean", "lo", "hi", "n"} (lo = hi = mean for one value, None for none)."""
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    if len(v) == 0:
        return {"mean": None, "lo": None, "hi": None, "n": 0}
    mean = float(v.mean())
    if len(v) == 1:
        return {"mean": mean, "lo": mean, "hi": mean, "n": 1}
    draws = rng.integers(0, len(v), size=(config.resamples, len(v)))
    means = v[draws].mean(axis=1)
    a = (1.0 - config.level) / 2.0
    lo, hi = np.quantile(means, [a, 1.0 - a])
    return {"mean": mean, "lo": float(lo), "hi": float(hi), "n": int(len(v))}


def paired_test(
    a: np.ndarray,
    b: np.ndarray,
    rng: np.random.Generator,
    config: StatsConfig = StatsConfig(),
) -> dict:
    """Is ``a`` larger than ``b``, paired by index (by seed)? d = a - b over the pairs
    where both are finite: the mean difference with its bootstrap CI, how many pairs have
    d > 0, and the one-sided p-value of the sign-flip permutation test (H0: d is
    symmetric about 0; p = share of sign patterns whose mean is >= the observed one)."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if a.shape != b.shape:
        raise InvalidInputError(f"paired values differ in shape: {a.shape} and {b.shape}")
    ok = np.isfinite(a) & np.isfinite(b)
    d = a[ok] - b[ok]
    n = len(d)
    if n == 0:
        return {"n": 0, "mean_diff": None, "lo": None, "hi": None, "n_positive": 0, "p": None}
    ci = bootstrap_mean_ci(d, rng, config)
    observed = float(d.mean())
    if n <= 16:
        signs = np.array(list(itertools.product((1.0, -1.0), repeat=n)))
    else:
        signs = rng.choice((1.0, -1.0), size=(1 << 16, n))
    means = (signs * np.abs(d)).mean(axis=1)
    p = float(np.mean(means >= observed - 1e-15))
    return {
        "n": n,
        "mean_diff": observed,
        "lo": ci["lo"],
        "hi": ci["hi"],
        "n_positive": int(np.sum(d > 0)),
        "p": p,
    }


def pearson(x: np.ndarray, y: np.ndarray) -> float | None:
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    if len(x) < 3 or np.std(x) == 0 or np.std(y) == 0:
        return None
    return float(np.corrcoef(x, y)[0, 1])


def cluster_correlation(
    groups: list[tuple[np.ndarray, np.ndarray]],
    rng: np.random.Generator,
    config: StatsConfig = StatsConfig(),
) -> dict:
    """Pearson r of x against y pooled over ``groups`` ((x, y) per drive, (n_i,) each),
    with a bootstrap interval that resamples whole drives, and the least-squares slope of
    x on y (x per unit of y) with its interval the same way: {"r", "lo", "hi", "slope",
    "slope_lo", "slope_hi", "frames", "drives"}."""
    groups = [(np.asarray(x, float), np.asarray(y, float)) for x, y in groups if len(x)]
    if not groups:
        return {"r": None, "lo": None, "hi": None, "frames": 0, "drives": 0}
    x_all = np.concatenate([g[0] for g in groups])
    y_all = np.concatenate([g[1] for g in groups])
    r = pearson(x_all, y_all)
    slope = None if r is None else float(np.cov(x_all, y_all, bias=True)[0, 1] / np.var(y_all))
    out = {
        "r": r,
        "lo": None,
        "hi": None,
        "slope": slope,
        "slope_lo": None,
        "slope_hi": None,
        "frames": int(len(x_all)),
        "drives": len(groups),
    }
    if r is None or len(groups) < 2:
        return out
    # Sufficient statistics per drive make each resample a few sums.
    stats = np.array(
        [[len(x), x.sum(), y.sum(), (x * x).sum(), (y * y).sum(), (x * y).sum()] for x, y in groups]
    )
    draws = rng.integers(0, len(groups), size=(config.resamples, len(groups)))
    s = stats[draws].sum(axis=1)
    n, sx, sy, sxx, syy, sxy = s.T
    cov = sxy / n - sx * sy / n**2
    vx, vy = sxx / n - (sx / n) ** 2, syy / n - (sy / n) ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        rs = cov / np.sqrt(vx * vy)
        slopes = cov / vy
    rs, slopes = rs[np.isfinite(rs)], slopes[np.isfinite(slopes)]
    a = (1.0 - config.level) / 2.0
    out["lo"], out["hi"] = (float(v) for v in np.quantile(rs, [a, 1.0 - a]))
    out["slope_lo"], out["slope_hi"] = (float(v) for v in np.quantile(slopes, [a, 1.0 - a]))
    return out
