"""Benchmark bayesrob.errors.kde against statsmodels and scipy; one JSON line per case.

    python benchmarks/bench_kde.py [--quick] [--case CASE ...] [--sizes N ...]

Cases:
  loo-ml-diag         KDE.fit(bandwidth="loo-ml-diag") vs statsmodels
                      KDEMultivariate(bw="cv_ml"), 4-D skewed/bimodal data, N = 700, 1000, 1300.
  kernel-conditional  ConditionalKDE.fit(method="kernel") vs statsmodels
                      KDEMultivariateConditional(bw="cv_ml"), 2-D x | 2-D z, same N.
  logpdf              KDE.logpdf at 100,000 points from N = 10,000 in 4-D vs
                      scipy.stats.gaussian_kde.logpdf with the same diagonal bandwidth.

For the two fits, every N is timed four ways, each against statsmodels at that N measured in
the same run (it runs once, in the parent process; cv_ml takes tens of seconds):

- ``ours_first_in_process_s``: in one process, after an earlier fit at another size (N = 200),
  the first fit at this N. Nothing is recompiled for a new N, so this is the speed wherever
  data sizes vary; ``ours_s`` is the median of repeated fits at the same N.
- ``ours_fresh_warm_cache_s``: the first fit in a fresh process whose persistent compilation
  cache was filled by the earlier process. Interpreter start, imports and JAX's backend
  start-up are excluded (reported as ``startup_s``).
- ``ours_compile_s``: the first fit in a fresh process with the cache off
  (``BAYESROB_NO_CACHE=1``): tracing and XLA compilation included.

The cache is a scratch directory made for the run, so earlier runs do not warm it. The
targets (``target_in_process`` 200x, ``target_fresh_warm_cache`` 100x) are checked per line.
``--quick`` shrinks the problem sizes.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
import warnings

import numpy as np

SIZES = (700, 1000, 1300)
EARLIER_N = 200
TARGET_IN_PROCESS = 200.0
TARGET_FRESH_WARM = 100.0


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


def _fit_fn(case: str, n: int):
    from bayesrob.errors.kde import KDE, ConditionalKDE

    if case == "loo-ml-diag":
        data = skewed_bimodal(n)
        return lambda: KDE.fit(data, "loo-ml-diag").bandwidth
    x, z = conditional_data(n)
    return lambda: ConditionalKDE.fit(x, z, "kernel").bandwidth


def _timed(fn) -> tuple[float, object]:
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


def _worker(case: str, mode: str, sizes: list[int], m: int, repeats: int) -> dict:
    """Our side, in a fresh process. ``mode``: ``first`` times the first fit at sizes[0];
    ``in-process`` fits at EARLIER_N, then times the first and repeated fits at each size."""
    t0 = time.perf_counter()
    import jax
    import jax.numpy as jnp

    import bayesrob  # noqa: F401
    from bayesrob.errors.kde import KDE

    jnp.zeros(1).block_until_ready()  # backend start-up is not compilation
    startup = time.perf_counter() - t0
    warnings.simplefilter("ignore")
    if case == "logpdf":
        data, pts, bw = logpdf_data(sizes[0], m)
        kde = KDE.fit(data, bw)

        def run():
            return np.asarray(jax.block_until_ready(kde.logpdf(pts)))

        first, out = _timed(run)
        times = [_timed(run)[0] for _ in range(repeats)]
        return {"first": first, "median": statistics.median(times),
                "out": np.asarray(out).tolist(), "startup": startup}
    if mode == "first":
        first, out = _timed(_fit_fn(case, sizes[0]))
        return {"first": first, "out": np.asarray(out).tolist(), "startup": startup}
    _timed(_fit_fn(case, EARLIER_N))
    res = {}
    for n in sizes:
        fn = _fit_fn(case, n)
        first, out = _timed(fn)
        times = [_timed(fn)[0] for _ in range(repeats)]
        res[str(n)] = {"first": first, "median": statistics.median(times),
                       "out": np.asarray(out).tolist()}
    return res


def run_ours(case: str, mode: str, sizes: list[int], m: int = 0, repeats: int = 3,
             env: dict[str, str] | None = None) -> dict:
    cmd = [sys.executable, __file__, "--worker", case, mode, ",".join(map(str, sizes)), str(m),
           str(repeats)]
    proc = subprocess.run(cmd, capture_output=True, text=True, check=True,
                          env={**os.environ, **(env or {})})
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


def fit_lines(case: str, sizes: list[int], ref, **extra) -> None:
    """Time our fits four ways (see the module docstring) and print one line per size."""
    with tempfile.TemporaryDirectory(prefix="bench-kde-cache-") as cache:
        warm = {"BAYESROB_CACHE_DIR": cache}
        in_proc = run_ours(case, "in-process", sizes, env=warm)
        fresh = {n: run_ours(case, "first", [n], env=warm) for n in sizes}
    cold = {n: run_ours(case, "first", [n], env={"BAYESROB_NO_CACHE": "1"}) for n in sizes}
    for n in sizes:
        ref_s, ref_bw = ref(n)
        ours = in_proc[str(n)]
        diff = float(np.max(np.abs(np.array(ours["out"]) / ref_bw - 1)))
        rec = {
            "case": case, "n": n, "d": 4, **extra,
            "ours_s": round(ours["median"], 4),
            "ours_first_in_process_s": round(ours["first"], 4),
            "ours_fresh_warm_cache_s": round(fresh[n]["first"], 4),
            "ours_compile_s": round(cold[n]["first"], 4),
            "startup_s": round(fresh[n]["startup"], 2),
            "reference_s": round(ref_s, 3),
            "speedup_excl_compile": round(ref_s / ours["median"], 1),
            "speedup_in_process": round(ref_s / ours["first"], 1),
            "speedup_fresh_warm_cache": round(ref_s / fresh[n]["first"], 1),
            "speedup_incl_compile": round(ref_s / cold[n]["first"], 1),
            "target_in_process": ref_s / ours["first"] >= TARGET_IN_PROCESS,
            "target_fresh_warm_cache": ref_s / fresh[n]["first"] >= TARGET_FRESH_WARM,
            "max_rel_bw_diff": round(diff, 5),
            "load1": round(os.getloadavg()[0], 2),
        }
        print(json.dumps(rec), flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="smaller problems")
    ap.add_argument("--case", nargs="+", choices=("loo-ml-diag", "kernel-conditional", "logpdf"),
                    default=["loo-ml-diag", "kernel-conditional", "logpdf"])
    ap.add_argument("--sizes", nargs="+", type=int, help=f"fit sizes (default {SIZES})")
    ap.add_argument("--worker", nargs=5, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        case, mode, sizes, m, repeats = args.worker
        print(json.dumps(_worker(case, mode, [int(v) for v in sizes.split(",")], int(m),
                                 int(repeats))))
        return

    sizes = args.sizes or ([300, 400, 500] if args.quick else list(SIZES))
    lp_n, lp_m = (2000, 20_000) if args.quick else (10_000, 100_000)
    if "loo-ml-diag" in args.case:
        fit_lines("loo-ml-diag", sizes, ref_loo_ml_diag)
    if "kernel-conditional" in args.case:
        fit_lines("kernel-conditional", sizes, ref_conditional, dx=2, dz=2)
    if "logpdf" in args.case:
        ours = run_ours("logpdf", "first", [lp_n], lp_m, repeats=3)
        ref_s, ref_out = ref_logpdf(lp_n, lp_m)
        lp_diff = float(np.max(np.abs(np.array(ours["out"]) - ref_out)))
        rec = {"case": "logpdf", "n": lp_n, "d": 4, "m": lp_m,
               "ours_s": round(ours["median"], 4), "ours_compile_s": round(ours["first"], 4),
               "reference_s": round(ref_s, 3),
               "speedup_excl_compile": round(ref_s / ours["median"], 1),
               "speedup_incl_compile": round(ref_s / ours["first"], 1),
               "max_abs_logpdf_diff": lp_diff, "load1": round(os.getloadavg()[0], 2)}
        print(json.dumps(rec), flush=True)


if __name__ == "__main__":
    main()
