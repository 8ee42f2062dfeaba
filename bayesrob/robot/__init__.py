"""Kinematic models: one general chain/tree model for every robot (:mod:`.chain`), read from
URDF (:mod:`.urdf`) or DH tables (:mod:`.dh`), and the paper's planar two-link arm
(:mod:`.planar`), whose closed-form functions are a tested specialisation of the chain.

The planar functions are re-exported here because the grid predictions, samplers and
diagnosis work on them directly (``from bayesrob import kinematics as kin; kin.forward_u``).
"""

from bayesrob.robot.chain import (
    ALL_GROUPS,
    GROUPS,
    MASS_SOURCES,
    OPTIONAL_GROUPS,
    PLAY_SIDE_RAD,
    SAG_GROUPS,
    Chain,
    KinematicsError,
    ParamLayout,
    Robot,
    RobotStructure,
)
from bayesrob.robot.dh import dh_chain
from bayesrob.robot.planar import (
    PARAM_NAMES,
    Arm,
    ArmParams,
    choose_elbow,
    elbow_point,
    forward,
    forward_u,
    inverse,
    jacobian,
    log_abs_det_inverse_jacobian,
    planar_chain,
    servo,
    servo_inverse,
    wrap_angle,
)
from bayesrob.robot.urdf import urdf_chain, write_urdf

__all__ = [
    "ALL_GROUPS", "GROUPS", "MASS_SOURCES", "OPTIONAL_GROUPS", "PARAM_NAMES", "PLAY_SIDE_RAD",
    "SAG_GROUPS",
    "Arm", "ArmParams", "Chain", "KinematicsError", "ParamLayout", "Robot", "RobotStructure",
    "choose_elbow", "dh_chain", "elbow_point", "forward", "forward_u", "inverse",
    "jacobian", "log_abs_det_inverse_jacobian", "planar_chain", "servo", "servo_inverse",
    "urdf_chain", "wrap_angle", "write_urdf",
]
