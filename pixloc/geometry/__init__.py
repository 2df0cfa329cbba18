"""Batched geometry: poses, cameras and lens distortion, with analytic Jacobians."""

from .camera import COLMAP_MODELS, Camera
from .pose import Pose, pose_error, relative_motion

__all__ = ["Camera", "COLMAP_MODELS", "Pose", "pose_error", "relative_motion"]
