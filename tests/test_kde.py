"""Tests for bayesrob.errors.kde: densities, bandwidth selectors, conditionals, sampling, gradients.

References are scipy's gaussian_kde (densities) and statsmodels' KDEMultivariate /
KDEMultivariateConditional with bw="cv_ml" (bandwidths). Every random draw is seeded; each
statistical tolerance is stated next to the assertion with the reason for it.
"""

from __future__ import annotations

import math
import warnings
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.stats import gaussian_kde

import bayesrob  # noqa: F401  (enables float64 before any array is made)
import bayesrob.errors.kde as kde_mod
from bayesrob.errors.kde import (
    KDE,
    BandwidthOnBoundWarning,
    ConditionalKDE,
    KDEError,
    command_spacing,
    conditional_kde_logpdf,
    guided_histogram_lookup,
    histogram_guide,
    histogram_lookup,
    j_loo,
    kde_logpdf,
    kernel_conditional_weights,
    loo_loglik,
)

sm_kd = pytest.importorskip("statsmodels.nonparametric.kernel_density")


class DiagGaussianKDE(gaussian_kde):
    """scipy's gaussian_kde with a fixed diagonal kernel covariance diag(bw^2).

    gaussian_kde scales the *data* covariance by a scalar factor, which cannot give a diagonal
    kernel for correlated data. Since scipy 1.10 both pdf and logpdf evaluate through
    ``self.cho_cov`` (the Cholesky factor of the kernel covariance), which
    ``_compute_covariance`` sets, so overriding that method is the supported hook.
    """

    def __init__(self, data: np.ndarray, bw: np.ndarray):
        self._bw = np.asarray(bw, dtype=float)
        super().__init__(data)

    def _compute_covariance(self) -> None:
        self.factor = 1.0
        self.covariance = np.diag(self._bw**2)
        self.cho_cov = np.diag(self._bw).astype(np.float64)
        self.log_det = 2 * np.log(np.diag(self.cho_cov * np.sqrt(2 * np.pi))).sum()


def _loo_lse(groups) -> jnp.ndarray:
    """Row-wise ``logsumexp_{j != i} sum_g -0.5 |(y_gi - y_gj) * inv_bw_g|^2``: the plain
    N x N leave-one-out sums of (y (N, d_g), inv_bw (d_g,)) column groups' product kernel."""
    logk = sum(-0.5 * jnp.sum(((y[:, None, :] - y[None, :, :]) * inv) ** 2, axis=-1)
               for y, inv in groups)
    return jax.scipy.special.logsumexp(jnp.where(jnp.eye(logk.shape[0], dtype=bool), -jnp.inf,
                                                 logk), axis=1)


def _neg_loo_loglik(log_bw: jnp.ndarray, y: jnp.ndarray) -> jnp.ndarray:
    """Negative leave-one-out log-likelihood ``-sum_i log f_-i(y_i)``, plainly."""
    n, d = y.shape
    lse = _loo_lse([(y, jnp.exp(-log_bw))])
    return -(jnp.sum(lse) - n * jnp.sum(log_bw) - n * jnp.log(n - 1.0)
             - 0.5 * n * d * kde_mod._LOG_2PI)


def _neg_cond_loo_loglik(log_bw: jnp.ndarray, y: jnp.ndarray, dx: int) -> jnp.ndarray:
    """Negative leave-one-out conditional log-likelihood ``-sum_i log f_-i(x_i | z_i)``, the
    plain reference the library's hand-written gradient is tested against. ``y`` holds [x, z]
    columns. As in statsmodels ``KDEMultivariateConditional.loo_likelihood``, both the joint
    f(x, z) and the marginal f(z) leave out point i, and the marginal uses only the z
    bandwidths, so the ratio is exactly the kernel conditional with point i removed."""
    n = y.shape[0]
    inv = jnp.exp(-log_bw)
    gx, gz = (y[:, :dx], inv[:dx]), (y[:, dx:], inv[dx:])
    ll = (jnp.sum(_loo_lse([gx, gz]) - _loo_lse([gz]))
          - n * jnp.sum(log_bw[:dx]) - 0.5 * n * dx * kde_mod._LOG_2PI)
    return -ll


def _skewed_bimodal(rng: np.random.Generator, n: int) -> np.ndarray:
    """4-D data with a log-normal column, a bimodal column and correlation."""
    x = rng.normal(size=(n, 4)) @ rng.normal(size=(4, 4))
    x[:, 0] = np.exp(0.6 * x[:, 0])
    x[: n // 2, 1] += 4.0
    return x


# --------------------------------------------------------------------------------------------
# Densities
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("d", "bw"),
    [(1, [0.3]), (2, [0.4, 0.15]), (4, [0.5, 0.2, 0.9, 0.35])],
)
def test_density_equals_scipy_gaussian_kde(d: int, bw: list[float]) -> None:
    rng = np.random.default_rng(10 + d)
    data = rng.normal(size=(80, d)) @ rng.normal(size=(d, d)) + 3.0
    pts = data[:25] + 0.7 * rng.normal(size=(25, d))
    ours = KDE.fit(data, bw)
    ref = DiagGaussianKDE(data.T, np.array(bw))
    # Both are exact float64 sums of the same Gaussians: only rounding separates them.
    np.testing.assert_allclose(np.asarray(ours.pdf(pts)), ref.pdf(pts.T), rtol=1e-10)
    np.testing.assert_allclose(np.asarray(ours.logpdf(pts)), ref.logpdf(pts.T), rtol=0, atol=1e-10)


def test_blocked_evaluation_equals_single_block(monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(1)
    data = jnp.asarray(rng.normal(size=(300, 3)))
    pts = jnp.asarray(rng.normal(size=(1001, 3)))
    bw = jnp.asarray([0.3, 0.4, 0.5])

    def everything():
        return [
            kde_logpdf(pts, data, bw),
            kde_mod._j_loo_normalised(jnp.float64(0.4), data, jnp.float64(0.0)),
        ]

    whole = everything()
    # 64-row blocks over 300 data points and 1001 query points: both leave a ragged last
    # block, which exercises the padding and its masking out of the sums.
    monkeypatch.setattr(kde_mod, "_BLOCK_ELEMENTS", 300 * 64)
    jax.clear_caches()
    blocked = everything()
    jax.clear_caches()
    for b, w in zip(blocked, whole, strict=True):
        np.testing.assert_allclose(np.asarray(b), np.asarray(w), rtol=1e-12, atol=1e-12)


def test_far_points_do_not_underflow() -> None:
    kde = KDE.fit(np.array([0.0, 1.0, 2.0]), 0.1)
    lp = float(kde.logpdf(np.array([50.0]))[0])
    # Nearest kernel dominates: log(1/3 N(50; 2, 0.1)).
    expected = math.log(1 / 3) - 0.5 * (48 / 0.1) ** 2 - math.log(0.1 * math.sqrt(2 * math.pi))
    assert lp == pytest.approx(expected, rel=1e-9)


def test_integrates_to_one_1d() -> None:
    kde = KDE.fit(np.random.default_rng(2).gamma(2.0, size=60), "loo-ml-diag")
    grid = np.linspace(-5, 15, 20001)
    # Trapezoid error on a smooth density with spacing 1e-3 is ~1e-8; tails beyond the grid
    # are > 20 bandwidths out.
    assert np.trapezoid(np.asarray(kde.pdf(grid)), grid) == pytest.approx(1.0, abs=1e-6)


def test_integrates_to_one_2d() -> None:
    data = np.random.default_rng(3).normal(size=(50, 2)) @ np.array([[1.0, 0.6], [0.0, 0.5]])
    kde = KDE.fit(data, "loo-ml-diag")
    gx = np.linspace(-6, 6, 401)
    gy = np.linspace(-5, 5, 401)
    xx, yy = np.meshgrid(gx, gy, indexing="ij")
    dens = np.asarray(kde.pdf(np.c_[xx.ravel(), yy.ravel()])).reshape(xx.shape)
    total = np.trapezoid(np.trapezoid(dens, gy, axis=1), gx)
    # 0.03 grid spacing against bandwidths ~0.3: trapezoid error ~1e-5.
    assert total == pytest.approx(1.0, abs=1e-4)


def test_single_point_and_1d_inputs() -> None:
    data = np.random.default_rng(4).normal(size=(30, 2))
    kde = KDE.fit(data, 0.5)
    assert kde.bandwidth.shape == (2,) and kde.selector == "fixed" and kde.h is None
    one = kde.logpdf(np.array([0.1, 0.2]))
    assert one.shape == ()
    assert float(one) == pytest.approx(float(kde.logpdf(np.array([[0.1, 0.2]]))[0]))
    kde1 = KDE.fit(data[:, 0], [0.4])
    assert kde1.data.shape == (30, 1)
    assert kde1.logpdf(np.linspace(-1, 1, 7)).shape == (7,)


# --------------------------------------------------------------------------------------------
# Bandwidth selectors
# --------------------------------------------------------------------------------------------


def _sm_bw(data: np.ndarray) -> np.ndarray:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return sm_kd.KDEMultivariate(data, "c" * data.shape[1], bw="cv_ml").bw


@pytest.mark.parametrize(
    "case",
    ["1d-gamma", "2d-correlated", "4d-skewed-bimodal", "4d-gaussian"],
)
def test_loo_ml_diag_matches_statsmodels_cv_ml(case: str) -> None:
    rng = np.random.default_rng(20)
    if case == "1d-gamma":
        data = rng.gamma(3.0, size=(120, 1))
    elif case == "2d-correlated":
        data = rng.normal(size=(150, 2)) @ np.array([[1.0, 0.8], [0.0, 0.4]])
    elif case == "4d-skewed-bimodal":
        data = _skewed_bimodal(rng, 200)
    else:
        data = rng.normal(size=(100, 4)) * np.array([1.0, 10.0, 0.1, 3.0])
    ours = KDE.fit(data, "loo-ml-diag")
    ref = _sm_bw(data)
    # Same objective; statsmodels stops Nelder-Mead at xtol=1e-3 in absolute bandwidth, which
    # is <= 0.5% of these widths, so 1% covers its stopping error.
    np.testing.assert_allclose(ours.bandwidth, ref, rtol=0.01)
    # And ours is at least as good an optimum of the shared objective.
    assert loo_loglik(data, ours.bandwidth) >= loo_loglik(data, ref) - 1e-6
    assert ours.selector == "loo-ml-diag" and not ours.on_bound


@pytest.mark.parametrize(
    ("n", "q", "dx", "conditional"),
    [(40, 4, 4, False), (256, 3, 3, False), (300, 4, 2, True), (513, 2, 1, True),
     (700, 4, 4, False)],
)
def test_hand_written_objective_equals_autodiff_of_the_plain_one(n, q, dx, conditional
                                                                  ) -> None:
    """The size-independent objective (zero-weight rows up to the buffer, tiles of
    ``_TILE``, hand-written gradient) against autodiff of the plain N x N LOO likelihood,
    for N below, at and past tile boundaries and buffers of two sizes.

    Tolerance: the same sums in another order (tile by tile, with running rescaling), so only
    rounding separates them: 1e-10 relative on the value; the gradient is ``n - sum(...)``,
    near zero close to the optimum, so it is compared to 1e-10 * n absolutely.
    """
    rng = np.random.default_rng(n)
    y = rng.normal(size=(n, q))
    y[: n // 2, 0] += 3.0
    y = (y - y.mean(axis=0)) / y.std(axis=0)
    theta = jnp.asarray(np.log(rng.uniform(0.1, 0.6, q)))
    plain = (partial(_neg_cond_loo_loglik, dx=dx) if conditional
             else _neg_loo_loglik)
    v0, g0 = jax.value_and_grad(plain)(theta, jnp.asarray(y))
    for cap in (kde_mod._capacity(n), 2 * kde_mod._capacity(n)):
        buf = jnp.asarray(np.pad(y, ((0, cap - n), (0, 0)), constant_values=7.0))
        v1, g1 = kde_mod._loo_value_and_grad_padded(theta, buf, jnp.asarray(n), dx=dx,
                                                   conditional=conditional)
        assert float(v1) == pytest.approx(float(v0), rel=1e-10, abs=0)
        np.testing.assert_allclose(np.asarray(g1), np.asarray(g0), rtol=0, atol=1e-10 * n)


def test_fits_of_new_sizes_reuse_one_compiled_objective(monkeypatch) -> None:
    """Fits at N = 150, 333 and 520 (4-D, and 2-D given 2-D) run one compiled program each,
    and their bandwidths do not depend on how far the data were padded."""
    rng = np.random.default_rng(3)
    data = _skewed_bimodal(rng, 520)
    KDE.fit(data[:150], "loo-ml-diag")
    ConditionalKDE.fit(data[:150, :2], data[:150, 2:], "kernel")
    compiled = dict(kde_mod._OBJECTIVES)
    fits = {n: KDE.fit(data[:n], "loo-ml-diag").bandwidth for n in (333, 520)}
    conds = {n: ConditionalKDE.fit(data[:n, :2], data[:n, 2:], "kernel").bandwidth
             for n in (333, 520)}
    assert kde_mod._OBJECTIVES == compiled
    # A buffer of 1024 rows instead of 4096: a different program, the same answers (the loops
    # never reach the extra zero-weight rows, so equal to the last bit in practice; 1e-12).
    monkeypatch.setattr(kde_mod, "_MIN_CAPACITY", 1024)
    for n in (333, 520):
        np.testing.assert_allclose(KDE.fit(data[:n], "loo-ml-diag").bandwidth, fits[n],
                                   rtol=1e-12)
        np.testing.assert_allclose(
            ConditionalKDE.fit(data[:n, :2], data[:n, 2:], "kernel").bandwidth, conds[n],
            rtol=1e-12)
    assert len(kde_mod._OBJECTIVES) == len(compiled) + 2


def test_loo_ml_single_width_is_the_grid_argmax() -> None:
    data = np.random.default_rng(6).normal(size=(40, 2)) * np.array([1.0, 5.0])
    kde = KDE.fit(data, "loo-ml")
    hs = np.linspace(0.2, 1.5, 1301)
    ll = [loo_loglik(data, h * data.std(axis=0)) for h in hs]
    # The refinement works to 1e-6 in log h; the grid step is 1e-3.
    assert kde.h == pytest.approx(hs[int(np.argmax(ll))], abs=2e-3)
    np.testing.assert_allclose(kde.bandwidth, kde.h * data.std(axis=0))
    assert kde.search_range == (0.05, 2.0) and not kde.on_bound


def test_loo_ml_equals_diag_in_1d() -> None:
    data = np.random.default_rng(7).normal(size=(70,))
    a = KDE.fit(data, "loo-ml").bandwidth
    b = KDE.fit(data, "loo-ml-diag").bandwidth
    # Same objective in 1-D, two optimisers: Brent to 1e-6 in log h, L-BFGS-B to gtol 1e-9.
    np.testing.assert_allclose(a, b, rtol=1e-4)


def _j_loo_double_loop(data: np.ndarray, h: float) -> float:
    """J_LOO exactly as printed, with D_-j built explicitly and NOTES item 3's normalisation."""
    sigma = data.std(axis=0)
    d = data.shape[1]

    def pdf(x, ds):
        u = (x - ds) / sigma / h
        sgf = np.exp(-0.5 * np.sum(u * u, axis=1)) / (2 * np.pi * h * h) ** (d / 2)
        return sgf.sum() / len(ds) / np.prod(sigma)

    total = 0.0
    for i in range(len(data)):
        for j in range(len(data)):
            total += (pdf(data[i], data) - pdf(data[i], np.delete(data, j, axis=0))) ** 2
    return total


@pytest.mark.parametrize("h", [0.1, 0.5, 2.0])
def test_j_loo_matches_double_loop(h: float) -> None:
    data = np.random.default_rng(8).normal(size=(7, 2)) * np.array([2.0, 0.5])
    assert j_loo(data, h) == pytest.approx(_j_loo_double_loop(data, h), rel=1e-12)


@pytest.mark.parametrize("d", [1, 2, 4])
def test_paper_selector_lands_on_bound_for_16_gaussian_points(d: int) -> None:
    data = np.random.default_rng(30 + d).normal(size=(16, d))
    # The criterion is monotone (NOTES): every pdf -> 0 as h grows.
    hs = np.geomspace(0.01, 100.0, 25)
    assert np.all(np.diff([j_loo(data, h) for h in hs]) < 0)
    with pytest.warns(BandwidthOnBoundWarning, match="bound"):
        kde = KDE.fit(data, "paper", h_range=(0.05, 2.0))
    assert kde.on_bound and kde.selector == "paper"
    assert kde.h == pytest.approx(2.0)
    np.testing.assert_allclose(kde.bandwidth, 2.0 * data.std(axis=0))


def test_paper_selector_warning_can_be_silenced() -> None:
    data = np.random.default_rng(9).normal(size=(16, 2))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        kde = KDE.fit(data, "paper", h_range=(0.1, 0.7), n_grid=9, warn_on_bound=False)
    assert kde.on_bound and kde.h == pytest.approx(0.7) and kde.search_range == (0.1, 0.7)


def test_fixed_bandwidths_validated() -> None:
    data = np.random.default_rng(11).normal(size=(20, 3))
    np.testing.assert_allclose(KDE.fit(data, [0.1, 0.2, 0.3]).bandwidth, [0.1, 0.2, 0.3])
    for bad in ([0.1, 0.2], -1.0, 0.0, [0.1, np.nan, 0.2]):
        with pytest.raises(KDEError):
            KDE.fit(data, bad)
    with pytest.raises(ValueError, match="unknown bandwidth selector"):
        KDE.fit(data, "scott")
    with pytest.raises(ValueError, match="h_range"):
        KDE.fit(data, "paper", h_range=(1.0, 0.5))


@pytest.mark.parametrize(
    ("data", "match"),
    [
        (np.array([[1.0, 2.0]]), "at least 2"),
        (np.ones((5, 2)), "identical"),
        (np.c_[np.arange(5.0), np.full(5, 3.0)], "zero variance"),
        (np.array([0.0, 1.0, np.nan]), "NaN"),
        (np.array([0.0, 1.0, np.inf]), "infinite"),
        (np.zeros((2, 2, 2)), "shape"),
    ],
)
def test_degenerate_data_raises(data: np.ndarray, match: str) -> None:
    with pytest.raises(KDEError, match=match) as err:
        KDE.fit(data, "loo-ml-diag")
    assert isinstance(err.value, ValueError)


# --------------------------------------------------------------------------------------------
# Conditional densities
# --------------------------------------------------------------------------------------------


def _cond_data(seed: int, n: int = 100) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    z = rng.normal(size=(n, 2))
    x = np.c_[z[:, 0] + 0.3 * rng.normal(size=n), z[:, 1] ** 2 + 0.3 * rng.normal(size=n)]
    return x, z


def _sm_cond(x: np.ndarray, z: np.ndarray, bw="cv_ml"):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return sm_kd.KDEMultivariateConditional(x, z, "cc", "cc", bw=bw)


def _cond_objective(x: np.ndarray, z: np.ndarray, bw: np.ndarray) -> float:
    j = np.c_[x, z]
    s = j.std(axis=0)
    y = jnp.asarray((j - j.mean(axis=0)) / s)
    return float(_neg_cond_loo_loglik(jnp.log(jnp.asarray(bw / s)), y, dx=x.shape[1]))


def test_kernel_conditional_matches_statsmodels_cv_ml() -> None:
    x, z = _cond_data(0)
    ours = ConditionalKDE.fit(x, z, "kernel")
    ref = _sm_cond(x, z)
    # As for the unconditional test: Nelder-Mead's absolute xtol=1e-3 is < 1.2% of the
    # narrowest width here (0.09) and < 0.5% of the others.
    np.testing.assert_allclose(ours.bandwidth, ref.bw, rtol=0.012)
    np.testing.assert_allclose(ours.bw_x, ours.bandwidth[:2])
    # Same density formula f(x, z) / f(z) given the same bandwidths.
    pts_x, pts_z = x[:20] + 0.1, z[:20] - 0.1
    np.testing.assert_allclose(
        np.asarray(ours.pdf(pts_x, pts_z)),
        _sm_cond(x, z, bw=ours.bandwidth).pdf(pts_x, pts_z),
        rtol=1e-10,
    )


def test_kernel_conditional_never_worse_than_statsmodels() -> None:
    # Data where the conditional likelihood has several local maxima (the normal-reference
    # start alone stops in a worse one than statsmodels does); our multi-start L-BFGS-B and
    # statsmodels' single Nelder-Mead may stop in different maxima, but ours must be as high.
    rng = np.random.default_rng(6)
    z = rng.normal(size=(100, 2))
    x = np.c_[np.sin(2 * z[:, 0]), z[:, 0] * z[:, 1]] + np.array([0.2, 0.5]) * rng.normal(
        size=(100, 2)
    )
    ours = ConditionalKDE.fit(x, z, "kernel", warn_on_bound=False)
    ref = _sm_cond(x, z).bw
    assert _cond_objective(x, z, ours.bandwidth) <= _cond_objective(x, z, np.abs(ref)) + 1e-6


def test_kernel_conditional_integrates_to_one_over_x() -> None:
    x, z = _cond_data(2, 60)
    cond = ConditionalKDE.fit(x, z, "kernel", bandwidth=[0.25, 0.4, 0.3, 0.2])
    gx = np.linspace(-5, 5, 301)
    gy = np.linspace(-3, 9, 301)
    xx, yy = np.meshgrid(gx, gy, indexing="ij")
    grid = np.c_[xx.ravel(), yy.ravel()]
    for zq in ([0.0, 0.0], [1.0, -1.5]):
        dens = np.asarray(cond.pdf(grid, np.array(zq))).reshape(xx.shape)
        # Grid spacing 0.033-0.04 against widths >= 0.1: trapezoid error well below 1e-3.
        assert np.trapezoid(np.trapezoid(dens, gy, axis=1), gx) == pytest.approx(1.0, abs=1e-3)


def test_one_dimensional_conditionals_integrate_to_one() -> None:
    rng = np.random.default_rng(16)
    z = rng.normal(size=(50,))
    x = np.sin(2 * z) + 0.3 * rng.normal(size=(50,))
    grid = np.linspace(-6, 6, 6001)
    kern = ConditionalKDE.fit(x, z, "kernel", bandwidth=[0.2, 0.3])
    # Spacing 2e-3 against widths >= 0.2: trapezoid error ~1e-7.
    assert np.trapezoid(np.asarray(kern.pdf(grid, np.array([0.4]))), grid) == pytest.approx(
        1.0, abs=1e-6
    )
    hist = ConditionalKDE.fit(x, z, "histogram", bandwidth="loo-ml")
    dens = np.asarray(hist.pdf(grid, np.array([0.4])))
    # Piecewise constant: the trapezoid rule errs only at the 11 bin edges, ~spacing/width each.
    assert np.trapezoid(dens, grid) == pytest.approx(1.0, abs=5e-3)
    assert hist.joint.selector == "loo-ml" and hist.joint.h is not None


def test_kernel_conditional_broadcasting_and_weights() -> None:
    x, z = _cond_data(3, 50)
    cond = ConditionalKDE.fit(x, z, "kernel", bandwidth=[0.3, 0.4, 0.5, 0.6])
    assert cond.selector == "fixed"
    xs = x[:7] + 0.05
    zq = np.array([0.2, -0.3])
    one_z = np.asarray(cond.logpdf(xs, zq))
    paired = np.asarray(cond.logpdf(xs, np.repeat(zq[None], 7, axis=0)))
    np.testing.assert_allclose(one_z, paired, rtol=1e-12)
    assert cond.logpdf(xs[0], zq).shape == ()
    w = np.asarray(kernel_conditional_weights(np.stack([zq, zq + 1]), z, cond.bw_z))
    assert w.shape == (2, 50)
    np.testing.assert_allclose(w.sum(axis=1), 1.0, rtol=1e-12)
    k = np.exp(-0.5 * np.sum(((zq - z) / cond.bw_z) ** 2, axis=1))
    np.testing.assert_allclose(w[0], k / k.sum(), rtol=1e-10)
    # Far from every z_i the weights still normalise (softmax of log-kernels, no 0/0).
    far = np.asarray(kernel_conditional_weights(np.array([80.0, 80.0]), z, cond.bw_z))
    assert np.all(np.isfinite(far)) and far.sum() == pytest.approx(1.0)
    # The mixture form equals the pure conditional log-density.
    mix = np.log(
        np.sum(w[0] * np.prod(np.exp(-0.5 * ((xs[0] - x) / cond.bw_x) ** 2), axis=1))
        / np.prod(cond.bw_x * math.sqrt(2 * math.pi))
    )
    assert float(one_z[0]) == pytest.approx(mix, rel=1e-10)


def test_histogram_conditional_normalises_over_x() -> None:
    x, z = _cond_data(4, 80)
    with pytest.warns(BandwidthOnBoundWarning):
        cond = ConditionalKDE.fit(x, z, "histogram")
    assert cond.selector == "paper" and cond.on_bound
    assert list(cond.bins) == [10, 10, 10, 10]
    # Default grid spans the data range.
    joint = np.c_[x, z]
    np.testing.assert_allclose(cond.grid_lo, joint.min(axis=0))
    np.testing.assert_allclose(cond.grid_lo + 10 * cond.bin_widths, joint.max(axis=0))
    cx = [cond.grid_lo[k] + (np.arange(10) + 0.5) * cond.bin_widths[k] for k in range(2)]
    xx, yy = np.meshgrid(*cx, indexing="ij")
    centres = np.c_[xx.ravel(), yy.ravel()]
    vol = np.prod(cond.bin_widths[:2])
    for zq in (z[0], z[5], np.array([0.1, 0.2])):
        # Exact by construction: a sum of the normalised table over the x bins.
        total = float(np.sum(np.asarray(cond.pdf(centres, zq)))) * vol
        assert total == pytest.approx(1.0, rel=1e-12)
    # Outside the grid: the documented floor.
    out = cond.logpdf(np.array([1e3, 0.0]), z[0])
    assert float(out) == pytest.approx(math.log(cond.floor))


def test_histogram_conditional_with_paper_bin_widths_centres_on_mean() -> None:
    x, z = _cond_data(5, 60)
    widths = [0.5, 0.5, 0.4, 0.4]
    cond = ConditionalKDE.fit(x, z, "histogram", bandwidth="loo-ml-diag", bin_widths=widths)
    mean = np.c_[x, z].mean(axis=0)
    np.testing.assert_allclose(cond.grid_lo + 5 * np.array(widths), mean)
    gx = np.linspace(cond.grid_lo[0] - 1, cond.grid_lo[0] + 6, 1401)
    gy = np.linspace(cond.grid_lo[1] - 1, cond.grid_lo[1] + 6, 1401)
    xx, yy = np.meshgrid(gx, gy, indexing="ij")
    dens = np.asarray(cond.pdf(np.c_[xx.ravel(), yy.ravel()], mean[2:])).reshape(xx.shape)
    # A piecewise-constant density: trapezoid error only at the bin edges, ~ spacing/width.
    total = np.trapezoid(np.trapezoid(dens, gy, axis=1), gx)
    assert total == pytest.approx(1.0, abs=2e-2)
    with pytest.raises(NotImplementedError):
        cond.weights(mean[2:])


def test_guided_histogram_lookup_has_the_tables_value_and_a_guiding_gradient() -> None:
    """NUTS on the paper's COND relies on this: exact table values, a finite gradient that
    follows the table inside the grid and points back into it outside."""
    x, z = _cond_data(6, 80)
    cond = ConditionalKDE.fit(x, z, "histogram", bandwidth="loo-ml")
    bins, floor = tuple(int(b) for b in cond.bins), math.log(cond.floor)
    args = (jnp.asarray(cond.log_table), jnp.asarray(cond.grid_lo),
            jnp.asarray(cond.bin_widths))
    lo, hi = cond.grid_lo[:2], cond.grid_lo[:2] + 10 * cond.bin_widths[:2]
    rng = np.random.default_rng(1)
    pts = jnp.asarray(rng.uniform(lo - 0.5 * (hi - lo), hi + 0.5 * (hi - lo), (400, 2)))
    zq = jnp.broadcast_to(jnp.asarray(np.median(z, axis=0)), pts.shape)

    def guided(p):
        return guided_histogram_lookup(p, zq, *args, bins, floor, 0.25)

    np.testing.assert_array_equal(np.asarray(guided(pts)),
                                  np.asarray(histogram_lookup(pts, zq, *args, bins, floor)))
    grad = np.asarray(jax.grad(lambda p: guided(p).sum())(pts))
    assert np.all(np.isfinite(grad))
    guide_grad = jax.grad(lambda p: histogram_guide(p, zq, *args, bins, 0.25).sum())(pts)
    np.testing.assert_array_equal(grad, np.asarray(guide_grad))
    # Outside the grid the gradient points back towards it.
    outside = np.any((np.asarray(pts) < lo) | (np.asarray(pts) > hi), axis=1)
    towards = np.clip(np.asarray(pts), lo, hi) - np.asarray(pts)
    assert outside.sum() > 100
    assert np.all(np.sum(grad[outside] * towards[outside], axis=1) > 0)
    # Inside, the guide interpolates the table: equal to it at every bin centre.
    cx = [lo[k] + (np.arange(10) + 0.5) * cond.bin_widths[k] for k in range(2)]
    centres = jnp.asarray(np.stack(np.meshgrid(*cx, indexing="ij"), -1).reshape(-1, 2))
    zc = jnp.broadcast_to(zq[0], centres.shape)
    np.testing.assert_allclose(np.asarray(histogram_guide(centres, zc, *args, bins, 0.25)),
                               np.asarray(histogram_lookup(centres, zc, *args, bins, floor)),
                               rtol=1e-12)


def test_conditional_input_errors() -> None:
    x, z = _cond_data(6, 30)
    with pytest.raises(KDEError, match="rows"):
        ConditionalKDE.fit(x, z[:-1])
    with pytest.raises(ValueError, match="method"):
        ConditionalKDE.fit(x, z, "copula")
    with pytest.raises(KDEError, match="zero variance"):
        ConditionalKDE.fit(x, np.c_[z[:, 0], np.zeros(30)])


# --------------------------------------------------------------------------------------------
# Gradients
# --------------------------------------------------------------------------------------------


def test_logpdf_is_differentiable() -> None:
    data = _skewed_bimodal(np.random.default_rng(14), 60)
    kde = KDE.fit(data, [0.3, 0.8, 0.5, 0.4])
    p0 = jnp.asarray(data[3] + 0.2)

    def f(p):
        return kde.logpdf(p)

    g = np.asarray(jax.grad(f)(p0))
    assert np.all(np.isfinite(g))
    eps = 1e-6
    fd = [
        (float(f(p0.at[k].add(eps))) - float(f(p0.at[k].add(-eps)))) / (2 * eps) for k in range(4)
    ]
    # Central differences: truncation ~eps^2 * f''' and rounding ~1e-16 / eps = 1e-10.
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-7)
    # Also under jit, and through the pure function w.r.t. the bandwidth.
    assert float(jax.jit(f)(p0)) == pytest.approx(float(f(p0)), rel=1e-14)
    gb = jax.grad(lambda b: kde_logpdf(p0[None], jnp.asarray(data), b)[0])(
        jnp.asarray(kde.bandwidth)
    )
    assert np.all(np.isfinite(np.asarray(gb)))


def test_conditional_logpdf_is_differentiable() -> None:
    x, z = _cond_data(15, 40)
    cond = ConditionalKDE.fit(x, z, "kernel", bandwidth=[0.3, 0.4, 0.3, 0.3])

    def f(xq, zq):
        return conditional_kde_logpdf(
            xq[None], zq[None], jnp.asarray(x), jnp.asarray(z), cond.bw_x, cond.bw_z
        )[0]

    xq, zq = jnp.asarray([0.1, 0.5]), jnp.asarray([0.2, -0.4])
    gx, gz = jax.grad(f, argnums=(0, 1))(xq, zq)
    eps = 1e-6
    for k in range(2):
        fd_x = (float(f(xq.at[k].add(eps), zq)) - float(f(xq.at[k].add(-eps), zq))) / (2 * eps)
        fd_z = (float(f(xq, zq.at[k].add(eps))) - float(f(xq, zq.at[k].add(-eps)))) / (2 * eps)
        # Same finite-difference error budget as test_logpdf_is_differentiable.
        assert float(gx[k]) == pytest.approx(fd_x, rel=1e-6, abs=1e-7)
        assert float(gz[k]) == pytest.approx(fd_z, rel=1e-6, abs=1e-7)


# ------------------------------------------------------------------ command-bandwidth floor


def _grid_commands(n: int, step: float, jitter: float, rng: np.random.Generator) -> np.ndarray:
    g = 1300.0 + step * np.arange(n)
    return np.array([(a, b) for a in g for b in g]) + rng.normal(0.0, jitter, (n * n, 2))


def test_command_spacing_is_the_median_nearest_neighbour_gap() -> None:
    u = _grid_commands(4, 150.0, 0.0, np.random.default_rng(0))
    assert command_spacing(u) == pytest.approx(150.0)
    # repeated commands are one sampled value, not a zero gap
    assert command_spacing(np.vstack([u, u])) == pytest.approx(150.0)
    assert command_spacing(u[:1]) == 0.0


def test_command_floor_stops_widths_below_the_grid_spacing() -> None:
    """A 4 x 4 command grid whose errors follow the grid column: leave-one-out alone picks a
    command width far below the 150 us spacing (it conditions each point on its column's
    neighbours); with the floor every command width is at least one spacing."""
    rng = np.random.default_rng(3)
    u = _grid_commands(4, 150.0, 2.0, rng)
    x = np.c_[0.004 * np.sin(u[:, 0] / 120.0), 0.003 * np.cos(u[:, 0] / 90.0)]
    x = x + rng.normal(0.0, 3e-4, x.shape)
    spacing = command_spacing(u)
    free = ConditionalKDE.fit(x, u, "kernel", warn_on_bound=False)
    floored = ConditionalKDE.fit(x, u, "kernel", warn_on_bound=False, z_spacing_floor=1.0)
    assert free.bw_z.min() < 0.5 * spacing
    assert np.all(floored.bw_z >= spacing * (1 - 1e-9))


def test_command_floor_keeps_structure_sampled_densely() -> None:
    """On a 12 x 12 grid 40 us apart the floor (one spacing) is narrower than the errors'
    structure: at a command between grid points the conditional still follows it. Tolerance:
    the smoothing bias of a 40 us kernel on cos(u / 90) is about 4e-4 rad; the marginal mean
    is off by more than 2e-3, so the check separates conditioning from ignoring u. Ending on
    the floor is a choice, not a search that ran out of range: no bound is reported."""
    rng = np.random.default_rng(3)
    u = _grid_commands(12, 40.0, 1.0, rng)
    x = np.c_[0.004 * np.sin(u[:, 0] / 120.0), 0.003 * np.cos(u[:, 1] / 90.0)]
    x = x + rng.normal(0.0, 3e-4, x.shape)
    k = ConditionalKDE.fit(x, u, "kernel", warn_on_bound=False, z_spacing_floor=1.0)
    new = np.array([1300.0 + 5.5 * 40.0, 1300.0 + 3.5 * 40.0])
    truth = np.array([0.004 * np.sin(new[0] / 120.0), 0.003 * np.cos(new[1] / 90.0)])
    mean = np.asarray(k.weights(new)) @ x
    assert np.all(np.abs(mean - truth) < 6e-4), (mean, truth)
    assert np.abs(x.mean(axis=0) - truth).max() > 2e-3
    assert not k.on_bound
