"""Diagnosis: which physical effects does a calibrated model miss? Candidates are scored on
rows their fit did not see (:mod:`.groups`: calibration groups of any robot, on held-back
selection poses; :mod:`.refits`: a planar arm's angle corrections, by the leave-one-out
refits its 16-36 train points need) and named by the rules of :mod:`.rule`.
"""
