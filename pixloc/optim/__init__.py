"""Featuremetric Levenberg-Marquardt: cost, damping and the solver loop."""

from .bodies import Bodies
from .cost import FeaturemetricProblem, Linearization, build_system, linearize
from .damping import ConstantDamping, LearnedDamping
from .evidence import alignment_contrast, alignment_depth_contrast, alignment_evidence, alignment_uncertainty
from .solver import LevenbergMarquardt, LMResult, StoppingRule, solve_damped

__all__ = ["Bodies", "ConstantDamping", "FeaturemetricProblem", "LearnedDamping", "LevenbergMarquardt",
           "Linearization", "LMResult", "StoppingRule", "alignment_contrast", "alignment_depth_contrast",
           "alignment_evidence", "alignment_uncertainty", "build_system", "linearize", "solve_damped"]
