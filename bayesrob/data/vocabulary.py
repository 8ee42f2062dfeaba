"""The names the command line and the rig, design and model files accept: physical effects,
parameter groups, where links' masses come from, fusion rules.

They live here, apart from the numerical modules that act on them, so that checking an
argument needs no numerical library: ``bayesrob --help`` and every argument error answer at
once, before JAX, SciPy or arviz are imported. The modules that act on these names import them
from here (one definition each).
"""

from __future__ import annotations

# Physical effects of the planar simulator and of the planar diagnosis (names are a contract:
# rig truth files, ``simulate --effects``, ``diagnose --effects``).
EFFECTS = ("gravity_sag", "backlash", "servo_nonlinearity")

# Chain effects the diagnosis names -> the parameter group that fits each.
CHAIN_EFFECTS = {"joint_compliance": "compliance", "lateral_compliance": "lateral",
                 "encoder_error": "encoder", "backlash": "backlash",
                 "servo_nonlinearity": "servo_curve"}

# Parameter groups of a chain calibration: always available, then fitted only when asked for
# (joints that give way under gravity, bending across the joints' axes, eccentric encoders,
# play that gravity takes up, a curved command map).
GROUPS = ("frames", "offsets", "geometric", "servo")
OPTIONAL_GROUPS = ("compliance", "lateral", "encoder", "backlash", "servo_curve")
ALL_GROUPS = GROUPS + OPTIONAL_GROUPS

# Where a compliance fit takes the links' masses from: fitted with the compliances, or held at
# the description's <inertial> values.
MASS_SOURCES = ("fitted", "description")

# How linked arms share their end point.
EQUILIBRIUM = "equilibrium"  # the stiffnesses' balance (bayesrob.predict.fusion)
FUSIONS = ("product", EQUILIBRIUM)
DEFAULT_FUSION = EQUILIBRIUM
