"""Pose verification: is a refined pose supported by the evidence, and how confident are we?

PixLoc's LM always returns a pose; official PixLoc reports it as refined unless the solver
failed outright, so a refinement that slid into a wrong minimum (a night photo moving 38 deg,
a truncated image) is reported as a success. Here a refinement is accepted only when the
evidence at the finest level supports it (``pixloc.optim.evidence``):

- ``inliers``: the fraction of the map points that, at the refined pose, are inliers of the
  robust loss. A correct pose explains many points; a wrong minimum few.
- ``gain``: inliers at the refined pose less inliers at the prior, on the same points and
  features. A refinement that explains no more than its prior has not found anything.
- ``move``: how far the pose moved from the prior, relative to the median depth of the
  points: a jump of many scene depths or tens of degrees is not a refinement.

The thresholds and the confidence were chosen by measurement on the shared scenes:
see docs/verification.md (``pixloc benchmark verification``).
"""

import math
from dataclasses import asdict, dataclass
from typing import Dict, Optional, Tuple


@dataclass(frozen=True)
class VerificationConfig:
    """When a refined pose is reported as a success.

    enabled: False reports every converged refinement as a success (official PixLoc).
    min_confidence: refinements whose confidence is below this are rejected (the prior is kept).
    inlier_scale: inlier fraction at which the inlier term of the confidence reaches 1/2.
    max_move_R: rotation (degrees) from the prior above which a refinement is rejected.
    max_move_t: camera motion from the prior, in median point depths, above which it is rejected.
    """

    enabled: bool = True
    min_confidence: float = 0.5
    inlier_scale: float = 0.1
    max_move_R: float = 45.0
    max_move_t: float = 2.0

    def to_dict(self) -> Dict:
        return asdict(self)


def confidence(evidence: Dict[str, float], conf: VerificationConfig = VerificationConfig()) -> float:
    """A score in [0, 1] from the evidence: high when many points are inliers at the refined
    pose and more than at the prior."""
    inliers = float(evidence.get("weighted_inliers", 0.0))
    gain = inliers - float(evidence.get("weighted_inliers_prior", 0.0))
    if not (math.isfinite(inliers) and math.isfinite(gain)):
        return 0.0
    score = inliers / (inliers + conf.inlier_scale) if inliers > 0 else 0.0
    return float(min(max(score, 0.0), 1.0))


def verify(evidence: Dict[str, float], conf: VerificationConfig = VerificationConfig()
           ) -> Tuple[float, Optional[str]]:
    """(confidence, None) for an accepted refinement, (confidence, "rejected: why") otherwise."""
    if not evidence:
        return 0.0, "rejected: no evidence recorded for the refined pose"
    c = confidence(evidence, conf)
    if not conf.enabled:
        return c, None
    if evidence.get("move_R", 0.0) > conf.max_move_R:
        return c, f"rejected: the pose turned {evidence['move_R']:.1f} deg from its prior (> {conf.max_move_R:g})"
    if evidence.get("move_t", 0.0) > conf.max_move_t:
        return c, (f"rejected: the camera moved {evidence['move_t']:.2f} scene depths from its prior "
                   f"(> {conf.max_move_t:g})")
    if c < conf.min_confidence:
        return c, (f"rejected: confidence {c:.2f} < {conf.min_confidence:g} "
                   f"({100 * evidence.get('weighted_inliers', 0):.0f}% inliers at the refined pose, "
                   f"{100 * evidence.get('weighted_inliers_prior', 0):.0f}% at the prior)")
    return c, None
