"""Prediction: where an assembly's end point lands, as draws through the calibrated robot.

- :mod:`.draws`: the modules calibrated and their joint-error populations fitted, and draws of
  one arm's end point or of linked arms' shared point (any number of arms, 2-D or 3-D).
- :mod:`.fusion`: how linked arms share their point (``equilibrium``: the balance of their
  stiffnesses; ``product``: the paper's product of likelihoods).
- :mod:`.stiffness`: the joint stiffnesses the balance draws.
- :mod:`.aiming`: the commands that aim a calibrated arm at a target.
- :mod:`.regions`: the draws' KDE and its highest-density regions.
- :mod:`.grid`: the paper's exact 2-D grid, which the reproduction reports and checks the
  draws against.
- :mod:`.assembly`: ``bayesrob predict``.
"""
