"""Kinematic models: one chain/tree model for every robot (:mod:`.chain`), read from URDF
(:mod:`.urdf`) or DH tables (:mod:`.dh`), and the paper's planar arm (:mod:`.planar`), a
tested specialisation whose functions the grid, samplers and diagnosis use directly.
"""

from bayesrob.robot.chain import (
    ALL_GROUPS,
    APPROACH,
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
    on_row_buckets,
    pad_rows,
    row_bucket,
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
    "ALL_GROUPS", "APPROACH", "GROUPS", "MASS_SOURCES", "OPTIONAL_GROUPS", "PARAM_NAMES",
    "PLAY_SIDE_RAD", "SAG_GROUPS",
    "Arm", "ArmParams", "Chain", "KinematicsError", "ParamLayout", "Robot", "RobotStructure",
    "choose_elbow", "dh_chain", "elbow_point", "forward", "forward_u", "inverse",
    "jacobian", "log_abs_det_inverse_jacobian", "on_row_buckets", "pad_rows", "planar_chain",
    "row_bucket", "servo", "servo_inverse",
    "urdf_chain", "wrap_angle", "write_urdf",
]
