"""PixLoc: learned featuremetric camera localization, as a pure-torch library.

Sarlin et al., "Back to the Feature: Learning Robust Camera Localization from
Pixels to Pose", CVPR 2021. This package holds the method only: geometry,
interpolation, robust costs, the Levenberg-Marquardt solver, the networks and
the two-view refiner used for training. It has no file paths and no I/O
beyond loading checkpoints.
"""

__version__ = "0.1.0"

DEFAULT_MODEL = "pixloc-lite0"  # the one default of every command and config (``pixloc.nets.registry``)
