"""Grid predictions of where an end point lands, for one arm or several arms linked together.

A test point d_tst about the target implies the joint error theta_err = f^-1(d_tst) - g(u);
its density under a joint-error model (times |det df^-1/dd| in the improved variants) is the
arm's likelihood of d_tst. Linked arms share d_tst: the prediction is the product of their
likelihoods, normalised over the grid.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from scipy.special import logsumexp, softmax

from bayesrob import robot as kin
from bayesrob.calibrate.arms import mean_ci95, observed_errors, predicted_points
from bayesrob.data.rig import Rig
from bayesrob.errors.distributions import ArmStatic, arm_structures, compiled_arm_log_density
from bayesrob.errors.noise_models import FittedNoiseModel
from bayesrob.predict.regions import density_levels, region_sizes


@dataclass(frozen=True)
class Grid:
    """A square grid of test points around each target (the paper: +-30 mm, 100 x 100)."""

    half_width_mm: float = 30.0
    n: int = 100

    @property
    def axis(self) -> np.ndarray:
        step = 2 * self.half_width_mm / self.n
        return -self.half_width_mm + step * (np.arange(self.n) + 0.5)  # cell centres

    @property
    def cell_area_mm2(self) -> float:
        return (2 * self.half_width_mm / self.n) ** 2

    @property
    def offsets(self) -> np.ndarray:
        """(n*n, 2) offsets from the target, x fastest."""
        return _mesh(self.axis, 2)


def _mesh(axis: np.ndarray, dim: int) -> np.ndarray:
    """The dim-fold product of ``axis`` (n^dim, dim), x fastest."""
    return np.stack(np.meshgrid(*[axis] * dim, indexing="ij")[::-1], -1).reshape(-1, dim)


@dataclass
class Prediction:
    """Predicted end-point distributions of one setup over its targets."""

    config: str
    model: str
    targets: np.ndarray  # (T, 2) mm
    grid: Grid
    prob: np.ndarray  # (T, n*n) probability mass per grid cell, rows sum to 1
    expected_point: np.ndarray  # (T, 2)
    expected_error_mm: np.ndarray  # (T,) E ||d - d_targ||
    hdr50_mm2: np.ndarray  # (T,) area of the 50% highest-density region
    hdr90_mm2: np.ndarray  # (T,)

    @property
    def edge_mass(self) -> np.ndarray:
        """(T,) probability in the grid's outermost cells: large means the grid cut the mass
        off, and the expected error is an underestimate."""
        n = self.grid.n
        p = self.prob.reshape(-1, n, n)
        inner = p[:, 1:-1, 1:-1].sum(axis=(1, 2))
        return 1.0 - inner

    @property
    def mean_expected_error_mm(self) -> float:
        return float(np.mean(self.expected_error_mm))

    @property
    def error_density(self) -> np.ndarray:
        """Mass per cell of d - d_targ summed over targets and normalised (Figure 8), (n, n)."""
        return self.prob.mean(axis=0).reshape(self.grid.n, self.grid.n)

    def density(self, i: int) -> np.ndarray:
        """Density (per mm^2) of target i on the grid, (n, n), rows along y."""
        return self.prob[i].reshape(self.grid.n, self.grid.n) / self.grid.cell_area_mm2


def hdr_area(prob: np.ndarray, mass: float, cell_area: float | np.ndarray) -> np.ndarray:
    """Area of the smallest set of cells holding ``mass`` of each row of ``prob`` (T,)."""
    with np.errstate(divide="ignore"):
        log_density = np.log(prob.T) - np.log(cell_area)
    return region_sizes(log_density, [mass], weights=prob.T, volume=cell_area)[0]


def predict(config: str, models: dict[str, FittedNoiseModel], arms: dict[str, kin.Arm],
            commands: dict[str, np.ndarray], targets: np.ndarray, grid: Grid = Grid(),
            model_name: str = "") -> Prediction:
    """Predict the end point of a setup (arms joined by '+') at each target (T, 2), each arm
    at its ``commands`` (T, 2)."""
    members = config.split("+")
    targets = np.asarray(targets, float)
    offsets = jnp.asarray(grid.offsets)
    points = jnp.asarray(targets)[:, None, :] + offsets[None]
    logp = points_log_likelihood([models[a] for a in members], [arms[a] for a in members],
                                 [commands[a] for a in members], points)
    prob = np.asarray(jax.nn.softmax(logp, axis=-1))
    prob = np.nan_to_num(prob)  # a target no arm can reach anywhere on its grid
    pts = np.asarray(points)
    expected = np.einsum("tm,tmk->tk", prob, pts)
    dist = np.linalg.norm(np.asarray(offsets), axis=-1)
    return Prediction(
        config=config,
        model=model_name,
        targets=targets,
        grid=grid,
        prob=prob,
        expected_point=expected,
        expected_error_mm=prob @ dist,
        hdr50_mm2=hdr_area(prob, 0.5, grid.cell_area_mm2),
        hdr90_mm2=hdr_area(prob, 0.9, grid.cell_area_mm2),
    )


def setup_set(config: str) -> str:
    """The rows a setup is judged on: validation for single arms, test for linked ones."""
    return "test" if "+" in config else "validation"


def setup_rows(rig: Rig, arms: dict[str, kin.Arm], config: str) -> dict:
    """Commands, targets and observed end points of a setup's judged rows."""
    s = setup_set(config)
    rows = rig.config_rows(config, s)
    return {"set": s, "commands": rows["commands"], "observed": rows["observed"],
            "targets": predicted_points(rig, arms, config, s)}


def setups(rig: Rig) -> list[str]:
    """Every single arm with validation rows, then every linked config with test rows."""
    single = [a for a in rig.arms if rig.measurements.mask(a, "validation").any()]
    linked = [c for c in rig.linked_configs if rig.measurements.mask(c, "test").any()]
    return single + linked


def accuracy_document(rig: Rig, arms: dict[str, kin.Arm],
                      predictions: dict[str, dict[str, Prediction]]) -> dict:
    """The ``accuracy.json`` document: observed vs each model's predicted expected error."""
    out: dict[str, dict] = {}
    for config in setups(rig):
        obs = mean_ci95(observed_errors(rig, arms, config, setup_set(config)))
        pred = {}
        for model, by_setup in predictions.items():
            if config in by_setup:
                p = by_setup[config]
                e = p.mean_expected_error_mm
                pred[model] = {
                    "expected_error_mm": e,
                    "ratio": e / obs["mean_mm"] if obs["mean_mm"] > 0 else float("nan"),
                    "hdr50_mm2": float(np.mean(p.hdr50_mm2)),
                    "hdr90_mm2": float(np.mean(p.hdr90_mm2)),
                    "edge_mass_max": float(np.max(p.edge_mass)),
                }
        out[config] = {"observed": obs, "predicted": pred, "set": setup_set(config)}
    return {"setups": out}


# The prediction's +-30 mm box at 0.4 mm cells: only finds the mass for the zoomed grid. It has
# as many cells as the zoomed grid, so one compiled likelihood serves both.
COARSE_GRID = Grid(30.0, 150)


@dataclass
class GridPosterior:
    """A point's density on a zoomed grid (2-D or 3-D) fine enough for moments
    (:func:`zoomed_grid`). ``loglik(d) - log_normaliser`` is the normalised log density at d
    (per mm^dim)."""

    targets: np.ndarray  # (T, dim) the coarse grids' centres
    lo: np.ndarray  # (T, dim) lower corner of each fine grid
    cell_mm: np.ndarray  # (T, dim) fine cell size
    n: int
    prob: np.ndarray  # (T, n^dim) mass per fine cell
    mean: np.ndarray  # (T, dim)
    cov: np.ndarray  # (T, dim, dim)
    log_normaliser: np.ndarray  # (T,)
    edge_mass: np.ndarray  # (T,) coarse-grid mass in its outermost ring of cells
    coarse: Grid
    seconds: float = 0.0

    def points(self) -> np.ndarray:
        """Fine cell centres (T, n*n, 2), x fastest."""
        return _cell_centres(self.lo, self.cell_mm, self.n)

    def sample(self, seed: int, n: int) -> np.ndarray:
        """n draws (n, T, dim): a cell by its mass, then uniform within the cell."""
        rng = np.random.default_rng(seed)
        pts = self.points()
        out = np.empty((n, *self.targets.shape))
        for t in range(len(self.targets)):
            # Systematic resampling: n draws spread over the CDF, so even 4 chains land in
            # the modes in proportion to their mass instead of by luck.
            cdf = np.cumsum(self.prob[t])
            pos = (rng.permutation(n) + rng.uniform()) / n
            idx = np.minimum(np.searchsorted(cdf, pos * cdf[-1]), cdf.size - 1)
            jitter = rng.uniform(-0.5, 0.5, size=(n, pts.shape[-1])) * self.cell_mm[t]
            out[:, t] = pts[t, idx] + jitter
        return out

    def hdr_level(self, log_density: np.ndarray) -> np.ndarray:
        """The HDR level (mass denser than it) of one point per target of normalised
        ``log_density`` (T,) (:func:`point_log_density`): uniform on (0, 1) over real outcomes
        for a calibrated model."""
        log_area = np.log(np.prod(self.cell_mm, axis=1))
        with np.errstate(divide="ignore"):
            cell_ld = np.log(self.prob.T) - log_area
        return density_levels(cell_ld, log_density, self.prob.T)


def _cell_centres(lo: np.ndarray, cell: np.ndarray, n: int) -> np.ndarray:
    return lo[:, None, :] + _mesh(np.arange(n) + 0.5, lo.shape[1])[None] * cell[:, None, :]


@functools.lru_cache(maxsize=64)
def _compiled_loglik(statics: tuple[ArmStatic, ...]) -> Callable:
    def one_target(args, params):
        points, commands = args  # (M, 2), tuple of (2,)
        return sum(compiled_arm_log_density(s, ap, arr, u[None], points[:, None, :])[:, 0]
                   for s, (ap, arr), u in zip(statics, params, commands, strict=True))

    # Targets one after the other (lax.map): an (M x N) kernel block per target stays small
    # where all targets at once would hold T times as much.
    return jax.jit(lambda points, commands, params: jax.lax.map(
        lambda a: one_target(a, params), (points, commands)))


def points_log_likelihood(models: Sequence[FittedNoiseModel], arms: Sequence[kin.Arm],
            commands: Sequence[np.ndarray], points: Any) -> np.ndarray:
    """Summed unnormalised log-likelihood of points (T, M, 2): the grid's density, compiled
    once per structure and shapes."""
    statics, params = arm_structures(models, arms)
    cmds = tuple(jnp.asarray(np.atleast_2d(u), dtype=jnp.float64) for u in commands)
    return np.asarray(_compiled_loglik(statics)(jnp.asarray(points, dtype=jnp.float64), cmds,
                                                params))


def grid_posterior(models: Sequence[FittedNoiseModel], arms: Sequence[kin.Arm],
                   commands: Sequence[np.ndarray], targets: np.ndarray,
                   coarse: Grid = COARSE_GRID, n: int = 150,
                   tail: float = 1e-9) -> GridPosterior:
    """The planar arms' linked end-point density of each target on a zoomed grid.

    The paper's 100 x 100 grid has 0.6 mm cells, as wide as the posterior itself (sd ~0.4 to
    2 mm), so its moments carry discretisation error of the order of the 0.1 mm / 10%
    tolerances of ``cross_check``. The zoom spans about +-6 posterior sd, so a cell is ~0.08
    sd and the midpoint rule's relative error in the variance is ~(cell / sd)^2 / 12 < 0.1%.
    """
    commands = [np.atleast_2d(np.asarray(u, float)) for u in commands]
    return zoomed_grid(lambda pts: points_log_likelihood(models, arms, commands, pts), targets,
                       coarse, n, tail)


def zoomed_grid(loglik: Callable[[np.ndarray], np.ndarray], targets: np.ndarray,
                coarse: Grid = COARSE_GRID, n: int = 150, tail: float = 1e-9) -> GridPosterior:
    """Mean, covariance and normaliser of the density ``loglik`` (points (T, M, dim) -> (T, M)
    unnormalised log densities) about each target (T, dim), by the midpoint rule: a coarse
    grid locates the mass, a second n^dim grid over the box holding all but ``tail`` of it."""
    t0 = time.perf_counter()
    targets = np.atleast_2d(np.asarray(targets, float))
    offsets = _mesh(coarse.axis, targets.shape[1])
    pts = targets[:, None, :] + offsets[None]
    ll = loglik(pts)
    if not np.all(np.isfinite(ll).any(axis=1)):
        t = int(np.flatnonzero(~np.isfinite(ll).any(axis=1))[0])
        raise ValueError(f"target {t} ({', '.join(f'{v:g}' for v in targets[t])}): no point of "
                         f"the +-{coarse.half_width_mm:g} mm box around it is reached by every "
                         "arm")
    p = softmax(ll, axis=-1)
    step = 2 * coarse.half_width_mm / coarse.n
    ring = np.any(np.abs(offsets) > coarse.half_width_mm - step, axis=1)
    edge = p[:, ring].sum(axis=1)
    lo = np.empty_like(targets)
    hi = np.empty_like(targets)
    for t in range(len(targets)):
        order = np.argsort(p[t])[::-1]
        k = int(np.searchsorted(np.cumsum(p[t, order]), 1.0 - tail)) + 1
        keep = pts[t][order[:k]]
        # Margin of two coarse cells: the kept cells' centres understate the support by half
        # a cell, and the density between neighbours of the last kept cell is not yet zero.
        lo[t] = keep.min(axis=0) - 2 * step
        hi[t] = keep.max(axis=0) + 2 * step
    cell = (hi - lo) / n
    fine = _cell_centres(lo, cell, n)
    llf = loglik(fine)
    log_normaliser = logsumexp(llf, axis=-1) + np.log(np.prod(cell, axis=1))
    prob = softmax(llf, axis=-1)
    mean = np.einsum("tm,tmk->tk", prob, fine)
    dev = fine - mean[:, None, :]
    cov = np.einsum("tm,tmi,tmj->tij", prob, dev, dev)
    return GridPosterior(targets, lo, cell, n, prob, mean, cov, log_normaliser, edge, coarse,
                         time.perf_counter() - t0)


def point_log_density(post: GridPosterior, models: Sequence[FittedNoiseModel],
                      arms: Sequence[kin.Arm], commands: Sequence[np.ndarray],
                      points: np.ndarray) -> np.ndarray:
    """Normalised log density (per mm^2) of one point per target under the grid prediction:
    the exact point's log-likelihood minus the grid's log normaliser."""
    pts = np.asarray(points, float)[:, None, :]
    ll = points_log_likelihood(models, arms, commands, pts)[:, 0]
    return ll - post.log_normaliser
