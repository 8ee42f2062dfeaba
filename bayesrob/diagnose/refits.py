"""Model criticism of planar arms: name the missing physical effect, add it and show the gap
shrink (the paper could only say its model "was too constrained"), from the rig files alone.

1. Fit each arm's eight-parameter base model; test its residuals for structure noise would
   not show (lack of fit against the repeats, Moran's I, score tests, jumps) and say where.
2. Fit every candidate effect (:mod:`bayesrob.robot.effects`) into the current model and
   score it on data it was not fitted on: cross-validated refits over ``train`` (exact LOO up
   to 40 points, structural settings profiled again) under a Gaussian measurement model;
   ``holdout`` rows are reported beside, deciding nothing.
3. Name the best candidate passing :class:`bayesrob.diagnose.rule.DecisionRule` (the chains'
   rule, on the refits' errors), repeat; if none passes at first, try pairs (each member
   needed). The arms an effect goes to are chosen on one half of the train rows and scored on
   the other (cross-fitting).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import scipy.optimize
import scipy.stats

from bayesrob import robot as kin
from bayesrob.data.rig import ArmSpec, Rig
from bayesrob.diagnose.rule import DecisionRule, elpd_diff, paired_z, public_scores
from bayesrob.robot import effects as fx

N_BASE = len(kin.PARAM_NAMES)


@dataclass
class ArmData:
    """One arm's single-arm rows: what the diagnosis fits and scores."""

    name: str
    spec: ArmSpec
    u: np.ndarray  # (n, 2) train pulses
    d: np.ndarray  # (n, 2) train end points
    u_val: np.ndarray  # (m, 2)
    d_val: np.ndarray  # (m, 2)
    ctx: fx.EffectContext
    # new poses, reported and never decided on (validation rows only see repeatability)
    u_hold: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    d_hold: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))

    @classmethod
    def from_rig(cls, rig: Rig, name: str) -> ArmData:
        u, d = rig.rows(name, "train")
        uv, dv = rig.rows(name, "validation")
        uh, dh = rig.rows(name, "holdout")
        return cls(name, rig.arms[name], u, d, uv, dv,
                   fx.EffectContext.from_commands(u, rig.gravity), uh, dh)

    @property
    def ctx_array(self) -> jax.Array:
        return self.ctx.to_array()

    def replicate_pairs(self) -> tuple[np.ndarray, np.ndarray]:
        ti, vi = [], []
        for j, uv in enumerate(self.u_val):
            hit = np.flatnonzero(np.all(np.abs(self.u - uv) < 1e-9, axis=1))
            if len(hit):
                ti.append(int(hit[0]))
                vi.append(j)
        return np.array(ti, int), np.array(vi, int)


class _ModelFns:
    """Jitted functions of one model structure (base + named effects), the arm's context an
    argument, so one compilation serves every arm and rig with the same number of rows."""

    def __init__(self, names: tuple[str, ...]):
        self.names = names
        self.classes = [fx.REGISTRY[n] for n in names]
        probe = [c(fx.EffectContext()) for c in self.classes]
        self.sizes = [len(e.param_names()) for e in probe]
        self.n_params = N_BASE + sum(self.sizes)
        self.param_names = list(kin.PARAM_NAMES) + [
            f"{n}.{p}" for n, e in zip(names, probe, strict=True) for p in e.param_names()]
        self.effect_scales = (np.concatenate([e.scales() for e in probe]) if probe
                              else np.zeros(0))
        self.prior_sd = (np.concatenate([e.prior_sd() for e in probe]) if probe
                         else np.zeros(0))
        self.initial_extra = [e.initial() for e in probe]

        def pred(v, ctx, settings, u):
            params, effs, extras = self.unpack(v, ctx, settings)
            return kin.forward(params, fx.apply_effects(effs, params, extras, u))

        prior_sd = jnp.asarray(self.prior_sd)

        def res_prior(v, ctx, settings, u, d, w):
            # Weight 0 drops a row (cross-validation); a weak penalty on the effects' parameters
            # keeps directions the data cannot see at "no effect", not where the solver left them.
            r = ((pred(v, ctx, settings, u) - d) * w[:, None]).ravel()
            return jnp.concatenate([r, v[N_BASE:] / prior_sd])

        def with_jac(f):
            def flat(v, *args):
                J, val = jax.jacfwd(lambda x: (f(x, *args),) * 2, has_aux=True)(v)
                return jnp.concatenate([val.ravel(), J.ravel()])
            jitted = jax.jit(flat)

            def both(v, *args):
                # One array back from the device: each transfer costs more than the maths.
                out = np.asarray(jitted(v, *args))
                m = out.size // (1 + self.n_params)
                return out[:m], out[m:].reshape(m, self.n_params)
            return both

        # Value and Jacobian in one compiled function: scipy asks for both at the same points,
        # and compilation and transfers, not arithmetic, are what these small models cost.
        self.residuals = with_jac(res_prior)  # (2n + q,), (2n + q, p)
        flat_predict = with_jac(pred)

        def predict(v, ctx, settings, u):
            r, J = flat_predict(v, ctx, settings, u)
            return r.reshape(-1, 2), J.reshape(-1, 2, self.n_params)

        self.predict = predict  # (n, 2), (n, 2, p)

    def unpack(self, v, ctx, settings):
        c = fx.EffectContext.from_array(ctx)
        params = kin.ArmParams.from_vector(v[:N_BASE])
        effs, extras, k = [], [], N_BASE
        for cls, s, size in zip(self.classes, settings, self.sizes, strict=True):
            effs.append(cls(c, s))
            extras.append(v[k:k + size])
            k += size
        return params, tuple(effs), extras

    def effects_for(self, ctx: fx.EffectContext, settings: Sequence) -> list[fx.Effect]:
        return [cls(ctx, s) for cls, s in zip(self.classes, settings, strict=True)]


@cache
def model_fns(names: tuple[str, ...]) -> _ModelFns:
    return _ModelFns(names)


def _base_scales(v: np.ndarray) -> np.ndarray:
    # typical sizes of the base parameters, so the solver's steps mean the same in each
    return np.array([10.0, 10.0, 10.0, 10.0, 0.05 * abs(v[4]) + 1e-9, 0.05 * abs(v[5]) + 1e-9,
                     0.05, 0.05])


@dataclass
class _Fit:
    v: np.ndarray
    settings: tuple
    cost: float  # sum of squared (weighted) residuals
    nfev: int
    J: np.ndarray  # Jacobian of the residuals and penalty at v
    all: list = field(default_factory=list)  # every setting's fit, when profiled


def _least_squares(fns: _ModelFns, v0: np.ndarray, ctx: jax.Array, settings: tuple,
                   u: jax.Array, d: jax.Array, w: jax.Array) -> _Fit:
    scale = np.concatenate([_base_scales(v0), fns.effect_scales])
    settings_j = _jsettings(settings)
    last: dict = {}

    def fun(v: np.ndarray) -> np.ndarray:
        r, J = fns.residuals(v, ctx, settings_j, u, d, w)
        last.update(v=v.copy(), r=r, J=J)
        return last["r"]

    def jac(v: np.ndarray, *_) -> np.ndarray:
        if "v" not in last or not np.array_equal(last["v"], v):
            fun(v)
        return last["J"]

    res = scipy.optimize.least_squares(fun, v0, jac=jac, x_scale=scale, method="trf",
                                       xtol=1e-9, ftol=1e-9, gtol=1e-9, max_nfev=200)
    r = fun(res.x)[: 2 * len(w)]
    return _Fit(res.x, settings, float(r @ r), int(res.nfev), last["J"])


def _profile_fit(fns: _ModelFns, v0: np.ndarray, ctx: jax.Array, grid: list[tuple],
                 u: jax.Array, d: jax.Array, w: jax.Array) -> _Fit:
    """Best fit over the structural settings (a gradient cannot move them)."""
    fits = [_least_squares(fns, v0, ctx, s, u, d, w) for s in grid]
    best = min(fits, key=lambda f: f.cost)
    best.all = fits
    return best


def _gauss2_logpdf(r: np.ndarray, cov: np.ndarray) -> np.ndarray:
    det = cov[:, 0, 0] * cov[:, 1, 1] - cov[:, 0, 1] * cov[:, 1, 0]
    inv = np.stack([np.stack([cov[:, 1, 1], -cov[:, 0, 1]], -1),
                    np.stack([-cov[:, 1, 0], cov[:, 0, 0]], -1)], -2) / det[:, None, None]
    quad = np.einsum("ni,nij,nj->n", r, inv, r)
    return -np.log(2 * np.pi) - 0.5 * np.log(det) - 0.5 * quad


@dataclass
class ArmEval:
    """A model of one arm fitted on ``train`` and scored on data it was not fitted on."""

    arm: str
    effects: tuple[str, ...]
    v: np.ndarray
    settings: tuple
    cov: np.ndarray  # (p, p) of v
    sigma_mm: float  # fitted scale of the Gaussian measurement model, per axis
    dof: int
    train_errors: np.ndarray  # (n,) mm
    train_lpd: np.ndarray  # (n,) in-sample log density (for p_loo: lppd - elpd)
    val_errors: np.ndarray  # (m,) mm
    val_lpd: np.ndarray  # (m,) log predictive density of the validation rows
    cv_errors: np.ndarray  # (n,) mm, each from a fit that did not see the point
    cv_lpd: np.ndarray  # (n,) log predictive density of each point from that fit
    resid_train: np.ndarray  # (n, 2) observed - predicted
    resid_val: np.ndarray  # (m, 2)
    _magnitudes: dict | None = None
    hold_errors: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (h,) mm, reported only
    hold_lpd: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (h,)

    def magnitudes(self, data: ArmData) -> dict:
        """Each effect's fitted size with standard errors (computed once, on demand: losing
        candidates never need it)."""
        if self._magnitudes is None:
            self._magnitudes = _magnitudes(model_fns(self.effects), data, self)
        return self._magnitudes

    @property
    def params(self) -> kin.ArmParams:
        return kin.ArmParams.from_vector(jnp.asarray(self.v[:N_BASE]))


def _folds(n: int, k: int | None, seed: int) -> list[np.ndarray]:
    if k is None:
        k = n if n <= 40 else 10  # exact leave-one-out while refits are cheap
    k = max(2, min(k, n))
    perm = np.random.default_rng(seed).permutation(n)
    return [np.sort(perm[i::k]) for i in range(k)]


def _predictive(fns: _ModelFns, fit: _Fit, ctx: jax.Array, u: np.ndarray, d: np.ndarray,
                s2: float, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Residuals (n, 2), errors (mm) and Gaussian log predictive densities of rows (u, d)
    under a fit: scale s2 plus the parameters' uncertainty through the Jacobian."""
    pred, J = fns.predict(fit.v, ctx, _jsettings(fit.settings), jnp.asarray(u))
    pcov = s2 * np.eye(2)[None] + np.einsum("nip,pq,njq->nij", J, cov, J)
    r = d - pred
    return r, np.linalg.norm(r, axis=1), _gauss2_logpdf(r, pcov)


def _jsettings(settings: tuple) -> tuple:
    return tuple(None if s is None else jnp.asarray(s) for s in settings)


def _cov(fit: _Fit, dof: int) -> tuple[float, np.ndarray]:
    """Measurement variance and the parameters' covariance s^2 (J'J)^-1 at the fit."""
    s2 = fit.cost / dof
    return s2, s2 * np.linalg.pinv(fit.J.T @ fit.J)


def evaluate_arm(data: ArmData, names: tuple[str, ...], start: ArmEval | None = None,
                 k_folds: int | None = None, seed: int = 0) -> ArmEval:
    """Fit ``base + names`` to the arm's train rows and score it on held-out data. ``start``:
    a fitted model whose effects prefix ``names`` (warm start; else the base model first);
    ``k_folds``: None for exact leave-one-out up to 40 points, else 10-fold."""
    names = tuple(names)
    fns = model_fns(names)
    ctx = data.ctx_array
    u, d = jnp.asarray(data.u), jnp.asarray(data.d)
    n = len(data.u)
    ones = jnp.ones(n)
    if start is None and names:
        start = evaluate_arm(data, (), None, k_folds=2, seed=seed)
    if start is None:
        v0 = np.asarray(kin.ArmParams.from_spec(data.spec).to_vector())
    else:
        k = len(start.effects)
        if names[:k] != start.effects:
            raise ValueError(f"start model {start.effects} is not a prefix of {names}")
        v0 = np.concatenate([start.v, *fns.initial_extra[k:]])
    grid = _settings_grid(fns, data, v0)

    fit = _profile_fit(fns, v0, ctx, grid, u, d, ones)
    p = fns.n_params
    dof = max(2 * n - p, 1)
    s2, cov = _cov(fit, dof)
    resid, train_err, train_lpd = _predictive(fns, fit, ctx, data.u, data.d, s2,
                                              np.zeros_like(cov))
    if len(data.u_val):
        resid_val, val_err, val_lpd = _mixture_predictive(fns, fit, ctx, data.u_val,
                                                          data.d_val, dof)
    else:
        val_err, val_lpd, resid_val = np.zeros(0), np.zeros(0), np.zeros((0, 2))
    hold_err, hold_lpd = np.zeros(0), np.zeros(0)
    if len(data.u_hold):
        _, hold_err, hold_lpd = _mixture_predictive(fns, fit, ctx, data.u_hold, data.d_hold,
                                                    dof)

    # Each fold profiles every setting again on its own rows: a setting chosen on all the
    # data would have seen the row the fold leaves out.
    cv_err, cv_lpd = _cross_validate(fns, data, fit.v, grid, k_folds, seed)
    ev = ArmEval(
        arm=data.name, effects=names, v=fit.v, settings=fit.settings, cov=cov,
        sigma_mm=math.sqrt(s2), dof=dof, train_errors=train_err, train_lpd=train_lpd,
        val_errors=val_err, val_lpd=val_lpd, cv_errors=cv_err, cv_lpd=cv_lpd,
        resid_train=resid, resid_val=resid_val, hold_errors=hold_err, hold_lpd=hold_lpd)
    return ev


def _settings_grid(fns: _ModelFns, data: ArmData, v: np.ndarray) -> list[tuple]:
    params = kin.ArmParams.from_vector(jnp.asarray(v[:N_BASE]))
    per_effect = []
    for eff in fns.effects_for(data.ctx, [None] * len(fns.names)):
        s = eff.settings(params, data.u)
        per_effect.append([None] if s is None else [np.asarray(r) for r in s])
    return [tuple(c) for c in itertools.product(*per_effect)]


def _cross_validate(fns: _ModelFns, data: ArmData, v: np.ndarray, grid: list[tuple],
                    k_folds: int | None, seed: int) -> tuple[np.ndarray, np.ndarray]:
    ctx = data.ctx_array
    u, d = jnp.asarray(data.u), jnp.asarray(data.d)
    n, p = len(data.u), fns.n_params
    errs, lpd = np.zeros(n), np.zeros(n)
    for fold in _folds(n, k_folds, seed):
        w = np.ones(n)
        w[fold] = 0.0
        wj = jnp.asarray(w)
        fit = _profile_fit(fns, v, ctx, grid, u, d, wj)
        # Predict every row (one compiled shape for all folds), keep the fold's.
        _, e, lp = _mixture_predictive(fns, fit, ctx, data.u, data.d,
                                       max(2 * (n - len(fold)) - p, 1))
        errs[fold], lpd[fold] = e[fold], lp[fold]
    return errs, lpd


def _mixture_predictive(fns: _ModelFns, fit: _Fit, ctx: jax.Array, u: np.ndarray,
                        d: np.ndarray, dof: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_predictive` mixed over the profiled structural settings, weighted by their
    profile likelihood exp(-(RSS - RSS_min) / 2 s^2): a point near a sign change is predicted
    as "one side or the other", not confidently on the wrong side."""
    fits = fit.all or [fit]
    s2_best = fit.cost / dof
    logw = np.array([-(f.cost - fit.cost) / (2 * s2_best) for f in fits])
    keep = logw > -20  # negligible weights: skip their predictions
    fits, logw = [f for f, k in zip(fits, keep, strict=True) if k], logw[keep]
    logw -= np.logaddexp.reduce(logw)
    preds, lpds = [], []
    for f in fits:
        s2, cov = _cov(f, dof)
        r, _, lp = _predictive(fns, f, ctx, u, d, s2, cov)
        preds.append(d - r)
        lpds.append(lp)
    w = np.exp(logw)
    mean = np.einsum("k,knj->nj", w, np.asarray(preds))
    r = d - mean
    lpd = np.logaddexp.reduce(logw[:, None] + np.asarray(lpds), axis=0)
    return r, np.linalg.norm(r, axis=1), lpd


def _magnitudes(fns: _ModelFns, data: ArmData, ev: ArmEval) -> dict:
    out = {}
    params = ev.params
    k = N_BASE
    for eff, size in zip(fns.effects_for(data.ctx, ev.settings), fns.sizes, strict=True):
        extra = ev.v[k:k + size]
        idx = list(range(N_BASE)) + list(range(k, k + size))
        cov = ev.cov[np.ix_(idx, idx)]
        rep = eff.magnitude_report(params, extra, cov)
        rep["params"] = {name: {"value": float(x), "se": float(math.sqrt(max(ev.cov[i, i], 0)))}
                         for i, (name, x) in enumerate(zip(eff.param_names(), extra,
                                                           strict=True), start=k)}
        if eff.setting is not None:
            rep["setting"] = np.asarray(eff.setting).tolist()
        out[eff.name] = rep
        k += size
    return out


def workspace_regions(points: np.ndarray) -> list[str]:
    """Name each point's third of the workspace: 'lower-left', 'middle-centre', ..."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    span = np.where(hi - lo > 0, hi - lo, 1.0)
    f = (points - lo) / span
    cols = np.array(["left", "centre", "right"])[np.minimum((f[:, 0] * 3).astype(int), 2)]
    rows = np.array(["lower", "middle", "upper"])[np.minimum((f[:, 1] * 3).astype(int), 2)]
    return [f"{r}-{c}" for r, c in zip(rows, cols, strict=True)]


def neighbour_pairs(points: np.ndarray) -> list[tuple[int, int]]:
    """Pairs of grid neighbours (not diagonals): closer than 1.25 typical nearest gaps."""
    dist = np.linalg.norm(points[:, None] - points[None], axis=-1)
    np.fill_diagonal(dist, np.inf)
    gap = np.median(dist.min(axis=1))
    i, j = np.nonzero(np.triu(dist < 1.25 * gap, 1))
    return list(zip(i.tolist(), j.tolist(), strict=True))


def morans_i(resid: np.ndarray, pairs: list[tuple[int, int]]) -> float:
    """Moran's I of a vector field over neighbour pairs: do neighbours err alike?"""
    r = resid - resid.mean(axis=0)
    if not pairs:
        return float("nan")
    i, j = np.array(pairs).T
    num = np.sum(r[i] * r[j]) / len(pairs)
    den = np.sum(r * r) / len(r)
    return float(num / den) if den > 0 else float("nan")


def residual_tests(data: ArmData, ev: ArmEval, candidates: Sequence[str] = (),
                   n_perm: int = 999, seed: int = 0) -> dict:
    """Structure in one arm's residual field that noise would not show, and where it is."""
    rng = np.random.default_rng(seed)
    resid = ev.resid_train
    ti, vi = data.replicate_pairs()
    field_ = resid.copy()
    if len(ti):
        field_[ti] = (resid[ti] + ev.resid_val[vi]) / 2
    points = data.d
    pairs = neighbour_pairs(points)
    regions = workspace_regions(points)
    out: dict = {"arm": data.name, "n": len(resid), "sigma_mm": ev.sigma_mm}

    moran = morans_i(field_, pairs)
    perm = np.array([morans_i(field_[rng.permutation(len(field_))], pairs)
                     for _ in range(n_perm)])
    out["morans_i"] = {"value": moran,
                       "p_value": float((1 + np.sum(perm >= moran)) / (n_perm + 1))}

    # lack of fit against pure error from the repeated commands (an F test)
    if len(ti) >= 3:
        pure = data.d[ti] - data.d_val[vi]
        ss_pe = float(np.sum(pure**2) / 2)
        df_pe = 2 * len(ti)
        mean_res = field_[ti]
        ss_lof = float(2 * np.sum(mean_res**2))
        df_lof = max(2 * len(ti) - (ev.v.size if len(ti) == len(resid) else 0), 1)
        F = (ss_lof / df_lof) / (ss_pe / df_pe)
        out["lack_of_fit"] = {"F": F, "df": [df_lof, df_pe],
                              "p_value": float(scipy.stats.f.sf(F, df_lof, df_pe)),
                              "pure_error_sigma_mm": math.sqrt(ss_pe / df_pe)}

    # Jumps: neighbours whose residuals differ by more than noise allows.
    if pairs:
        i, j = np.array(pairs).T
        jumps = np.linalg.norm(field_[i] - field_[j], axis=1)
        k = int(np.argmax(jumps))
        perm_max = np.array([np.max(np.linalg.norm(
            (q := field_[rng.permutation(len(field_))])[i] - q[j], axis=1))
            for _ in range(n_perm)])
        out["largest_jump"] = {
            "mm": float(jumps[k]), "between": [int(i[k]), int(j[k])],
            "where": _pair_where(regions[i[k]], regions[j[k]]),
            "p_value": float((1 + np.sum(perm_max >= jumps[k])) / (n_perm + 1))}

    # Where: the workspace third whose residuals are largest against the rest.
    mag = np.linalg.norm(field_, axis=1)
    names = sorted(set(regions))
    means = {r: float(np.mean(mag[[g == r for g in regions]])) for r in names}
    worst = max(means, key=means.get)
    rest = mag[[g != worst for g in regions]]
    out["worst_region"] = {"region": worst, "mean_mm": means[worst],
                           "elsewhere_mm": float(np.mean(rest)) if len(rest) else float("nan")}
    out["score_tests"] = {c: _score_test(data, ev, c) for c in candidates
                          if c not in ev.effects}
    return out


def _pair_where(a: str, b: str) -> str:
    (ra, ca), (rb, cb) = a.split("-"), b.split("-")
    if ca == cb and ra != rb:
        return f"{ca} column, {ra} to {rb}"
    if ra == rb and ca != cb:
        return f"{ra} row, {ca} to {cb}"
    return a if a == b else f"{a} to {b}"


def _score_test(data: ArmData, ev: ArmEval, name: str) -> dict:
    """The Lagrange-multiplier test of an effect at the current fit: T = r'P S (S'P S)^-1 S'P
    r / s^2 (S its signature, P off the fitted Jacobian), chi2 with the effect's parameter
    count; of structural settings the best (so the p value is optimistic)."""
    names = (*ev.effects, name)
    fns = model_fns(names)
    ctx = data.ctx_array
    u, d = jnp.asarray(data.u), jnp.asarray(data.d)
    n = len(data.u)
    v = np.concatenate([ev.v, *fns.initial_extra[len(ev.effects):]])
    p0 = ev.v.size
    best = None
    for s in _settings_grid(fns, data, ev.v):
        sj = _jsettings((*ev.settings, *s[len(ev.effects):]))
        r, J = fns.residuals(v, ctx, sj, u, d, jnp.ones(n))
        r, J = -r[: 2 * n], J[: 2 * n]
        A, S = J[:, :p0], J[:, p0:]
        Q, _ = np.linalg.qr(A)
        Sp = S - Q @ (Q.T @ S)
        rp = r - Q @ (Q.T @ r)
        coef, *_ = np.linalg.lstsq(Sp, rp, rcond=None)
        explained = float(rp @ (Sp @ coef))
        T = explained / ev.sigma_mm**2
        q = S.shape[1]
        if best is None or T > best["chi2"]:
            best = {"chi2": T, "df": q, "p_value": float(scipy.stats.chi2.sf(T, q)),
                    "explained_fraction": explained / max(float(rp @ rp), 1e-300)}
    return best


@dataclass
class Diagnosis:
    """Result of :func:`diagnose`; ``to_json`` is the ``--json`` document."""

    rig: str
    arms: list[str]
    rule: DecisionRule
    candidates: list[str]
    baseline: dict[str, ArmEval]
    final: dict[str, ArmEval]
    history: list[dict[str, ArmEval]]  # model after each step, starting with the baseline
    steps: list[dict]
    rounds: list[list[dict]]  # every candidate's score in every round
    tests_before: dict[str, dict]
    tests_after: dict[str, dict]
    data: dict[str, ArmData]

    @property
    def effects(self) -> list[str]:
        """Named effects in the order first named (a later step may add one to more arms)."""
        return list(dict.fromkeys(s["effect"] for s in self.steps))

    def to_json(self) -> dict:
        base = _pooled_errors(self.baseline)
        fin = _pooled_errors(self.final)
        return {
            "effects": self.effects,
            "steps": self.steps,
            "baseline_heldout_error_mm": base["heldout"],
            "final_heldout_error_mm": fin["heldout"],
            "baseline_cv_error_mm": base["cv"],
            "final_cv_error_mm": fin["cv"],
            # New poses (holdout rows); None when the rig has none. Reported, not decided on.
            "baseline_holdout_error_mm": base["holdout"],
            "final_holdout_error_mm": fin["holdout"],
            "rig": self.rig,
            "rule": self.rule.text(),
            "candidates": self.candidates,
            "rounds": self.rounds,
            "arms": {a: _arm_json(self.baseline[a], self.final[a], self.data[a])
                     for a in self.arms},
            "residual_tests": {"before": self.tests_before, "after": self.tests_after},
        }

    to_dict = to_json  # the name every result's JSON goes by (bayesrob.__all__)


def _mean(x: list[np.ndarray]) -> float | None:
    x = np.concatenate(x) if x else np.zeros(0)
    return float(np.mean(x)) if len(x) else None


def _pooled_errors(model: dict[str, ArmEval]) -> dict:
    return {"heldout": _mean([e.val_errors for e in model.values()]),
            "cv": _mean([e.cv_errors for e in model.values()]),
            "train": _mean([e.train_errors for e in model.values()]),
            "holdout": _mean([e.hold_errors for e in model.values()])}


def _arm_json(before: ArmEval, after: ArmEval, data: ArmData) -> dict:
    def errs(e: ArmEval) -> dict:
        p = _pooled_errors({e.arm: e})
        return {"train_error_mm": p["train"], "heldout_error_mm": p["heldout"],
                "cv_error_mm": p["cv"], "sigma_mm": e.sigma_mm, "holdout_error_mm": p["holdout"]}

    return {"effects": list(after.effects), "before": errs(before), "after": errs(after),
            "magnitudes": after.magnitudes(data),
            "params": {k: float(x) for k, x in zip(model_fns(after.effects).param_names,
                                                    after.v, strict=True)}}


def _pooled_lpd(model: dict[str, ArmEval]) -> np.ndarray:
    return np.concatenate([model[a].cv_lpd for a in model])


def _pooled_cv_errors(model: dict[str, ArmEval]) -> np.ndarray:
    return np.concatenate([model[a].cv_errors for a in model])


def halves(n: int, seed: int) -> np.ndarray:
    """Which half (0 or 1) of an arm's ``n`` train rows each row is in, drawn with the seed:
    the arms an effect is added to are chosen on one half and scored on the other."""
    h = np.zeros(n, int)
    h[np.random.default_rng([seed, n]).permutation(n)[: n // 2]] = 1
    return h


def _takes(before: ArmEval, after: ArmEval, rows: np.ndarray) -> bool:
    """Does an arm take the effect, judged on ``rows`` alone: its cross-validated elpd rises,
    or its error falls by 10% (with one of two needed effects in, the tightened fit can lose
    density on a few points while the errors fall)."""
    if not rows.any():
        return False
    gain = float(np.sum(after.cv_lpd[rows] - before.cv_lpd[rows]))
    shrink = np.mean(after.cv_errors[rows]) < 0.9 * np.mean(before.cv_errors[rows])
    return bool(gain > 0 or shrink)


def _crossfit(current: dict[str, ArmEval], cand: dict[str, ArmEval], seed: int
              ) -> tuple[np.ndarray, np.ndarray]:
    """Pooled cross-validated lpd and errors, each half of an arm's train rows predicted by
    the model chosen on the other half."""
    cv, err = [], []
    for a, cur in current.items():
        n = len(cur.cv_lpd)
        half = halves(n, seed)
        pick = np.zeros(n, bool)
        if a in cand:
            for h in (0, 1):
                pick[half == h] = _takes(cur, cand[a], half != h)
        new = cand.get(a, cur)
        cv.append(np.where(pick, new.cv_lpd, cur.cv_lpd))
        err.append(np.where(pick, new.cv_errors, cur.cv_errors))
    return np.concatenate(cv), np.concatenate(err)


def _score_candidate(name: str, current: dict[str, ArmEval], cand: dict[str, ArmEval],
                     rule: DecisionRule, seed: int = 0) -> dict:
    """Pool a candidate's arms (the arms it helps get it), scored cross-fitted
    (:func:`_crossfit`) so the choice of arms does not flatter it."""
    arms = [a for a in cand
            if _takes(current[a], cand[a], np.ones(len(current[a].cv_lpd), bool))]
    cv, cv_err = _crossfit(current, cand, seed)
    s = _step_record(name, arms, current, {a: (cand[a] if a in arms else current[a])
                                           for a in current}, cv, float(np.mean(cv_err)))
    # the parameters the candidate adds to the arms that take it
    s["parameters"] = int(sum(cand[x].v.size - current[x].v.size for x in arms))
    s["z"] = paired_z(_pooled_cv_errors(current), cv_err)
    s["drop_per_parameter_mm"] = (s["cv_error_before_mm"] - s["cv_error_after_mm"]) / max(
        s["parameters"], 1)
    s["guard_nats"] = rule.threshold(s["parameters"])
    s["guard_passes"] = rule.guard_passes(s)
    s["_cv_errors"] = cv_err
    s["elpd_gain_per_arm"] = {x: float(np.sum(cand[x].cv_lpd - current[x].cv_lpd))
                              for x in cand}
    s["passes"] = rule.passes(s)
    return s


def _step_record(name: str, arms: list[str], before: dict[str, ArmEval],
                 after: dict[str, ArmEval], cv: np.ndarray | None = None,
                 cv_error: float | None = None) -> dict:
    """One named step (or a candidate's score): the effect, its arms and the gap before and
    after; ``cv``, ``cv_error``: the cross-fitted lpd and error in place of ``after``'s."""
    diff, dse = elpd_diff(_pooled_lpd(before), _pooled_lpd(after) if cv is None else cv)
    b, a = _pooled_errors(before), _pooled_errors(after)
    return {"effect": name, "arms": list(arms), "heldout_error_before_mm": b["heldout"],
            "heldout_error_after_mm": a["heldout"], "elpd_diff": diff, "elpd_diff_se": dse,
            "cv_error_before_mm": b["cv"],
            "cv_error_after_mm": a["cv"] if cv_error is None else cv_error,
            "heldout_elpd_diff": float(sum(np.sum(after[x].val_lpd - before[x].val_lpd)
                                           for x in before)),
            "holdout_error_before_mm": b["holdout"], "holdout_error_after_mm": a["holdout"]}


def _pair_scores(candidates: Sequence[str], current: dict[str, ArmEval],
                 fitted: dict[str, dict[str, ArmEval]], add: Callable,
                 rule: DecisionRule, seed: int = 0) -> list[dict]:
    """Score every pair of candidates added together; a pair passes against the current
    model *and* each member alone, so both effects are needed."""
    out = []
    for i, first in enumerate(candidates):
        for second in candidates[i + 1:]:
            if not fitted.get(first) or not fitted.get(second):
                continue
            mid = {**current, **fitted[first]}
            both = add(mid, second)
            full = {a: both.get(a, mid[a]) for a in current
                    if a in both or a in fitted[first]}
            s = _score_candidate(f"{first}+{second}", current, full, rule, seed)
            s["pair"] = [first, second]
            if s["passes"]:
                cv, _ = _crossfit(current, full, seed)
                over = []
                for member in (first, second):
                    alone = {**current, **fitted[member]}
                    s[f"elpd_diff_over_{member}"] = list(elpd_diff(_pooled_lpd(alone), cv))
                    over.append(paired_z(_pooled_cv_errors(alone), s["_cv_errors"]))
                    s[f"z_over_{member}"] = over[-1]
                s["passes"] = rule.pair_passes(s, over)
            out.append(s)
    return out


def diagnose(rig: Rig, candidates: Sequence[str] | None = None, rule: DecisionRule | None = None,
             k_folds: int | None = None, seed: int = 0, progress: bool = False,
             max_steps: int | None = None) -> Diagnosis:
    """Run the model-criticism workflow on a rig's single-arm rows; ``candidates`` as
    :func:`bayesrob.robot.effects.resolve_effects` takes them (default: all)."""
    from bayesrob.progress import progress as make_progress

    rule = rule or DecisionRule()
    candidates = fx.resolve_effects(candidates)
    arms = list(rig.arms)
    data = {a: ArmData.from_rig(rig, a) for a in arms}
    bar = make_progress(len(arms) * (1 + len(candidates) * (len(candidates) + 1) // 2),
                        "diagnose", "fits", enabled=progress)

    cache: dict[tuple[str, tuple[str, ...]], ArmEval] = {}

    def ev(a: str, names: tuple[str, ...], start: ArmEval | None) -> ArmEval:
        if (a, names) not in cache:
            cache[(a, names)] = evaluate_arm(data[a], names, start, k_folds=k_folds,
                                             seed=seed)
            if bar.n + 1 > bar.total:
                # pairs of effects are tried when no single one pays: more fits than planned
                bar.total = bar.n + 1
                bar.set_postfix("more fits than planned: pairs of effects tried")
            bar.update()
        return cache[(a, names)]

    current = {a: ev(a, (), None) for a in arms}
    baseline = dict(current)
    tests_before = {a: residual_tests(data[a], current[a], candidates, seed=seed) for a in arms}
    history, steps, rounds = [dict(current)], [], []
    # An effect stays a candidate for the arms without it: one may need it once another is in.
    pending = {a: list(candidates) for a in arms}

    def add(model: dict[str, ArmEval], name: str, only: Sequence[str] | None = None
            ) -> dict[str, ArmEval]:
        """``name`` fitted into each arm's model where it is pending (and in ``only``)."""
        return {a: ev(a, (*model[a].effects, name), model[a]) for a in arms
                if name in pending[a] and (only is None or a in only)}

    def take(name: str, arms_: list[str], new: dict[str, ArmEval], **extra) -> None:
        if not arms_:
            return
        before = dict(current)
        for a in arms_:
            current[a] = new[a]
            pending[a].remove(name)
        step = _step_record(name, arms_, before, current)
        step.update(extra)
        step["magnitudes"] = {a: current[a].magnitudes(data[a])[name] for a in arms_}
        steps.append(step)
        history.append(dict(current))

    while any(pending.values()) and (max_steps is None or len(steps) < max_steps):
        scores, fitted = [], {}
        for name in candidates:
            fitted[name] = add(current, name)
            if fitted[name]:
                scores.append(_score_candidate(name, current, fitted[name], rule, seed))
        passing = [s for s in scores if s["passes"]]
        if not passing and not steps:
            # Two hidden effects may only pay together (sag bends the map that backlash is
            # judged against): before concluding that nothing is missing, try the pairs.
            pairs = _pair_scores(candidates, current, fitted, add, rule, seed)
            scores += pairs
            rounds.append(public_scores(scores))
            joint = [s for s in pairs if s["passes"]]
            if not joint:
                break
            best = rule.best(joint)
            first, second = best["pair"]
            mid = fitted[first]
            take(first, [a for a in best["arms"] if a in mid], mid, joint_with=second,
                 joint_elpd_diff=best["elpd_diff"], joint_elpd_diff_se=best["elpd_diff_se"])
            arms2 = [a for a in best["arms"] if second in pending[a]]
            take(second, arms2, add(current, second, arms2), joint_with=first,
                 joint_elpd_diff=best["elpd_diff"], joint_elpd_diff_se=best["elpd_diff_se"])
            continue
        rounds.append(public_scores(scores))
        if not passing:
            break
        best = rule.best(passing)
        take(best["effect"], best["arms"], fitted[best["effect"]])
    if bar.total and bar.n < bar.total:
        # the plan counted a step for every candidate; the search stops at the first round in
        # which none passes, so the fits it did not need are dropped from the count
        bar.set_postfix(f"{bar.total - bar.n} planned fits not needed: no further effect "
                        "passed")
        bar.total = bar.n
    bar.close()
    tests_after = {a: residual_tests(data[a], current[a], candidates, seed=seed) for a in arms}
    return Diagnosis(rig.name, arms, rule, candidates, baseline, current, history, steps,
                     rounds, tests_before, tests_after, data)


def diagnose_rig(path: str | Path, candidates: Sequence[str] | None = None,
                 progress: bool = False, **kwargs) -> Diagnosis:
    """Load a rig directory and diagnose it (the ``bayesrob diagnose`` command's work)."""
    from bayesrob.data.rig import load_rig

    return diagnose(load_rig(path), candidates, progress=progress, **kwargs)


__all__ = ["ArmData", "ArmEval", "Diagnosis", "diagnose", "diagnose_rig",
           "evaluate_arm", "residual_tests"]
