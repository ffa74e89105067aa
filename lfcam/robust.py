"""Robust spread: the normal-consistent median absolute deviation.

``scipy.stats.median_abs_deviation(x, scale="normal")`` computes the same number; importing
``scipy.stats`` costs ~0.3 s, paid by every ``lfcam`` command and by every worker process of
``lfcam distance --jobs`` (docs/distance.md, "Start-up overlap, the faint search on a
raster, a polish only where it moves the answer"), for a two-line formula.
"""

from __future__ import annotations

import numpy as np

# 1 / Φ⁻¹(3/4): the MAD of a normal distribution is this many times smaller than its σ
NORMAL_MAD_SCALE = 1.482602218505602


def mad_sigma(values: np.ndarray) -> float:
    """σ estimated from the median absolute deviation of all ``values`` (NaN propagates).

    Parameters
    ----------
    values : array_like
        Any shape; flattened.

    Returns
    -------
    float
        ``1.4826 · median(|x − median(x)|)``: σ for normal data, robust to outliers.
    """
    x = np.asarray(values, dtype=np.float64).ravel()
    if x.size == 0:
        return float("nan")
    return float(NORMAL_MAD_SCALE * np.median(np.abs(x - np.median(x))))
