"""Choosing the poses to measure (``bayesrob plan``): a pool of candidate poses
(:mod:`~bayesrob.plan.pool`), what each is worth to the calibration
(:mod:`~bayesrob.plan.criteria`), greedy selection (:mod:`~bayesrob.plan.greedy`) and the
command's flow (:mod:`~bayesrob.plan.planner`)."""

from bayesrob.plan.criteria import CRITERIA
from bayesrob.plan.planner import Plan, plan_poses, write_poses
from bayesrob.plan.pool import Pool, load_plan_rig

__all__ = ["CRITERIA", "Plan", "Pool", "load_plan_rig", "plan_poses", "write_poses"]
