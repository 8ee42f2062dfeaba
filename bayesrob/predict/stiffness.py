"""The joint stiffnesses linked arms balance with (equilibrium fusion, :mod:`.fusion`).

:class:`StiffnessPrior` of an arm's log joint stiffnesses along its path: the rig's when given;
else read from compliances fitted under the description's link masses; else log-normal, on
chains centred on the URDF torque limits with an arm term centred on the arm's fitted sag
(:func:`sag_scaled_priors`), on planar servo arms equal joints (:func:`given_or_servo_prior`).
Only the ratios of the arms' stiffnesses move the balance.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import numpyro
import numpyro.distributions as dist
from numpyro.infer import Predictive

from bayesrob.calibrate.least_squares import Calibration
from bayesrob.data.rig import Rig

__all__ = ["StiffnessPrior", "STIFFNESS_SOURCES", "STIFFNESS_LOG_SD", "given_or_servo_prior",
           "stiffness_prior", "arm_sags",
           "sag_scaled_priors", "stiffness_priors", "stiffness_draws"]

# The joint stiffness prior when the rig does not give them. Chosen on two sets of linked
# tuning rigs (arm6 --linked, each seed drawing its own arms' stiffnesses; 201-206, 24 points
# each, and 271-282, 8 each: 240 points; `bench_predict_3d.py --coverage tuning [--many-rigs]
# --variants`) as the prior whose pooled 50% / 90% coverage came closest to nominal: 0.47 /
# 0.96 (arm sd 0.5, chosen on 201-206 alone before: 0.64 / 0.98). Tried: per-joint sd 0.25 /
# 0.5 / 0.75, arm sd 0 / 0.25 / 0.5, centred on equal joints or on the torque limits. No prior
# moves the mean error's ratio by much (1.14-1.27 over all 18 on 271-282).
CHAIN_STIFFNESS_LOG_SD = 0.5  # each joint's own
CHAIN_STIFFNESS_ARM_LOG_SD = 0.25  # shared by an arm's joints: an arm stiffer or softer as a whole
# Where the prior is centred: "effort", each joint's stiffness in proportion to its URDF torque
# limit (a bigger drive is a stiffer one; equal joints where the file gives no limit), or
# "equal" joints
CHAIN_STIFFNESS_CENTRE = "effort"
# Where the arm term is centred when every linked arm takes the prior: "sags", each arm's log
# stiffness scale set against the others' by its fitted sag at the poses they were all trained
# on (:func:`sag_scaled_priors`), or "equal" arms (the two sds above).
CHAIN_STIFFNESS_ARM_CENTRE = "sags"
# The sag-centred prior's own per-joint and arm-term log sds: chosen on the tuning rigs
# 271-282 and 201-206 (`bench_predict_3d.py --coverage tuning [--many-rigs] --sag-variants`,
# 240 points) by a rule written before the sweep, the smallest largest miss relative to each
# target's half-width: 0.512 / 0.892, error ratio 0.929, against 0.471 / 0.958, 1.081 for the
# equal-arms prior (docs/fusion.md)
SAG_SCALED_LOG_SD = 0.4
SAG_SCALED_ARM_LOG_SD = 0.5
# How far a robot description's link masses are trusted (log sd): a compliance fitted under
# them carries their error into the stiffness read from it.
DESCRIBED_MASS_LOG_SD = 0.1
# The paper's planar servo arms: each joint's own log sd, no arm term: a factor e^0.4 = 1.5
# at one sd, about the spread of the simulator's per-seed draws (0.3 per arm and 0.3 per
# joint: sqrt(2) 0.3 = 0.42 per joint). Chosen on planar tuning rigs (seeds 101-106,
# stiffnesses drawn), never on the reported ones: the widest of 0.75 / 0.5 / 0.4 / 0.3 / 0.25
# that met every linked target there (docs/fusion.md).
STIFFNESS_LOG_SD = 0.4

class StiffnessPrior(NamedTuple):
    """An arm's log joint stiffnesses along its path: Normal(centre, sd) per joint (sd 0:
    known), plus an arm term where ``shared`` (the arm stiffer or softer as a whole);
    ``source`` is one of ``STIFFNESS_SOURCES``."""

    centre: np.ndarray
    sd: np.ndarray
    shared: np.ndarray
    source: str
    # the arm term's mean (its log scale against the other linked arms') and sd (None: the
    # module's CHAIN_STIFFNESS_ARM_LOG_SD as it stands when drawn: a sweep of priors sets it)
    arm_centre: float = 0.0
    arm_sd: float | None = None

    def arm_term_sd(self) -> float:
        return CHAIN_STIFFNESS_ARM_LOG_SD if self.arm_sd is None else self.arm_sd

    def record(self) -> dict[str, Any]:
        """The prior for a report (``predict``'s ``stiffness.<arm>``): ``from``, medians (N mm/rad,
        or ``relative`` to the first joint under the prior, whose scale is arbitrary), log
        sds, ``arm_log_centre``, and under the prior the arm term's sd."""
        k = np.exp(self.centre)
        out: dict[str, Any] = {"from": self.source}
        if np.any(self.shared):
            out |= {"relative": [float(v) for v in k / k[0]],
                    "log_sd": [float(v) for v in self.sd], "arm_log_sd": self.arm_term_sd()}
        else:
            out |= {"nmm_per_rad": [float(v) for v in k], "log_sd": [float(v) for v in self.sd]}
        return out | {"arm_log_centre": float(self.arm_centre)}


STIFFNESS_SOURCES = ("the rig", "compliances fitted under the URDF's masses", "the prior",
                     "the prior, the arms scaled by their fitted sags")


def given_or_servo_prior(k: Sequence[float] | None, n: int = 2) -> StiffnessPrior:
    """A planar servo arm's prior: the rig's stiffnesses ``k`` (N mm/rad), else ``n`` equal
    joints of log sd STIFFNESS_LOG_SD."""
    if k is not None:
        k = np.asarray(k, float)
        return StiffnessPrior(np.log(k), np.zeros_like(k), np.zeros(k.shape, bool),
                              STIFFNESS_SOURCES[0])
    return StiffnessPrior(np.zeros(n), np.full(n, STIFFNESS_LOG_SD), np.zeros(n, bool),
                          STIFFNESS_SOURCES[2])


def stiffness_prior(rig: Rig, arm: str, cal: Calibration | None = None
                     ) -> StiffnessPrior:
    """The log joint stiffnesses along the path to ``arm``: the rig's; else from compliances
    fitted under the description's masses (the unseen joints scaled to them); else the prior."""
    parts = [getattr(rig.arms[c.name], "stiffness", None) for c in rig.robot.path(arm)]
    if all(p is not None for p in parts):
        return given_or_servo_prior(np.concatenate(parts))
    n = rig.robot.n_path_joints(arm)
    efforts = [c.source.get("efforts") for c in rig.robot.path(arm)]
    centre = (np.log(np.concatenate(efforts))
              if CHAIN_STIFFNESS_CENTRE == "effort" and all(e is not None for e in efforts)
              else np.zeros(n))
    sd = np.full(n, CHAIN_STIFFNESS_LOG_SD)
    if cal is None or cal.masses != "description" or "compliance" not in cal.groups:
        # Not from compliances fitted with the masses: then only compliance x first moment is
        # identified, so each arm's compliances carry its own unknown mass scale. Read as
        # stiffnesses they put the arms' ratio 4.5 times off on a report rig (seed 2) and
        # overflowed on another (seed 1), though they helped on the tuning rigs.
        return StiffnessPrior(centre, sd, np.ones(n, bool), STIFFNESS_SOURCES[2])
    layout = cal.robot.layout
    every = np.arange(layout.nominal.size)
    idx = np.concatenate([every[layout.slices[c.name, "compliance"]]
                          for c in rig.robot.path(arm)])
    c, se, free = cal.x[idx], cal.se[idx], cal.ident.free[idx]
    seen = free & (c > 0) & np.isfinite(se)
    if not seen.any():
        return StiffnessPrior(centre, sd, np.ones(n, bool), STIFFNESS_SOURCES[2])
    # The prior, log k_j = scale + profile_j + N(0, sd), updated by the fitted compliances
    # (each log k_j measured with its standard error and the masses' accuracy): the arm's
    # scale is their precision-weighted mean about the profile, so a poorly seen joint (a
    # wrist that gravity hardly turns) neither sets it nor leaves the profile by much; a joint
    # gravity never turns (a vertical axis) keeps the profile at that scale.
    y = -np.log(np.where(seen, c, 1.0))
    var_fit = (se / np.where(seen, c, 1.0)) ** 2 + DESCRIBED_MASS_LOG_SD**2
    w = np.where(seen, 1.0 / (sd**2 + var_fit), 0.0)
    scale = np.sum(w * (y - centre)) / w.sum()
    prior_mean, prior_var = centre + scale, sd**2 + 1.0 / w.sum()
    post_var = np.where(seen, 1.0 / (1.0 / prior_var + 1.0 / np.where(seen, var_fit, 1.0)),
                        prior_var)
    centre = np.where(seen, post_var * (prior_mean / prior_var + y / var_fit), prior_mean)
    sd = np.sqrt(post_var)
    return StiffnessPrior(centre, sd, np.zeros(n, bool), STIFFNESS_SOURCES[1])


def arm_sags(rig: Rig, cal: Calibration, arms: Sequence[str]) -> dict[str, float] | None:
    """Each arm's mean fitted sag (mm): how far its marker moves with its own chains'
    compliances zeroed, over all ``arms``' train poses pooled; None where that cannot be read
    (paths of other joint counts, no compliance or gravity, or an arm without sag)."""
    robot = cal.robot
    if ("compliance" not in cal.groups or robot.gravity is None or len(arms) < 2
            or len({robot.n_path_joints(a) for a in arms}) > 1):
        return None
    shared = set.intersection(*({c.name for c in robot.path(a)} for a in arms))
    u = jnp.asarray(np.concatenate([rig.rows(a, "train")[0] for a in arms]))
    sags = {}
    for a in arms:
        rigid = np.array(cal.x, float)
        for c in robot.path(a):
            if c.name not in shared:
                rigid[robot.layout.slices[c.name, "compliance"]] = 0.0
        points = robot.compiled_points(a)
        moved = np.asarray(points(jnp.asarray(cal.x), u) - points(jnp.asarray(rigid), u))
        sags[a] = float(np.linalg.norm(moved, axis=1).mean())
    if not all(np.isfinite(v) and v > 0 for v in sags.values()):
        return None
    return sags


def sag_scaled_priors(rig: Rig, cal: Calibration, priors: dict[str, StiffnessPrior]
                      ) -> dict[str, StiffnessPrior]:
    """``priors`` with each arm's term centred on its fitted sag against the others' (log k_a
    = mean log sag - log sag_a), where every arm took the prior; else as given.

    A fit without the masses identifies compliance times first moment, not stiffness; but arms
    of one model carry alike moments, so the arm that sags further is the softer one. On the
    tuning rigs the log sag ratio followed the true log stiffness ratio with slope -0.98 /
    -0.94, scattered by about 0.25 (docs/fusion.md).
    """
    if (CHAIN_STIFFNESS_ARM_CENTRE != "sags"
            or any(p.source != STIFFNESS_SOURCES[2] for p in priors.values())):
        return priors
    sags = arm_sags(rig, cal, list(priors))
    if sags is None:
        return priors
    log_sag = {a: np.log(v) for a, v in sags.items()}
    mean = float(np.mean(list(log_sag.values())))
    return {a: p._replace(sd=np.full_like(p.sd, SAG_SCALED_LOG_SD), arm_centre=mean - log_sag[a],
                          arm_sd=SAG_SCALED_ARM_LOG_SD, source=STIFFNESS_SOURCES[3])
            for a, p in priors.items()}


def stiffness_priors(rig: Rig, arms: Sequence[str], cal: Calibration
                     ) -> dict[str, StiffnessPrior]:
    """Each of ``arms``' :func:`stiffness_prior`, linked: :func:`sag_scaled_priors`."""
    return sag_scaled_priors(rig, cal, {a: stiffness_prior(rig, a, cal) for a in arms})


def _log_stiffness_prior(priors: Sequence[StiffnessPrior]) -> None:
    for i, p in enumerate(priors):
        z = numpyro.sample(f"log_stiffness_z_{i}",
                           dist.Normal(0.0, 1.0).expand([len(p.centre)]).to_event(1))
        whole = numpyro.sample(f"log_stiffness_arm_{i}", dist.Normal(0.0, 1.0))
        shared = jnp.where(jnp.asarray(p.shared), p.arm_centre + p.arm_term_sd() * whole, 0.0)
        numpyro.deterministic(f"log_stiffness_{i}",
                              jnp.asarray(p.centre) + jnp.asarray(p.sd) * z + shared)


def stiffness_draws(priors: Sequence[StiffnessPrior], key: jax.Array,
                    num_samples: int) -> list[jax.Array]:
    """Draws (S, n_a) of each arm's joint log stiffnesses from their prior (centre, sd)."""
    sites = Predictive(_log_stiffness_prior, num_samples=num_samples)(key, priors)
    return [jnp.broadcast_to(sites[f"log_stiffness_{i}"], (num_samples, len(p.centre)))
            for i, p in enumerate(priors)]

