"""Which parameters the rows can identify: a rank analysis of the residuals' Jacobian. A
column the earlier (simpler) ones explain is held at nominal, reported with what explains it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bayesrob import robot as kin

# Groups are tried in this order when the rank analysis decides which of two redundant
# parameters to keep: the simpler explanation (a frame, a joint offset, a gain) before a
# general correction of a joint's origin.
PRIORITY = ("frames", "offsets", "servo", "geometric", "compliance", "lateral", "encoder",
            "backlash", "servo_curve")
# A column is identifiable when the part of it no earlier column explains is at least this
# fraction of its length (column-scaled to each parameter's typical size). Exact
# redundancies sit at 1e-10 and below; 1e-4 also drops directions whose standard error would
# be thousands of times the noise, which only fit noise.
RANK_TOL = 1e-4


@dataclass
class Identifiability:
    free: np.ndarray  # (P,) bool: fitted
    not_observed: list[str]  # no measured point depends on these at all
    unidentifiable: list[dict]  # {"name", "group", "explained_by": {name: coefficient}}


def identifiability(jac: np.ndarray, layout: kin.ParamLayout, candidates: np.ndarray
                    ) -> Identifiability:
    """Rank analysis of the column-scaled Jacobian: a greedy, priority-ordered Gram-Schmidt
    (a rank-revealing QR whose pivots follow :data:`PRIORITY` rather than column norms, so
    the parameter kept of a redundant pair is the one with the plain name)."""
    js = np.asarray(jac) * layout.scales[None, :]
    norms = np.linalg.norm(js, axis=0)
    top = norms[candidates].max() if candidates.any() else 1.0
    order = [i for g in PRIORITY for i, p in enumerate(layout.params)
             if p.group == g and candidates[i]]
    basis = np.zeros((js.shape[0], 0))
    free = np.zeros(len(layout.params), bool)
    not_observed, dropped = [], []
    for i in order:
        c = js[:, i]
        if norms[i] <= 1e-12 * top:
            not_observed.append(layout.params[i].name)
            continue
        r = c - basis @ (basis.T @ c)
        r = r - basis @ (basis.T @ r)  # twice: classical Gram-Schmidt loses orthogonality
        if np.linalg.norm(r) > RANK_TOL * norms[i]:
            basis = np.column_stack([basis, r / np.linalg.norm(r)])
            free[i] = True
        else:
            dropped.append(i)
    kept = np.flatnonzero(free)
    unident = []
    # every dropped column at once: one factorisation of the kept columns (one solve per
    # column took 8.6 s of a compliance fit's 11 s on a linked 6-joint pair)
    coefs = (np.linalg.lstsq(js[:, kept], js[:, dropped], rcond=None)[0] if dropped
             else np.zeros((len(kept), 0)))
    for col, i in enumerate(dropped):
        # back to parameter units: J_i ~ sum_k coef_k (s_k / s_i) J_k
        coef = coefs[:, col] * layout.scales[kept] / layout.scales[i]
        big = np.argsort(-np.abs(coef))[:3]
        unident.append({
            "name": layout.params[i].name, "group": layout.params[i].group,
            "explained_by": {layout.params[kept[k]].name: float(coef[k]) for k in big
                             if abs(coef[k]) > 1e-3 * np.abs(coef).max()}})
    return Identifiability(free, not_observed, unident)
