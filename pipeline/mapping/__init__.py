"""Map building: the map formats users bring (``readers``), the image pairs SfM and triangulation
match (``image_pairs``), points from depth (``depth``), and reference features at the points'
observations written to the store (``features``, ``build``)."""
