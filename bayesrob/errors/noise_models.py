"""Joint-error models IND, CORR and COND: densities of the angular error at each arm's joints.

The error an arm leaves after calibration is modelled as noise on its joint angles:
d = f(g(u) + theta_err). Where the rows observe those errors (:func:`joint_errors_observed`;
else the latent population of :mod:`bayesrob.errors.latent_errors` is the density), row i's
are J_i^-1 r_i (on the paper's planar arms exactly f^-1(d_obs_i) - g(u_i), NOTES item 1), and
a Parzen density of theta_err is fitted under one of three assumptions:

- IND: the joints' errors are independent (a product of 1-D densities);
- CORR: they may be correlated (one joint density);
- COND: their density depends on the commands sent, p(theta_err | u).

Each variant is one declarative TOML file in ``models/`` (family, bandwidth selector,
conditioning, bins, whether the Jacobian is applied); :func:`discover_models` finds them, so a
new variant needs no code.
"""

from __future__ import annotations

import tomllib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np

from bayesrob import robot as kin
from bayesrob.data.rig import Rig
from bayesrob.errors.kde import KDE, ConditionalKDE
from bayesrob.errors.latent_errors import joint_jacobian, scaled_train_residuals

FAMILIES = ("IND", "CORR", "COND")


class ModelFileError(ValueError):
    """A model file is malformed; the message names the file and key."""


def _non_negative(doc: dict, key: str, path: Path) -> float:
    value = doc.get(key, 0.0)
    if isinstance(value, bool) or not isinstance(value, int | float) or value < 0:
        raise ModelFileError(f"{path}: {key} must be a number >= 0, got {value!r}")
    return float(value)


@dataclass(frozen=True)
class ModelSpec:
    """One joint-error model variant, as declared in a ``models/*.toml`` file."""

    name: str
    family: str
    bandwidth: str | float | tuple[float, ...] = "loo-ml-diag"
    conditioning: str = "kernel"
    jacobian: bool = True
    h_range: tuple[float, float] = (0.05, 2.0)
    bins: int = 10
    bin_widths: tuple[float, ...] | None = None
    bin_margin: float = 0.0
    # COND kernel: least command-kernel width, in nearest-neighbour spacings of the train
    # commands (kde.ConditionalKDE.fit's z_spacing_floor; 0: none)
    command_bandwidth_floor: float = 0.0
    description: str = ""
    path: Path | None = field(default=None, compare=False)

    @property
    def paper(self) -> bool:
        """Whether this is a paper-faithful variant (by the bandwidth selector)."""
        return self.bandwidth == "paper"

    @classmethod
    def from_file(cls, path: str | Path) -> ModelSpec:
        path = Path(path)
        try:
            doc = tomllib.loads(path.read_text())
        except (OSError, tomllib.TOMLDecodeError) as exc:
            raise ModelFileError(f"{path}: cannot read model file: {exc}") from None
        known = {f.name for f in fields(cls)} - {"path"}
        for key in doc:
            if key not in known:
                raise ModelFileError(f"{path}: unknown key {key!r} (known: {sorted(known)})")
        for key in ("name", "family"):
            if key not in doc:
                raise ModelFileError(f"{path}: missing key {key!r}")
        family = str(doc["family"]).upper()
        if family not in FAMILIES:
            raise ModelFileError(f"{path}: family must be one of {FAMILIES}, got {family!r}")
        cond = doc.get("conditioning", "kernel")
        if cond not in ("kernel", "histogram"):
            raise ModelFileError(f"{path}: conditioning must be 'kernel' or 'histogram'")
        bw = doc.get("bandwidth", "loo-ml-diag")
        if isinstance(bw, list):
            bw = tuple(float(b) for b in bw)
        widths = doc.get("bin_widths")
        return cls(
            name=str(doc["name"]),
            family=family,
            bandwidth=bw,
            conditioning=cond,
            jacobian=bool(doc.get("jacobian", True)),
            h_range=tuple(doc.get("h_range", (0.05, 2.0))),
            bins=int(doc.get("bins", 10)),
            bin_widths=tuple(float(w) for w in widths) if widths is not None else None,
            bin_margin=float(doc.get("bin_margin", 0.0)),
            command_bandwidth_floor=_non_negative(doc, "command_bandwidth_floor", path),
            description=str(doc.get("description", "")),
            path=path,
        )

    def fit(self, theta_err: np.ndarray, u: np.ndarray,
            widths: Sequence[np.ndarray] | None = None) -> FittedNoiseModel:
        """Fit the density to one arm's joint errors (N, n) and commands (N, c); ``widths``:
        each part's bandwidths fixed (:attr:`FittedNoiseModel.widths`) instead of selected."""
        theta_err = np.asarray(theta_err, float)
        u = np.asarray(u, float)
        kw: dict[str, Any] = {"warn_on_bound": False}
        if self.bandwidth in ("paper", "loo-ml") and widths is None:
            kw["h_range"] = self.h_range
        if self.family != "COND":
            cols = ([theta_err[:, j:j + 1] for j in range(theta_err.shape[1])]
                    if self.family == "IND" else [theta_err])
            parts = [KDE.fit(c, self.bandwidth if widths is None else widths[j], **kw)
                     for j, c in enumerate(cols)]
            return FittedNoiseModel(self, theta_err, u, parts=parts)
        cond = ConditionalKDE.fit(theta_err, u, self.conditioning,
                                  self.bandwidth if widths is None else widths[0],
                                  bins=self.bins, bin_widths=self._bin_widths(theta_err, u),
                                  z_spacing_floor=self.command_bandwidth_floor, **kw)
        return FittedNoiseModel(self, theta_err, u, conditional=cond)

    def _bin_widths(self, theta_err: np.ndarray, u: np.ndarray) -> tuple[float, ...] | None:
        """Histogram bin widths: as declared, or each half-span about the data mean the farthest
        point plus ``bin_margin`` times the range, so few rows fall outside, on the floor."""
        if self.bin_widths is not None or self.bin_margin <= 0:
            return self.bin_widths
        x = np.hstack([theta_err, u])
        mean = x.mean(axis=0)
        half = np.maximum(x.max(axis=0) - mean, mean - x.min(axis=0))
        half = half + self.bin_margin * (x.max(axis=0) - x.min(axis=0))
        return tuple(float(w) for w in 2 * half / self.bins)


@dataclass(frozen=True, eq=False)
class FittedNoiseModel:
    """A fitted joint-error density for one arm: log p(theta_err | u), traceable in JAX."""

    spec: ModelSpec
    theta_err: np.ndarray
    u: np.ndarray
    parts: list[KDE] | None = None
    conditional: ConditionalKDE | None = None

    @property
    def _estimates(self) -> list[KDE | ConditionalKDE]:
        return self.parts if self.conditional is None else [self.conditional]

    @property
    def on_bound(self) -> bool:
        """Whether any bandwidth search ended on its bound (the paper's J_LOO always does)."""
        return any(bool(k.on_bound) for k in self._estimates)

    @property
    def search_range(self) -> tuple[float, float] | None:
        """The range the bandwidth search covered (normalised units)."""
        return self._estimates[0].search_range

    @property
    def widths(self) -> list[np.ndarray]:
        """Each part's bandwidths (the histogram COND's: its joint KDE's)."""
        return [np.asarray(k.bandwidth) for k in self._estimates]

    @property
    def bandwidth(self) -> np.ndarray:
        return np.concatenate(self.widths)


def joint_errors_observed(robot: kin.Robot, arms: Sequence[str]) -> bool:
    """Whether the rows observe ``arms``' joint errors: each path has as many joints as the
    tracker measures coordinates, so J is square and a residual r gives them, J^-1 r (the
    paper's planar arms); else a residual fixes only their projection."""
    return all(robot.n_path_joints(a) == robot.dim for a in arms)


def observed_joint_errors(rig: Rig, robot: kin.Robot, x: np.ndarray, arm: str
                          ) -> tuple[np.ndarray, np.ndarray]:
    """``arm``'s train commands (N, c) and joint errors J_i^-1 r_i (N, n), r_i its residuals
    under parameters x and J_i the robot's joint Jacobian (:func:`joint_errors_observed`); on
    a planar arm the linearisation of :func:`joint_errors`."""
    u, res, _, side = scaled_train_residuals(rig, robot, x, arm, 0)  # unscaled
    jac = joint_jacobian(robot, jnp.asarray(x), arm, jnp.asarray(u), side)
    return u, np.linalg.solve(np.asarray(jac), res[..., None])[..., 0]


def joint_errors(arm: kin.Arm, u: np.ndarray, d_obs: np.ndarray) -> np.ndarray:
    """theta_err_i = f^-1(d_obs_i) - g(u_i), wrapped to (-pi, pi] (NOTES item 1)."""
    theta, _ = kin.inverse(arm.params, jnp.asarray(d_obs), arm.elbow)
    return np.asarray(kin.wrap_angle(theta - kin.servo(arm.params, jnp.asarray(u))))


def without_tracker_noise(arm: kin.Arm, u: np.ndarray, theta_err: np.ndarray,
                          tracker_noise_mm: float) -> np.ndarray:
    """Joint errors (N, 2) with the tracker's noise taken out of them.

    A row's joint error read off its measured point is theta_err_i = e_i + J_i^-1 eps_i, and
    near a stretched or folded pose J_i^-1 is large: mapped through another pose's Jacobian
    such errors predict what the joints never do. With Sigma the joints' own covariance (the
    errors' less the mean of C_i = s^2 J_i^-1 J_i^-T), each row is mapped by
    Sigma^1/2 (Sigma + C_i)^-1/2 about the mean, giving it covariance Sigma (Gaussian errors);
    predictions add the tracker's noise to the measured point instead.
    """
    theta_err = np.asarray(theta_err, float)
    if tracker_noise_mm <= 0 or len(theta_err) < 3:
        return theta_err
    theta = np.asarray(kin.servo(arm.params, jnp.asarray(u))) + theta_err
    # pinv: at a straight elbow J has no inverse; the directions it has are kept
    jinv = np.linalg.pinv(np.asarray(kin.jacobian(arm.params, jnp.asarray(theta))))
    c = tracker_noise_mm**2 * np.einsum("nij,nkj->nik", jinv, jinv)
    mean = theta_err.mean(axis=0)
    total = np.cov(theta_err.T)
    w, v = np.linalg.eigh(total - c.mean(axis=0))
    # what the noise does not explain, kept at least a tenth of the errors' spread per axis:
    # a rig whose errors are all tracker noise still gets a proper (narrow) density
    w = np.maximum(w, 0.01 * np.linalg.eigvalsh(total).min())
    sigma = (v * w) @ v.T

    def root(m: np.ndarray, power: float) -> np.ndarray:
        ew, ev = np.linalg.eigh(m)
        return np.einsum("...ij,...j,...kj->...ik", ev, ew**power, ev)

    a = np.einsum("ij,njk->nik", root(sigma, 0.5), root(sigma[None] + c, -0.5))
    return mean + np.einsum("nij,nj->ni", a, theta_err - mean)


def models_dir() -> Path:
    """Where the shipped model files are: the checkout's models/ or the installed copy."""
    # In a source checkout models/ sits beside the package; prefer it so edits show at once.
    here = Path(__file__).resolve().parent.parent / "models"
    if any(here.glob("*.toml")):
        return here
    from importlib.resources import files

    return Path(str(files("bayesrob.models")))


def discover_models(directory: str | Path | None = None,
                    names: Sequence[str] | None = None) -> list[ModelSpec]:
    """All model files in a directory (default: the shipped ones), optionally by name."""
    directory = Path(directory) if directory is not None else models_dir()
    if not directory.is_dir():
        raise ModelFileError(f"{directory}: models directory not found")
    specs = [ModelSpec.from_file(p) for p in sorted(directory.glob("*.toml"))]
    order = {f: i for i, f in enumerate(FAMILIES)}
    specs.sort(key=lambda s: (order[s.family], not s.paper, s.name))
    seen: dict[str, Path] = {}
    for s in specs:
        if s.name in seen:
            raise ModelFileError(f"{s.path}: model name {s.name!r} also used by {seen[s.name]}")
        seen[s.name] = s.path
    if names:
        missing = [n for n in names if n not in seen]
        if missing:
            raise ModelFileError(f"{directory}: no model named {missing[0]!r} (have "
                                 f"{', '.join(seen)})")
        specs = [s for s in specs if s.name in names]
    return specs


def fit_noise_models(rig: Rig, arms: dict[str, kin.Arm], specs: Sequence[ModelSpec],
                     on_fit: Callable[[str, str], None] | None = None
                     ) -> dict[str, dict[str, FittedNoiseModel]]:
    """Fit every model to every arm's training rows: {model name: {arm: fitted}};
    ``on_fit(model, arm)`` is called after each fit (progress)."""
    data = {}
    for name, arm in arms.items():
        u, d = rig.rows(name, "train")
        data[name] = (joint_errors(arm, u, d), u)
    out: dict[str, dict[str, FittedNoiseModel]] = {}
    for s in specs:
        out[s.name] = {}
        for a in arms:
            out[s.name][a] = s.fit(*data[a])
            if on_fit is not None:
                on_fit(s.name, a)
    return out
