"""Stages and I/O adapters of the localization pipeline (readers, map store,
retrieval, localization of one shard, evaluation). Plain functions over typed
records; no Dask here: workflows/ builds the graphs."""
