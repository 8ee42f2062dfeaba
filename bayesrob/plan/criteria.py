"""What measuring a pose is worth to a calibration, from its linearised posterior.

The calibration's parameters z (each in its typical size, ``ParamLayout.scales``) have,
after rows with Jacobian J and measurement noise sigma, the Gaussian posterior covariance
C = (J^T J / sigma^2 + I / s_p^2)^-1 about the fit (s_p: PRIOR_SD unless given). One more
pose i (its marker's Jacobian J_i, dim x p, over sigma) changes it by a rank-dim update:
with B_i = J_i C and S_i = I + J_i C J_i^T, C' = C - B_i^T S_i^-1 B_i. Each criterion scores
every candidate from its B_i and S_i at once:

- ``accuracy``: the predicted end-point error over a task region, sqrt(tr(A C) + bias) mm,
  A = G^T G / T from the task poses' Jacobians G (I-optimal). The bias is that of omitted
  effects (parameters w, prior sd s, signature K at the rows and H at the task): the fit
  absorbs D w = C J^T K w, so the error gains s^2 (tr(D^T A D) - 2 tr(D^T R) + e0),
  R = G^T H / T, e0 = tr(H^T H) / T (without it the plan shrinks a variance the omitted sag
  outweighs); one pose moves D by B_i^T S_i^-1 (K_i - J_i D).
- ``identify``: log det C^-1 (D-optimal); a pose's gain is log det S_i.
- ``discriminate``: per candidate effect E, -log det C_EE (D_s-optimal: the part of its
  signature no other parameter mimics); a pose's gain sums -log det(I - S_i^-1 B_iE C_EE^-1
  B_iE^T).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

CRITERIA = ("accuracy", "identify", "discriminate")
# Prior sd of every parameter, in its typical size (1 mm, 1 mrad, 0.1% of a gain): wide
# enough that any pose set which fixes a parameter fixes it by its rows, not by this; it keeps
# the covariance finite before the first row and on directions no pose can see.
PRIOR_SD = 100.0


def _logdet(m: np.ndarray) -> np.ndarray:
    sign, value = np.linalg.slogdet(m)
    return np.where(sign > 0, value, -np.inf)


@dataclass
class Accuracy:
    """Predicted end-point error (mm, RMS over the task poses) from the parameters' spread and
    the bias of the omitted parameters (none where ``omitted`` is None)."""

    task: np.ndarray  # (p, p): G^T G / T of the task poses' Jacobians (mm per typical size)
    omitted: np.ndarray | None = None  # (N, dim, q): the candidates' K, over the noise sd
    cross: np.ndarray | None = None  # (p, q): R = G^T H / T
    e0: float = 0.0  # tr(H^T H) / T, mm^2
    measured: np.ndarray | None = None  # (p, q): J^T K of the rows measured already
    sd: float = 0.0  # the omitted parameters' prior sd, in their typical sizes
    unit = "mm"

    def _bias(self) -> float:
        if self.omitted is None:
            return 0.0
        d = self.d
        return self.sd**2 * float(np.einsum("pq,pr,rq->", d, self.task, d)
                                  - 2 * np.einsum("pq,pq->", d, self.cross) + self.e0)

    def start(self, jac: np.ndarray, b: np.ndarray, cov: np.ndarray) -> None:
        n, dim, p = b.shape
        self.ba = (b.reshape(-1, p) @ self.task).reshape(n, dim, p)  # B_i A, kept up to date
        if self.omitted is None:
            return
        q = self.omitted.shape[2]
        self.d = cov @ (np.zeros((p, q)) if self.measured is None else self.measured)
        self.kjd = self.omitted - (jac.reshape(-1, p) @ self.d).reshape(n, dim, q)
        self.m = (b.reshape(-1, p) @ (self.task @ self.d - self.cross)).reshape(n, dim, q)

    def update(self, k: int, jb: np.ndarray, sk: np.ndarray, bk: np.ndarray) -> None:
        """Pose ``k`` chosen (``bk`` = B_k, ``sk`` = S_k^-1 before it; ``jb`` = J_i B_k^T):
        B_i A, D, K_i - J_i D and M_i = B_i (A D - R) follow the rank-dim update."""
        n, dim, p = self.ba.shape
        jbs = jb.reshape(-1, dim) @ sk
        self.ba -= (jbs @ (bk @ self.task)).reshape(n, dim, p)
        if self.omitted is None:
            return
        q = self.d.shape[1]
        u = sk @ self.kjd[k]
        self.m -= (jbs @ (bk @ (self.task @ self.d - self.cross))).reshape(n, dim, q)
        self.m += (self.ba @ bk.T) @ u
        self.d += bk.T @ u
        self.kjd -= jb @ u

    def value(self, cov: np.ndarray) -> float:
        return float(np.sqrt(max(np.einsum("ij,ji->", self.task, cov) + self._bias(), 0.0)))

    def gains(self, jac: np.ndarray, b: np.ndarray, s_inv: np.ndarray,
              cov: np.ndarray) -> np.ndarray:
        bab = self.ba @ b.transpose(0, 2, 1)
        gain = np.einsum("nde,ned->n", s_inv, bab)
        if self.omitted is not None:
            u = s_inv @ self.kjd
            gain -= self.sd**2 * (2 * np.einsum("ndq,ndq->n", u, self.m)
                                  + np.einsum("ndq,ndq->n", u, bab @ u))
        return gain


@dataclass
class Identify:
    """log det of the parameters' information (nats): D-optimality."""

    unit = "nats"

    def value(self, cov: np.ndarray) -> float:
        return float(-_logdet(cov))

    def gains(self, jac: np.ndarray, b: np.ndarray, s_inv: np.ndarray,
              cov: np.ndarray) -> np.ndarray:
        return -_logdet(s_inv)


@dataclass
class Discriminate:
    """Summed log det of each candidate effect's information with every other parameter
    fitted beside it (nats): D_s-optimality per effect."""

    effects: dict[str, np.ndarray]  # effect -> its parameters' indices in the planned vector
    unit = "nats"

    def value(self, cov: np.ndarray) -> float:
        return float(sum(-_logdet(cov[np.ix_(i, i)]) for i in self.effects.values()))

    def gains(self, jac: np.ndarray, b: np.ndarray, s_inv: np.ndarray,
              cov: np.ndarray) -> np.ndarray:
        eye = np.eye(jac.shape[1])
        total = np.zeros(len(jac))
        for idx in self.effects.values():
            be = b[:, :, idx]
            m = (be @ np.linalg.inv(cov[np.ix_(idx, idx)])) @ be.transpose(0, 2, 1)
            total += -_logdet(eye - s_inv @ m)
        return total


Criterion = Accuracy | Identify | Discriminate
