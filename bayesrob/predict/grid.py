"""Grid predictions of where an end point lands, for one arm or several arms linked together.

For an arm commanded with u (aimed at d_targ = f(g(u))), a test point d_tst on a grid around
the target implies the joint error theta_err = f^-1(d_tst) - g(u) (NOTES item 2; g(u) is
f^-1(d_targ) on the arm's branch). Its density under a joint-error model, times the Jacobian
|det df^-1/dd| in the improved variants, is the arm's likelihood of d_tst. Arms linked at their
end points share d_tst: the prediction is the product of their likelihoods (a sum of logs),
normalised over the grid. Everything is vectorised over targets and grid points.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from bayesrob import robot as kin
from bayesrob.calibrate.arms import mean_ci95, observed_errors, predicted_points
from bayesrob.data.rig import Rig
from bayesrob.errors.noise_models import FittedNoiseModel
from bayesrob.predict.regions import region_sizes


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
        gx, gy = np.meshgrid(self.axis, self.axis)
        return np.column_stack([gx.ravel(), gy.ravel()])


@partial(jax.jit, static_argnames="elbow")
def _arm_geometry(params: kin.ArmParams, elbow: int, u: jax.Array, points: jax.Array
                  ) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """Joint errors, paired commands, log-Jacobian and reachability at (T, M, 2) points."""
    t, m = points.shape[:2]
    theta, ok = kin.inverse(params, points, elbow)
    err = kin.wrap_angle(theta - kin.servo(params, u)[:, None, :])
    u_rep = jnp.broadcast_to(u[:, None, :], (t, m, 2)).reshape(-1, 2)
    return err.reshape(-1, 2), u_rep, kin.log_abs_det_inverse_jacobian(params, theta), ok


def arm_log_likelihood(model: FittedNoiseModel, arm: kin.Arm, u: jnp.ndarray,
                       points: jnp.ndarray) -> jnp.ndarray:
    """log p(d | u) of one arm at end points (T, M, 2) for commands u (T, 2), unnormalised.

    Points the arm cannot reach get -inf: a linked end point there is impossible.
    """
    t, m = points.shape[:2]
    err, u_rep, log_jac, ok = _arm_geometry(arm.params, int(arm.elbow), jnp.asarray(u, float),
                                            jnp.asarray(points, float))
    lp = model.logpdf(err, u_rep).reshape(t, m)
    if model.spec.jacobian:
        lp = lp + log_jac
    return jnp.where(ok, lp, -jnp.inf)


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
        """(T,) probability in the grid's outermost cells: large means the grid cut the mass off.

        It happens when the commands do not aim near the target, or the spread is wider than
        the grid; the expected error is then an underestimate clipped by the grid.
        """
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
    """Predict the end point of a setup (one arm, or arms joined by '+') at each target.

    ``commands``: pulses (T, 2) sent to each arm of the config; ``targets``: (T, 2).
    """
    members = config.split("+")
    targets = np.asarray(targets, float)
    offsets = jnp.asarray(grid.offsets)
    points = jnp.asarray(targets)[:, None, :] + offsets[None]
    logp = sum(arm_log_likelihood(models[a], arms[a], jnp.asarray(commands[a], float), points)
               for a in members)
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
