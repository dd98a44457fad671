"""The thesis's statistics (§5.4): Friedman with Kendall's W across methods, and pairwise Wilcoxon
signed-rank tests with Holm's correction and the effect size r = Z / sqrt(N).

scipy.stats does the tests; Holm's step-down correction is the few lines below (scipy has none,
and statsmodels would be a large dependency for it). Episodes where any compared method has no
value (a request never served has no T_pos) are left out of the paired tests; ``n`` says how many
pairs remained.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
from scipy import stats as st


def _paired(samples: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    arrays = {k: np.asarray(v, np.float64) for k, v in samples.items()}
    lengths = {len(v) for v in arrays.values()}
    if len(lengths) != 1:
        raise ValueError(f"paired samples need equal lengths, got {sorted(lengths)}")
    keep = np.all([np.isfinite(v) for v in arrays.values()], axis=0)
    return {k: v[keep] for k, v in arrays.items()}


def friedman(samples: dict[str, np.ndarray]) -> dict:
    """Friedman's chi-square over >= 3 methods with Kendall's W = chi2 / (N (k - 1))."""
    if len(samples) < 3:
        raise ValueError("Friedman's test compares at least 3 methods")
    data = _paired(samples)
    n, k = len(next(iter(data.values()))), len(data)
    if n < 2:
        return {"chi2": math.nan, "df": k - 1, "p": math.nan, "kendall_w": math.nan, "n": n}
    chi2, p = st.friedmanchisquare(*data.values())
    return {"chi2": float(chi2), "df": k - 1, "p": float(p), "kendall_w": float(chi2 / (n * (k - 1))), "n": n}


def holm(p_values: list[float]) -> list[float]:
    """Holm-Bonferroni adjusted p-values (step-down, monotone, capped at 1)."""
    m = len(p_values)
    order = np.argsort(p_values)
    adjusted = np.empty(m)
    running = 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (m - rank) * p_values[i]))
        adjusted[i] = running
    return adjusted.tolist()


def wilcoxon(a: np.ndarray, b: np.ndarray) -> dict:
    """Two-sided Wilcoxon signed-rank test (normal approximation, as reported with Z in the thesis);
    ``z`` is |Z| and ``r`` = |Z| / sqrt(N)."""
    data = _paired({"a": a, "b": b})
    n = len(data["a"])
    if n < 2 or np.all(data["a"] == data["b"]):
        return {"z": 0.0, "p": 1.0, "r": 0.0, "n": n}
    res = st.wilcoxon(data["a"], data["b"], method="approx")
    z = abs(float(res.zstatistic))
    return {"z": z, "p": float(res.pvalue), "r": z / math.sqrt(n), "n": n}


def pairwise(samples: dict[str, np.ndarray]) -> list[dict]:
    """Wilcoxon for every pair of methods, with Holm-adjusted p-values (``p_holm``)."""
    rows = []
    for x, y in itertools.combinations(samples, 2):
        rows.append({"a": x, "b": y, **wilcoxon(samples[x], samples[y])})
    for row, p in zip(rows, holm([r["p"] for r in rows]), strict=True):
        row["p_holm"] = p
    return rows
