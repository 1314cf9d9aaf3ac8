"""Moments of per-position encoder features kept per scan, so that the mean and covariance of
any union of scans (a resample, a random subset) are pooled exactly without holding the cells,
and the Fréchet distances built on them."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from falsify.results.distances import frechet_distance

FLOOR_DRAWS = 10         # random subsets behind each synthetic set's frechet_floor


@dataclass
class ScanFeatures:
    """Encoder features of a batch of B scans: the tile means and, per scan, the moments of its
    valid cells (count, mean, covariance about its own mean), from which any union of scans'
    mean and covariance is pooled exactly (`pooled_moments`)."""

    tiles: np.ndarray           # (B * tiles a scan, C) float64: tile means
    counts: np.ndarray          # (B,) valid cells per scan
    means: np.ndarray           # (B, C) float64
    covs: np.ndarray            # (B, C, C) float32, ddof 1 (zeros for a scan with one cell);
    #                             float64 once `folded`

    def __len__(self) -> int:
        return len(self.counts)

    @staticmethod
    def concat(parts: list[ScanFeatures]) -> ScanFeatures:
        return ScanFeatures(*(np.concatenate([getattr(p, k) for p in parts])
                              for k in ("tiles", "counts", "means", "covs")))


def folded(parts: list[ScanFeatures]) -> ScanFeatures:
    """All scans' cell moments as one row (count, mean, covariance: what `pooled_moments` gives
    on them) with every tile kept: a set only pooled whole holds one C x C covariance, not one
    a scan (1 MB at C = 512)."""
    feats = ScanFeatures.concat(parts)
    mu, scatter, total = _scatter(feats, np.arange(len(feats)))
    cov = scatter / (total - 1) if total > 1 else np.zeros_like(scatter)
    return ScanFeatures(feats.tiles, np.array([int(total)], np.int64), mu[None], cov[None])


def cell_moments(f: np.ndarray, valid: np.ndarray) -> tuple[int, np.ndarray, np.ndarray]:
    """(count, mean, covariance) of the (C, h, w) feature grid `f` over the cells where the
    (h, w) mask `valid` holds."""
    cells = f.transpose(1, 2, 0)[valid].astype(np.float64)
    n = len(cells)
    if n == 0:
        return 0, np.zeros(f.shape[0]), np.zeros((f.shape[0],) * 2, np.float32)
    mu = cells.mean(axis=0)
    x = cells - mu
    cov = x.T @ x / (n - 1) if n > 1 else np.zeros((len(mu),) * 2)
    return n, mu, cov.astype(np.float32)


def pooled_moments(feats: ScanFeatures, idx: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray, int]:
    """Mean, covariance (ddof 1) and count of all valid cells of the scans `idx` (all if None):
    the parallel-axis sum of each scan's own covariance and its mean's offset."""
    idx = np.arange(len(feats)) if idx is None else np.asarray(idx)
    mu, scatter, total = _scatter(feats, idx)
    if total < 2:
        raise ValueError("the Fréchet distance needs at least 2 feature samples per set")
    return mu, scatter / (total - 1), total


def _scatter(feats: ScanFeatures, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Mean, scatter (sum of squared deviations) and count of the cells of scans `idx`: each
    scan's own scatter plus its mean's offset (the parallel-axis theorem); a zero mean for
    none."""
    n = feats.counts[idx].astype(np.float64)
    total = n.sum()
    mu = ((n[:, None] * feats.means[idx]).sum(axis=0) / total if total > 0
          else np.zeros(feats.means.shape[1]))
    off = feats.means[idx] - mu
    scatter = _weighted_sum(np.maximum(n - 1, 0), feats.covs, idx)
    scatter += (off * n[:, None]).T @ off
    return mu, scatter, int(total)


POOL_CHUNK = 64   # scans' covariances widened to float64 at a time (2 MB each at C = 512)


def _weighted_sum(weights: np.ndarray, covs: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """sum_k weights[k] * covs[idx[k]] in float64, POOL_CHUNK scans at a time: widening every
    scan's float32 covariance at once held 2 MB a scan on top of the 1 MB kept."""
    out = np.zeros(covs.shape[1:])
    for s in range(0, len(idx), POOL_CHUNK):
        out += np.einsum("b,bij->ij", weights[s:s + POOL_CHUNK],
                         covs[idx[s:s + POOL_CHUNK]].astype(np.float64))
    return out


def cell_frechet(a: ScanFeatures, b: ScanFeatures, ia: np.ndarray | None = None,
                 ib: np.ndarray | None = None) -> float:
    """The per-position Fréchet distance between the valid cells of scans `ia` of `a` and
    scans `ib` of `b` (all scans when None)."""
    ma, ca, _ = pooled_moments(a, ia)
    mb, cb, _ = pooled_moments(b, ib)
    return frechet_distance(ma, ca, mb, cb)


def frechet_floor(feats: ScanFeatures, scans: int, draws: int = FLOOR_DRAWS,
                  seed: int = 0) -> dict | None:
    """The per-position Fréchet distance between `scans` random scans of one set and the rest
    of it, over `draws` seeded draws: what sampling alone gives at a real set's scan count.
    None when the set has too few scans to leave two behind; a draw whose part holds blank
    scans only (no valid cell) has no distance and is counted in `undefined_draws`."""
    if scans < 1 or len(feats) < scans + 2:
        return None
    rng = np.random.default_rng(seed)
    values = []
    for _ in range(draws):
        p = rng.permutation(len(feats))
        a, b = p[:scans], p[scans:]
        if feats.counts[a].sum() >= 2 and feats.counts[b].sum() >= 2:   # else blank scans only
            values.append(cell_frechet(feats, feats, a, b))
    if not values:
        return None
    return {"scans": scans, "draws": draws, "seed": seed,
            "undefined_draws": draws - len(values),
            "mean": round(float(np.mean(values)), 6), "max": round(float(np.max(values)), 6)}
