"""The analyses of the reference paper's results section (3.1-3.4), and a few beyond it, as pure
functions of node errors.

A model's errors on one breast are the node RMSE of equation 2 per node and recorded step,
``(N, T)`` mm (`mammo_net.metrics.node_rmse`). A node's error "over all steps" is its mean over
the steps, as in the per-breast "all steps" RMSE; "last step" is the final recorded step.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from itertools import pairwise

import numpy as np
from numpy.typing import NDArray
from scipy import stats
from scipy.optimize import curve_fit

#: Upper edges of the paper's error classes (Fig. 4, 11, 22, 23): 2 mm bins to 22 mm, then > 22.
ERROR_CLASS_EDGES = np.arange(0.0, 24.0, 2.0)


def error_classes(node_errors: NDArray, edges: NDArray = ERROR_CLASS_EDGES) -> NDArray[np.float64]:
    """Percentage of nodes in each error class ``[e_i, e_i+1)``, and above the last edge.

    Parameters
    ----------
    node_errors : (M,)
        Node errors, mm.
    edges : (K + 1,)
        Increasing class edges, mm; the paper's are 0, 2, ..., 22.

    Returns
    -------
    (K + 1,) percentages summing to 100: K classes and the ``> edges[-1]`` class.
    """
    e = np.asarray(node_errors, float)
    counts = np.histogram(e, bins=np.append(edges, np.inf))[0]
    return 100.0 * counts / len(e)


def error_class_labels(edges: NDArray = ERROR_CLASS_EDGES) -> list[str]:
    """``["0-2", "2-4", ..., "20-22", "> 22"]`` (mm) for `error_classes`."""
    return [f"{a:g}-{b:g}" for a, b in pairwise(edges)] + [f"> {edges[-1]:g}"]


def binned_means(
    x: NDArray, y: NDArray, width: float
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]:
    """Mean of ``y`` in bins ``[k width, (k + 1) width)`` of ``x`` that hold any point.

    Returns the bin centres, the means and the number of points per bin.
    """
    k = np.floor(np.asarray(x, float) / width + 1e-9).astype(np.int64)
    bins, inverse, counts = np.unique(k, return_inverse=True, return_counts=True)
    means = np.bincount(inverse, weights=np.asarray(y, float)) / counts
    return (bins + 0.5) * width, means, counts


def r_squared(y: NDArray, fitted: NDArray) -> float:
    """Coefficient of determination ``1 - SS_res / SS_tot``."""
    y, fitted = np.asarray(y, float), np.asarray(fitted, float)
    ss_tot = ((y - y.mean()) ** 2).sum()
    return float(1.0 - ((y - fitted) ** 2).sum() / ss_tot) if ss_tot > 0 else float("nan")


def exp2(x: NDArray, a: float, b: float, c: float, d: float) -> NDArray:
    """The second-degree exponential ``a exp(b x) + c exp(d x)`` (MATLAB's ``exp2``)."""
    return a * np.exp(b * x) + c * np.exp(d * x)


def fit_exp2(x: NDArray, y: NDArray) -> tuple[NDArray[np.float64], float]:
    """Least-squares `exp2` fit of ``y(x)`` and its r^2 (the paper's Fig. 12, 13).

    Started from a one-term exponential through the log of the data plus a constant; returns
    NaN parameters and r^2 when there are fewer than five points or the fit does not converge.
    """
    x, y = np.asarray(x, float), np.asarray(y, float)
    nan = np.full(4, np.nan)
    if len(x) < 5:
        return nan, float("nan")
    positive = y > 0
    b, log_a = np.polyfit(x[positive], np.log(y[positive]), 1) if positive.sum() > 1 else (0, 0)
    starts = [(np.exp(log_a), b, 0.0, 0.0), (0.5 * y.mean(), 0.0, 0.1 * y.mean(), 5.0)]
    best, best_r2 = nan, -np.inf
    for p0 in starts:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                p, _ = curve_fit(exp2, x, y, p0=p0, maxfev=20000)
        except RuntimeError:
            continue
        r2 = r_squared(y, exp2(x, *p))
        if np.isfinite(r2) and r2 > best_r2:
            best, best_r2 = p, r2
    return (best, best_r2) if np.isfinite(best_r2) else (nan, float("nan"))


def fit_line(x: NDArray, y: NDArray) -> tuple[NDArray[np.float64], float]:
    """Least-squares line ``(slope, intercept)`` and its r^2; NaN with fewer than two points."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    if len(x) < 2:
        return np.full(2, np.nan), float("nan")
    p = np.polyfit(x, y, 1)
    return p, r_squared(y, np.polyval(p, x))


def pearson_r(x: NDArray, y: NDArray) -> float:
    """Pearson correlation coefficient; NaN when either variable is constant."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    if len(x) < 2 or x.std() == 0 or y.std() == 0:
        return float("nan")
    return float(np.corrcoef(x, y)[0, 1])


def paired_difference(a: NDArray, b: NDArray) -> dict[str, float]:
    """Compare two models on the same breasts by their per-breast errors.

    Parameters
    ----------
    a, b : (B,)
        Per-breast RMSE of models A and B on the same breasts, in the same order, mm.

    Returns
    -------
    dict
        ``n``; ``mean_diff`` (mean of a - b, mm) with the Student-t 95 % confidence interval
        ``ci95_low``, ``ci95_high``; ``relative`` (mean_diff over the mean of b);
        ``a_better`` (fraction of breasts with a < b); ``wilcoxon_p`` (two-sided signed-rank
        test of a - b; NaN under two breasts or when every difference is zero).
    """
    a, b = np.asarray(a, float), np.asarray(b, float)
    if a.shape != b.shape or a.ndim != 1:
        raise ValueError(f"paired errors need equal 1-D shapes, got {a.shape} and {b.shape}")
    d = a - b
    n, mean = len(d), float(d.mean()) if len(d) else float("nan")
    half = float(stats.t.ppf(0.975, n - 1) * d.std(ddof=1) / np.sqrt(n)) if n > 1 else float("nan")
    p = float(stats.wilcoxon(d).pvalue) if n > 1 and np.any(d != 0) else float("nan")
    return {
        "n": n,
        "mean_diff": mean,
        "ci95_low": mean - half,
        "ci95_high": mean + half,
        "relative": mean / float(b.mean()) if n else float("nan"),
        "a_better": float(np.mean(d < 0)) if n else float("nan"),
        "wilcoxon_p": p,
    }


def lognormal_fit(values: NDArray) -> tuple[float, float]:
    """Maximum-likelihood log-normal ``(mu, sigma)``: mean and standard deviation of ``ln v``
    over the positive values (the paper's Fig. 14)."""
    v = np.log(np.asarray(values, float)[np.asarray(values) > 0])
    return (float(v.mean()), float(v.std())) if len(v) else (float("nan"), float("nan"))


def lognormal_pdf(x: NDArray, mu: float, sigma: float) -> NDArray[np.float64]:
    """Density of the log-normal distribution at ``x > 0``."""
    x = np.asarray(x, float)
    return np.exp(-((np.log(x) - mu) ** 2) / (2 * sigma**2)) / (x * sigma * np.sqrt(2 * np.pi))


def value_at(x: NDArray, y: NDArray, x0: float) -> float:
    """``y`` linearly interpolated at ``x0`` along increasing ``x``; NaN outside
    ``[x[0], x[-1]]`` (the error of a breast at a compression ratio it passed through)."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    if not x[0] - 1e-12 <= x0 <= x[-1] + 1e-12:
        return float("nan")
    return float(np.interp(x0, x, y))


def mean_sd(values: Sequence[float] | NDArray) -> tuple[float, float]:
    """Mean and (population) standard deviation."""
    v = np.asarray(values, float)
    return float(v.mean()), float(v.std())
