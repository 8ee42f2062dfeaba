"""Prediction: where an assembly's end point lands, as draws through the calibrated robot
(:mod:`.draws`, fused by :mod:`.fusion` with :mod:`.stiffness`, aimed by :mod:`.aiming`, their
regions in :mod:`.regions`; ``bayesrob predict`` in :mod:`.assembly`), and the paper's exact 2-D
grid (:mod:`.grid`) that checks them."""
