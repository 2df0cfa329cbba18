"""Localization of a query, stage by stage: its references (``retrieval``), where its refinement
starts (``priors``, with ``pose_averaging`` and the ``search`` of many starts), the coarse-to-fine
refinement (``refine``), the verification of its result (``verify``), a shard of queries with its
records (``shard``, ``results``)."""
