"""The density of a prediction's draws (``scipy.stats.gaussian_kde``, Scott's rule) and its
highest-density regions (HDRs).

The region holding mass m is the densest points until their weights reach m, its size the
volume they stand for: draws from the KDE each stand for 1/K of the mass and 1 / (K p) of the
volume (the Monte Carlo vol{p > c} = E_p[1{p > c} / p]); a grid's cells for their own mass
and area (the paper's count). A point's HDR *level* is the mass denser than it: uniform on
(0, 1) over real outcomes when the prediction is calibrated.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.stats import gaussian_kde

__all__ = ["VOLUME_POINTS", "kernels", "kde_log_density", "region_sizes", "density_levels",
           "hdr_sizes", "hdr_levels"]

VOLUME_POINTS = 800  # draws from the KDE at which the region estimators are evaluated


def kernels(draws: np.ndarray) -> list[gaussian_kde]:
    """The KDE of draws (S, T, dim) at each target: T ``gaussian_kde`` (Scott's rule)."""
    draws = np.asarray(draws, float)
    return [gaussian_kde(draws[:, t].T) for t in range(draws.shape[1])]


def kde_log_density(draws: np.ndarray | Sequence[gaussian_kde], points: np.ndarray
                    ) -> np.ndarray:
    """Log density (per mm^dim) of the KDE of draws (S, T, dim) (or their :func:`kernels`)
    at points (T, dim) -> (T,), or (K, T, dim) -> (K, T)."""
    kdes = draws if isinstance(draws, list) else kernels(draws)
    pts = np.asarray(points, float)
    if pts.ndim == 2:
        return np.array([k.logpdf(p[:, None])[0] for k, p in zip(kdes, pts, strict=True)])
    return np.stack([k.logpdf(pts[:, t].T) for t, k in enumerate(kdes)], axis=1)


def region_sizes(log_density: np.ndarray, masses: Sequence[float] = (0.5, 0.9),
                 weights: np.ndarray | None = None,
                 volume: float | np.ndarray | None = None) -> np.ndarray:
    """Sizes (len(masses), T) of the highest-density regions of T predictions, each given by
    K points (K, T): their log densities, the mass each stands for (``weights``; None: 1/K
    each, points drawn from the prediction) and the volume (None: weight / density)."""
    ld = np.asarray(log_density, float)
    order = np.argsort(-ld, axis=0, kind="stable")
    ranked = np.take_along_axis(ld, order, axis=0)
    if weights is None:
        # counted, not summed in 1/K steps: the 90% region of 800 draws is 720 of them
        held = np.arange(1, ld.shape[0] + 1, dtype=float)[:, None] * np.ones_like(ld)
        need = [m * ld.shape[0] for m in masses]
        vol = np.exp(-ranked) / ld.shape[0] if volume is None else volume
    else:
        w = np.take_along_axis(np.asarray(weights, float), order, axis=0)
        held, need = np.cumsum(w, axis=0), list(masses)
        vol = w * np.exp(-ranked) if volume is None else volume
    total = np.cumsum(np.broadcast_to(vol, ld.shape), axis=0)
    return np.asarray([np.take_along_axis(total, np.argmax(held >= m, axis=0)[None], 0)[0]
                       for m in need])


def density_levels(ref_log_density: np.ndarray, log_density: np.ndarray,
                   weights: np.ndarray | None = None) -> np.ndarray:
    """The HDR level of points of log density (T,) or (M, T): the mass of the reference points
    (K, T; each standing for ``weights`` (K, T), None: 1/K) denser than each."""
    ref = np.asarray(ref_log_density, float)
    at = np.asarray(log_density, float)
    denser = ref > at[None] if at.ndim == 1 else ref[None] > at[:, None]
    if weights is None:
        return np.mean(denser, axis=-2)
    return np.sum(np.where(denser, weights, 0.0), axis=-2)


def _kde_draws(draws: np.ndarray, kdes: Sequence[gaussian_kde]) -> np.ndarray:
    """VOLUME_POINTS draws from the KDE itself: the region estimators are expectations under
    the KDE, not under the draws it smooths."""
    sub = np.asarray(draws, float)[:VOLUME_POINTS]
    chol = np.stack([np.linalg.cholesky(k.covariance) for k in kdes])  # (T, dim, dim)
    z = np.random.default_rng(0).standard_normal(sub.shape)
    return sub + np.einsum("tij,ktj->kti", chol, z)


def hdr_levels(draws: np.ndarray, points: np.ndarray) -> np.ndarray:
    """The HDR level of each point under the KDE of draws (S, T, dim): (T,) for points
    (T, dim), (K, T) for (K, T, dim)."""
    kdes = kernels(draws)
    ref = kde_log_density(kdes, _kde_draws(draws, kdes))
    return density_levels(ref, kde_log_density(kdes, points))


def hdr_sizes(draws: np.ndarray, masses: Sequence[float] = (0.5, 0.9)) -> np.ndarray:
    """Volumes (areas in 2-D) (len(masses), T) of the highest-density regions of the KDE of
    draws (S, T, dim)."""
    kdes = kernels(draws)
    return region_sizes(kde_log_density(kdes, _kde_draws(draws, kdes)), masses)
