"""Featuremetric Levenberg-Marquardt: cost, damping and the solver loop."""

from .cost import FeaturemetricProblem, Linearization, build_system, linearize
from .damping import ConstantDamping, LearnedDamping
from .solver import LevenbergMarquardt, LMResult, StoppingRule, solve_damped

__all__ = ["ConstantDamping", "FeaturemetricProblem", "LearnedDamping", "LevenbergMarquardt",
           "Linearization", "LMResult", "StoppingRule", "build_system", "linearize", "solve_damped"]
