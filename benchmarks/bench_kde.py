"""Benchmark bayesrob.kde against statsmodels and scipy; one JSON line per case.

    python benchmarks/bench_kde.py [--quick]

Cases:
  loo-ml-diag         KDE.fit(bandwidth="loo-ml-diag") vs statsmodels
                      KDEMultivariate(bw="cv_ml"), 4-D skewed/bimodal data, N = 200 and 1000.
  kernel-conditional  ConditionalKDE.fit(method="kernel") vs statsmodels
                      KDEMultivariateConditional(bw="cv_ml"), 2-D x | 2-D z, N = 1000.
  logpdf              KDE.logpdf at 100,000 points from N = 10,000 in 4-D vs
                      scipy.stats.gaussian_kde.logpdf with the same diagonal bandwidth.

Our side runs in a fresh subprocess per case, so ``ours_compile_s`` (the first call) really
includes tracing and XLA compilation and nothing is cached from an earlier case; ``ours_s`` is
the median of repeated calls in that process. The reference runs once in the parent process
(statsmodels' cv_ml takes tens of seconds). ``--quick`` shrinks the problem sizes.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
import warnings

import numpy as np


def skewed_bimodal(n: int, seed: int = 0) -> np.ndarray:
    """4-D data: correlated, one log-normal column, one bimodal column."""
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, 4)) @ rng.normal(size=(4, 4))
    x[:, 0] = np.exp(0.6 * x[:, 0])
    x[: n // 2, 1] += 4.0
    return x


def conditional_data(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """x depends non-linearly on z, as joint errors depend on servo commands."""
    rng = np.random.default_rng(seed)
    z = rng.normal(size=(n, 2))
    x = np.c_[np.sin(2 * z[:, 0]), z[:, 1] ** 2] + 0.3 * rng.normal(size=(n, 2))
    return x, z


def logpdf_data(n: int, m: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    data = skewed_bimodal(n, seed)
    pts = data[rng.integers(0, n, m)] + rng.normal(size=(m, 4)) * data.std(axis=0) * 0.3
    bw = 0.15 * data.std(axis=0)
    return data, pts, bw


# --------------------------------------------------------------------------------------------
# Our side (runs in a fresh subprocess)
# --------------------------------------------------------------------------------------------


def _worker(case: str, n: int, m: int, repeats: int) -> dict:
    import jax
    import jax.numpy as jnp

    import bayesrob  # noqa: F401
    from bayesrob.kde import KDE, ConditionalKDE

    jnp.zeros(1).block_until_ready()  # backend start-up is not compilation
    warnings.simplefilter("ignore")
    if case == "loo-ml-diag":
        data = skewed_bimodal(n)

        def run():
            return KDE.fit(data, "loo-ml-diag").bandwidth

    elif case == "kernel-conditional":
        x, z = conditional_data(n)

        def run():
            return ConditionalKDE.fit(x, z, "kernel").bandwidth

    elif case == "logpdf":
        data, pts, bw = logpdf_data(n, m)
        kde = KDE.fit(data, bw)

        def run():
            return np.asarray(jax.block_until_ready(kde.logpdf(pts)))

    else:
        raise ValueError(case)
    t0 = time.perf_counter()
    out = run()
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        run()
        times.append(time.perf_counter() - t0)
    return {"first": first, "median": statistics.median(times), "out": np.asarray(out).tolist()}


def run_ours(case: str, n: int, m: int = 0, repeats: int = 5) -> dict:
    cmd = [sys.executable, __file__, "--worker", case, str(n), str(m), str(repeats)]
    proc = subprocess.run(cmd, capture_output=True, text=True, check=True)
    return json.loads(proc.stdout.strip().splitlines()[-1])


# --------------------------------------------------------------------------------------------
# References
# --------------------------------------------------------------------------------------------


def ref_loo_ml_diag(n: int) -> tuple[float, np.ndarray]:
    from statsmodels.nonparametric.kernel_density import KDEMultivariate

    data = skewed_bimodal(n)
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        bw = KDEMultivariate(data, "cccc", bw="cv_ml").bw
    return time.perf_counter() - t0, bw


def ref_conditional(n: int) -> tuple[float, np.ndarray]:
    from statsmodels.nonparametric.kernel_density import KDEMultivariateConditional

    x, z = conditional_data(n)
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        bw = KDEMultivariateConditional(x, z, "cc", "cc", bw="cv_ml").bw
    return time.perf_counter() - t0, bw


def ref_logpdf(n: int, m: int) -> tuple[float, np.ndarray]:
    from scipy.stats import gaussian_kde

    class DiagGaussianKDE(gaussian_kde):
        """gaussian_kde with kernel covariance diag(bw^2) (scipy evaluates via cho_cov)."""

        def __init__(self, d, bw):
            self._bw = bw
            super().__init__(d)

        def _compute_covariance(self):
            self.factor = 1.0
            self.covariance = np.diag(self._bw**2)
            self.cho_cov = np.diag(self._bw).astype(np.float64)
            self.log_det = 2 * np.log(np.diag(self.cho_cov * np.sqrt(2 * np.pi))).sum()

    data, pts, bw = logpdf_data(n, m)
    ref = DiagGaussianKDE(data.T, bw)
    t0 = time.perf_counter()
    out = ref.logpdf(pts.T)
    return time.perf_counter() - t0, out


def line(case, n, d, ours, ref_s, diff, **extra) -> str:
    rec = {
        "case": case,
        "n": n,
        "d": d,
        "ours_s": round(ours["median"], 4),
        "ours_compile_s": round(ours["first"], 4),
        "reference_s": round(ref_s, 3),
        "speedup_excl_compile": round(ref_s / ours["median"], 1),
        "speedup_incl_compile": round(ref_s / ours["first"], 1),
        "max_rel_bw_diff": diff,
        **extra,
        "load1": round(os.getloadavg()[0], 2),
    }
    return json.dumps(rec)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="smaller problems")
    ap.add_argument("--worker", nargs=4, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        case, n, m, repeats = args.worker
        print(json.dumps(_worker(case, int(n), int(m), int(repeats))))
        return

    diag_ns = (200, 400) if args.quick else (200, 1000)
    cond_n = 300 if args.quick else 1000
    lp_n, lp_m = (2000, 20_000) if args.quick else (10_000, 100_000)

    for n in diag_ns:
        ours = run_ours("loo-ml-diag", n)
        ref_s, ref_bw = ref_loo_ml_diag(n)
        diff = float(np.max(np.abs(np.array(ours["out"]) / ref_bw - 1)))
        print(line("loo-ml-diag", n, 4, ours, ref_s, round(diff, 5)), flush=True)

    ours = run_ours("kernel-conditional", cond_n)
    ref_s, ref_bw = ref_conditional(cond_n)
    diff = float(np.max(np.abs(np.array(ours["out"]) / ref_bw - 1)))
    print(
        line("kernel-conditional", cond_n, 4, ours, ref_s, round(diff, 5), dx=2, dz=2), flush=True
    )

    ours = run_ours("logpdf", lp_n, lp_m, repeats=3)
    ref_s, ref_out = ref_logpdf(lp_n, lp_m)
    lp_diff = float(np.max(np.abs(np.array(ours["out"]) - ref_out)))
    print(
        line("logpdf", lp_n, 4, ours, ref_s, 0.0, m=lp_m, max_abs_logpdf_diff=lp_diff),
        flush=True,
    )


if __name__ == "__main__":
    main()
