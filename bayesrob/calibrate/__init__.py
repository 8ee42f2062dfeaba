"""Calibration: a robot's parameters from its measured markers, one path for every robot:
least squares over parameter groups after a rank analysis (:mod:`.least_squares`,
:mod:`.identifiability`), the planar arms' eight as one instance (:mod:`.arms`), the paper's
hill climb as a baseline (:mod:`.hill_climb`), and the NUTS posterior (:mod:`.bayes`)."""

from bayesrob.calibrate.arms import ArmCalibration, calibrate_arms
from bayesrob.calibrate.least_squares import Calibration, calibrate

__all__ = ["ArmCalibration", "Calibration", "calibrate", "calibrate_arms"]
