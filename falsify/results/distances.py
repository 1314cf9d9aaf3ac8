"""Distances between distributions, each a scalar where lower is closer: the Fréchet distance
between Gaussians (from moments or from samples), the 1-Wasserstein distance between histograms
and the total variation between count vectors."""

from __future__ import annotations

import numpy as np


def normalised(counts: np.ndarray) -> np.ndarray:
    """Counts as shares of their total (zeros when there are none)."""
    total = counts.sum()
    return counts / total if total > 0 else np.zeros_like(counts, np.float64)


def total_variation(a: np.ndarray, b: np.ndarray) -> float:
    """Total variation between two count vectors' shares: half their absolute difference."""
    return float(0.5 * np.abs(normalised(a) - normalised(b)).sum())


def frechet_distance(mu1: np.ndarray, cov1: np.ndarray, mu2: np.ndarray,
                     cov2: np.ndarray) -> float:
    """|mu1 - mu2|² + Tr(S1 + S2 - 2 (S1 S2)^½) for two Gaussians.

    Tr (S1 S2)^½ is the sum of the square roots of the eigenvalues of S1^½ S2 S1^½ (symmetric,
    positive semi-definite), which stays real and stable where S1 or S2 is singular."""
    mu1, mu2 = np.asarray(mu1, np.float64), np.asarray(mu2, np.float64)
    cov1, cov2 = np.atleast_2d(cov1).astype(np.float64), np.atleast_2d(cov2).astype(np.float64)
    w, v = np.linalg.eigh((cov1 + cov1.T) / 2)
    root = (v * np.sqrt(np.clip(w, 0.0, None))) @ v.T
    m = root @ cov2 @ root
    cross = np.sqrt(np.clip(np.linalg.eigvalsh((m + m.T) / 2), 0.0, None)).sum()
    d = float(((mu1 - mu2) ** 2).sum() + np.trace(cov1) + np.trace(cov2) - 2.0 * cross)
    return max(d, 0.0)


def frechet_from_samples(a: np.ndarray, b: np.ndarray) -> float:
    """The Fréchet distance between Gaussians fitted to two sample sets (rows are samples).

    When the smaller set has n <= d samples, Tr (S_a S_b)^½ is computed in its n x n sample
    space: the nonzero eigenvalues of S_b^½ S_s S_b^½ are those of X_s S_b X_sᵀ / (n - 1), with
    X_s the centred smaller set. Same value, no d x d square root (112 x 112 instead of
    512 x 512 for seven real scans)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    small, big = (a, b) if len(a) <= len(b) else (b, a)
    n = len(small)
    if n < 2:
        raise ValueError("the Fréchet distance needs at least 2 samples per set")
    if n - 1 >= small.shape[1]:
        return frechet_distance(a.mean(0), np.cov(a, rowvar=False), b.mean(0),
                                np.cov(b, rowvar=False))
    xs = small - small.mean(axis=0)
    cov_big = np.cov(big, rowvar=False)
    m = xs @ cov_big @ xs.T / (n - 1)
    cross = np.sqrt(np.clip(np.linalg.eigvalsh((m + m.T) / 2), 0.0, None)).sum()
    d = float(((a.mean(0) - b.mean(0)) ** 2).sum() + (xs ** 2).sum() / (n - 1)
              + np.trace(cov_big) - 2.0 * cross)
    return max(d, 0.0)


def wasserstein_hist(a: np.ndarray, b: np.ndarray, edges: np.ndarray) -> float:
    """1-Wasserstein distance between two histograms on the same bins (in the bins' unit), each
    bin's mass at its centre: sum_k |F_a(k) - F_b(k)| (c_{k+1} - c_k), the gaps between bin
    centres (which are the bin widths only where the bins are equal)."""
    ca, cb = np.cumsum(normalised(a)), np.cumsum(normalised(b))
    edges = np.asarray(edges, np.float64)
    centres = (edges[1:] + edges[:-1]) / 2
    return float((np.abs(ca - cb)[:-1] * np.diff(centres)).sum())

