"""The validation suite: the project's statistical studies, each on report seeds with targets
fixed in a file committed before those seeds first ran (``targets/<study>.toml``).

``bayesrob validate [NAME ...] [--quick] [--out DIR]`` runs them and writes
``validation.json`` and ``validation.md``; the committed ``validation/validation.json`` is the
full run the README's and docs' result tables are generated from
(:mod:`bayesrob.validation.tables`). The tests check the code is right; the studies measure
how well its predictions hold on data nothing was tuned on. See :mod:`.study` for the
targets file and :mod:`.suite` for the report.
"""
