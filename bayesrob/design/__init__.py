"""The configuration designer (``bayesrob design``): which calibrated modules, mounted where
and linked how, meet a required accuracy over a task region.

- :mod:`bayesrob.design.file`: the design file's format, read and checked (no numerical
  stack: a mistake in it is one line before anything is calibrated);
- :mod:`bayesrob.design.modules`: calibrated modules of any rig, mounted, aimed and drawn;
- :mod:`bayesrob.design.search`: candidates, the requirement, ranking, the Dask runner.

The figure is :func:`bayesrob.report.plots.design.design_figure`. Nothing is imported here, so that
reading a design file stays light.
"""
