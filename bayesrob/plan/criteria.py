"""What measuring a pose is worth to a calibration, from its linearised posterior.

The calibration's parameters z (each in its typical size, ``ParamLayout.scales``) have,
after rows with Jacobian J and measurement noise sigma, the Gaussian posterior covariance
C = (J^T J / sigma^2 + I / PRIOR_SD^2)^-1 about the fit. Measuring one more pose i (its
marker's Jacobian J_i, dim x p, already divided by sigma) changes it by a rank-dim update:
with B_i = J_i C and S_i = I + J_i C J_i^T, C' = C - B_i^T S_i^-1 B_i. Each criterion scores
every candidate from its B_i and S_i at once:

- ``accuracy``: the predicted end-point error over a task region, sqrt(tr(A C)) mm with
  A = G^T G / T from the task poses' Jacobians G (A-/I-optimal in the end point); a pose's
  gain is the drop of tr(A C), tr(S_i^-1 B_i A B_i^T).
- ``identify``: the information on the parameters, log det C^-1 (D-optimal, the classic
  criterion); a pose's gain is log det S_i (the matrix determinant lemma).
- ``discriminate``: for each candidate effect E (a group of parameters beside the base
  model and the other effects), log det of its information once every other parameter is
  fitted too, -log det C_EE (D_s-optimal: the part of the effect's signature no other
  parameter can mimic, the classic criterion for telling nested models apart). A pose's gain
  sums, over the effects, -log det(I - S_i^-1 B_iE C_EE^-1 B_iE^T).
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
    """Predicted end-point error (mm, RMS over the task poses) from the parameters' spread."""

    task: np.ndarray  # (p, p): G^T G / T of the task poses' Jacobians (mm per typical size)
    unit = "mm"

    def value(self, cov: np.ndarray) -> float:
        return float(np.sqrt(max(np.einsum("ij,ji->", self.task, cov), 0.0)))

    def gains(self, jac: np.ndarray, b: np.ndarray, s_inv: np.ndarray, cov: np.ndarray,
              ba: np.ndarray | None = None) -> np.ndarray:
        """``ba``: B_i A for every candidate, where the caller keeps it up to date."""
        n, dim, p = b.shape
        if ba is None:
            ba = (b.reshape(-1, p) @ self.task).reshape(n, dim, p)
        return np.einsum("nde,ned->n", s_inv, ba @ b.transpose(0, 2, 1))


@dataclass
class Identify:
    """log det of the parameters' information (nats): D-optimality."""

    unit = "nats"

    def value(self, cov: np.ndarray) -> float:
        return float(-_logdet(cov))

    def gains(self, jac: np.ndarray, b: np.ndarray, s_inv: np.ndarray, cov: np.ndarray,
              ba: np.ndarray | None = None) -> np.ndarray:
        return -_logdet(s_inv)


@dataclass
class Discriminate:
    """Summed log det of each candidate effect's information with every other parameter
    fitted beside it (nats): D_s-optimality per effect."""

    effects: dict[str, np.ndarray]  # effect -> its parameters' indices in the planned vector
    unit = "nats"

    def value(self, cov: np.ndarray) -> float:
        return float(sum(-_logdet(cov[np.ix_(i, i)]) for i in self.effects.values()))

    def gains(self, jac: np.ndarray, b: np.ndarray, s_inv: np.ndarray, cov: np.ndarray,
              ba: np.ndarray | None = None) -> np.ndarray:
        eye = np.eye(jac.shape[1])
        total = np.zeros(len(jac))
        for idx in self.effects.values():
            be = b[:, :, idx]
            m = (be @ np.linalg.inv(cov[np.ix_(idx, idx)])) @ be.transpose(0, 2, 1)
            total += -_logdet(eye - s_inv @ m)
        return total


Criterion = Accuracy | Identify | Discriminate
