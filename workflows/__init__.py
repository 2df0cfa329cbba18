"""Dask graphs wiring the pipeline stages, dataset presets, the ``pixloc``
command line, reports and benchmarks."""
