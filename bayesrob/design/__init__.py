"""The configuration designer (``bayesrob design``): :mod:`.file` (the design file, read with
no numerical stack), :mod:`.modules` (calibrated modules, mounted, aimed and drawn) and
:mod:`.search` (candidates, ranking, the Dask runner). Nothing is imported here, so reading a
design file stays light.
"""
