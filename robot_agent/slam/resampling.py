"""Importance resampling on log-weights (report §4.2), only when the weights degenerate."""

from __future__ import annotations

import numpy as np


def normalized_weights(log_weights: np.ndarray) -> np.ndarray:
    """Weights ``(P,)`` summing to one, from unnormalized log-weights (stable)."""
    w = np.exp(log_weights - np.max(log_weights))
    return w / w.sum()


def effective_sample_size(log_weights: np.ndarray) -> float:
    """``1 / Σ w²`` of the normalized weights: P for uniform weights, 1 for a single winner."""
    w = normalized_weights(log_weights)
    return float(1.0 / np.sum(w * w))


def systematic_resample(rng: np.random.Generator, log_weights: np.ndarray) -> np.ndarray:
    """Indices ``(P,)`` drawn by systematic resampling (one uniform offset, P even strata).

    Low variance: a particle of weight w is copied ⌊Pw⌋ or ⌈Pw⌉ times (Kitagawa 1996).
    """
    p = len(log_weights)
    cdf = np.cumsum(normalized_weights(log_weights))
    cdf[-1] = 1.0
    positions = (rng.random() + np.arange(p)) / p
    return np.searchsorted(cdf, positions, side="left")
