"""Calibration: a robot's parameters from its measured markers, one path for every robot.

- :mod:`~bayesrob.calibrate.least_squares`: :func:`calibrate` fits the parameter groups asked
  for (any robot; the paper's planar arms are 2-joint chains) after the rank analysis of
  :mod:`~bayesrob.calibrate.identifiability`, with the one Gauss-Newton covariance.
- :mod:`~bayesrob.calibrate.arms`: the paper's eight parameters per planar arm, an instance of
  those groups (``calibrate`` on a planar rig without ``--params``), and their observed
  accuracy.
- :mod:`~bayesrob.calibrate.hill_climb`: the paper's own procedure, a selectable baseline.
- :mod:`~bayesrob.calibrate.bayes`: the NUTS posterior (numpyro) of the same parameters.
"""

from bayesrob.calibrate.arms import ArmCalibration, calibrate_arms
from bayesrob.calibrate.least_squares import Calibration, calibrate

__all__ = ["ArmCalibration", "Calibration", "calibrate", "calibrate_arms"]
