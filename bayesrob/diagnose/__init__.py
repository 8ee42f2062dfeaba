"""Diagnosis: which physical effects does a calibrated model miss? Each candidate is added to
the model named so far, scored on rows its fit did not see, and named by one decision rule
for every robot (:mod:`bayesrob.diagnose.rule`).

Two searches feed the rule its evidence: :mod:`bayesrob.diagnose.groups` (any robot: the
candidates are calibration groups, scored on held-back selection poses) and
:mod:`bayesrob.diagnose.refits` (a planar rig's arms, each its own robot: the candidates are
the angle corrections of :mod:`bayesrob.robot.effects`, scored by leave-one-out refits, which its
16-36 train points per arm need). Report text is :mod:`bayesrob.report.tables`'s, figures
:mod:`bayesrob.report.plots.diagnosis`'s.
"""
