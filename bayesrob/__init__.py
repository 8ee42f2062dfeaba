"""bayesrob: probabilistic accuracy prediction for modular robot arms.

Importing the package switches JAX to 64-bit floats (``jax_enable_x64``): kernel
density sums over thousands of points and the inverse kinematics near the
workspace boundary lose too much precision in float32.
"""

import jax

jax.config.update("jax_enable_x64", True)

__version__ = "0.1.0"
