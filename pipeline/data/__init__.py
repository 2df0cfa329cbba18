"""Scenes the project generates (the demo's courtyard ``synthetic``, the ``city`` at scale) and
training pairs (``training_data``)."""
