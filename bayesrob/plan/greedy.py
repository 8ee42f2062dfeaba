"""Greedy selection with rank-dim updates: the pose that helps most given those before it.
Every prefix is the greedy plan of its length, so stopping early still leaves a good plan
(for D-optimality within (1 - 1/e) of the best set: log det is submodular).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bayesrob.plan.criteria import Accuracy, Criterion


@dataclass
class Selection:
    """Poses chosen in order (any prefix is the greedy plan of its length) and the
    criterion's value before the first and after each."""

    order: np.ndarray  # (n,) candidate indices, best first
    gains: np.ndarray  # (n,) the criterion's improvement each brought when it was chosen
    before: float
    values: np.ndarray  # (n,) the criterion after each pose


def greedy(jac: np.ndarray, info: np.ndarray, n: int, criterion: Criterion) -> Selection:
    """Choose ``n`` of the candidates ``jac`` (N, dim, p; Jacobians over the noise sd) one at a
    time, from the information ``info`` (p, p) of the prior and rows measured; rank-dim
    updates of C and every B_i = J_i C make a step O(N dim^2 p)."""
    cov = np.linalg.inv(info)
    cov = (cov + cov.T) / 2
    n_cand, dim, p = jac.shape
    flat = jac.reshape(-1, p)
    b = (flat @ cov).reshape(jac.shape)
    s = np.eye(dim) + jac @ b.transpose(0, 2, 1)
    # what accuracy keeps per candidate (B_i A, ...) follows the same rank-dim updates
    keeps = isinstance(criterion, Accuracy)
    if keeps:
        criterion.start(jac, b, cov)
    before = criterion.value(cov)
    taken = np.zeros(n_cand, bool)
    order, gains, values = [], [], []
    for _ in range(n):
        s_inv = np.linalg.inv(s)
        g = np.asarray(criterion.gains(jac, b, s_inv, cov), float)
        g[taken | ~np.isfinite(g)] = -np.inf
        k = int(np.argmax(g))
        taken[k] = True
        # C' = C - B_k^T S_k^-1 B_k; every B_i = J_i C, S_i = I + J_i C J_i^T and B_i A with it
        bk, sk = b[k].copy(), s_inv[k].copy()
        jb = (flat @ bk.T).reshape(n_cand, dim, dim)  # J_i B_k^T
        cov = cov - bk.T @ sk @ bk
        cov = (cov + cov.T) / 2
        b -= (jb.reshape(-1, dim) @ (sk @ bk)).reshape(jac.shape)
        s -= jb @ sk @ jb.transpose(0, 2, 1)
        if keeps:
            criterion.update(k, jb, sk, bk)
        order.append(k)
        values.append(criterion.value(cov))
        last = values[-2] if len(values) > 1 else before
        gains.append(last - values[-1] if isinstance(criterion, Accuracy)
                     else values[-1] - last)
    return Selection(np.array(order, int), np.array(gains), before, np.array(values))
