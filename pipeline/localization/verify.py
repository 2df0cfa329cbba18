"""Pose verification: is a refined pose supported by the evidence, and how confident are we?

PixLoc's LM always returns a pose; official PixLoc reports it as refined unless the solver
failed outright, so a refinement that slid into a wrong minimum (a night photo moving 38 deg,
a truncated image) is reported as a success. Here a refinement is accepted only when the
evidence at the finest level supports it (``pixloc.optim.evidence``):

- ``contrast``: how much sharper the featuremetric cost is at the refined pose than at the
  poses that shift the image by 3 pixels around it. A correct alignment sits in a narrow
  valley (the features match there, not a few pixels off); a wrong minimum of misaligned
  features is flat. Unlike the inlier fraction, it stays informative when day and night
  features differ too much for residuals to be small.
- ``move``: how far the pose moved from the prior, relative to the median depth of the
  points: a jump of many scene depths or tens of degrees is not a refinement.

- ``sigma``: how far the pose could slide along its least-determined direction, from the Hessian of
  the cost at the refined pose (``pixloc.optim.alignment_uncertainty``), in units of 1 % of the
  median point depth and 1 degree. Around a
  texture-poor object the cost can be sharp for image shifts and still leave the camera free to
  move along the ring of views while turning to keep the object in view: it stops near where it
  started, often a neighbouring reference's pose.
- ``valid``: the fraction of the map points that project into the image at the refined pose;
  a pose turned away from the map sees few of them.
- ``last turn``: the rotation of the finest level; a correct refinement is settled by then.

The confidence is ``c^2 / (c^2 + s^2)`` for the contrast ``c`` and the scale ``s``
(``contrast_scale``), 1/2 where the contrast equals the scale. Below a strong contrast
(``strong_contrast``), a refinement with fewer points in view than ``min_valid`` or a finest
level that turned more than ``max_last_turn`` has its confidence capped below 1/2, at
``valid / min_valid / 2`` and ``max_last_turn / last turn / 2``. The defaults were chosen by measurement on
the shared scenes:
see docs/verification.md (``pixloc benchmark verification``).
"""

import math
from dataclasses import asdict, dataclass
from typing import Dict, Optional, Tuple


CHI2_6DOF_99 = 16.8  # the 0.99 quantile of a chi-square of 6 degrees of freedom (a pose's)
NOT_PINNED = "rejected: the pose is not pinned down: "  # the reason of the ``max_sigma`` gate


@dataclass(frozen=True)
class VerificationConfig:
    """When a refined pose is reported as a success.

    enabled: False reports every converged refinement as a success (official PixLoc).
    min_confidence: refinements whose confidence is below this are rejected (the prior is kept).
    contrast_scale: the cost contrast (at 3 px) at which the confidence is 1/2.
    strong_contrast: a contrast at or above which the other evidence is not needed.
    min_valid: fraction of points inside the image below which the confidence is scaled down.
    max_last_turn: rotation (degrees) of the finest level above which the confidence is scaled down.
    max_move_R: rotation (degrees) from the prior above which a refinement is rejected.
    max_move_t: camera motion from the prior, in median point depths, above which it is rejected.
    max_sigma: the standard deviation of the pose along its least-determined direction (units of 1 % of
        the median point depth and 1 degree) above which a refinement is rejected as not pinned
        down (0: no limit).
    rivals: other retrieved references' poses refined to check a pose refined from the map's own
        poses (``pipeline.localization.search.check_rivals``; 0: no check); one verified at another pose
        rejects it as ambiguous.
    agree_t, agree_R: two poses agree when their camera centres lie within ``agree_t`` x the median
        point depth and their rotations within ``agree_R`` degrees.
    join: a rival start stops at the end of a coarser level where it lies within ``join`` x
        (``agree_t``, ``agree_R``) of one of its query's own starts: it has joined that start's basin,
        and agrees (0: every rival runs through every level).
    sharper_by: a rival start verified at another pose leaves the result verified where the result's
        cost is at least this many times sharper (its 3 px contrast) than the rival's: the two poses are
        not equally supported, and the rival's is the weaker (0: any rival verified elsewhere rejects it).
        The search's other starts reject it whatever their sharpness.
    max_keypoint_chi2: where a start is supported by 2D-3D matches (a PnP pose's inliers), the rise of their
        chi-square (squared reprojection errors over their residual scale) from the start to the refined pose
        above which the refined pose has left what they support: the start's pose is reported instead
        (e.g. ``CHI2_6DOF_99``; 0, the default: never). Off by default: with the keypoints' term in the
        refinement's cost it changed no recall on the accuracy benchmark, and on the demo it kept a PnP pose
        0.55 m off (21 inliers, an occluded query) that the refinement had left (docs/benchmarks.md).
    """

    enabled: bool = True
    min_confidence: float = 0.5
    contrast_scale: float = 0.035
    strong_contrast: float = 0.1
    min_valid: float = 0.5
    max_last_turn: float = 3.0
    max_move_R: float = 45.0
    max_move_t: float = 2.0
    max_sigma: float = 0.06
    rivals: int = 1
    agree_t: float = 0.10
    agree_R: float = 5.0
    join: float = 0.5
    sharper_by: float = 2.0
    max_keypoint_chi2: float = 0.0

    def __post_init__(self):
        if not 0 <= self.min_confidence <= 1 or not 0 <= self.min_valid <= 1:
            raise ValueError(f"verification: min_confidence and min_valid must lie in [0, 1] (fractions), not "
                             f"{self.min_confidence} and {self.min_valid}.")
        if min(self.max_sigma, self.max_last_turn, self.max_move_R, self.max_move_t, self.max_keypoint_chi2) < 0:
            raise ValueError(f"verification: max_sigma, max_last_turn, max_move_R, max_move_t and max_keypoint_chi2 "
                             f"must not be negative, not {self.max_sigma}, {self.max_last_turn}, {self.max_move_R}, "
                             f"{self.max_move_t} and {self.max_keypoint_chi2}.")
        if self.rivals < 0 or self.agree_t <= 0 or self.agree_R <= 0:
            raise ValueError("verification: rivals must not be negative, agree_t and agree_R must be positive.")
        if not 0 <= self.join <= 1:
            raise ValueError(f"verification: join must lie in [0, 1], not {self.join}.")
        if self.sharper_by != 0 and self.sharper_by < 1:
            raise ValueError(f"verification: sharper_by must be 0 (off) or at least 1, not {self.sharper_by}.")

    def to_dict(self) -> Dict:
        return asdict(self)


def confidence(evidence: Dict[str, float], conf: VerificationConfig = VerificationConfig()) -> float:
    """A score in [0, 1] from the sharpness of the cost at the refined pose, the fraction of
    points in view and the settling of the finest level (0 without evidence)."""
    c = float(evidence.get("contrast_3px", 0.0))
    if not math.isfinite(c) or c <= 0:
        return 0.0
    score = c * c / (c * c + conf.contrast_scale ** 2)
    if c >= conf.strong_contrast:
        return score
    valid = float(evidence.get("valid", 1.0))
    turn = float(evidence.get("last_R", 0.0))
    # a gate that fails caps the score below 1/2, in proportion to how far it falls short
    if valid < conf.min_valid:
        score = min(score, 0.5 * max(valid, 0.0) / conf.min_valid)
    if turn > conf.max_last_turn:
        score = min(score, 0.5 * conf.max_last_turn / turn)
    return float(score)


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
        contrast = 100 * evidence.get("contrast_3px", 0.0)
        lower = f"{contrast:.1f}% lower" if contrast >= 0.05 else "no lower"  # never '-0.0% lower'
        return c, (f"rejected: confidence {c:.2f} < {conf.min_confidence:g} (the cost is "
                   f"{lower} at the pose than 3 px around it, "
                   f"{100 * evidence.get('valid', 0.0):.0f}% of the points in view, finest level turned "
                   f"{evidence.get('last_R', 0.0):.1f} deg)")
    sigma = evidence.get("sigma", 0.0)
    if conf.max_sigma > 0 and not sigma <= conf.max_sigma:  # a NaN sigma is not pinned down either
        return c, (f"{NOT_PINNED}sigma {sigma:.3f} > {conf.max_sigma:g} along its "
                   f"least-determined direction (alone: {evidence.get('sigma_R', float('nan')):.3f} deg, "
                   f"{100 * evidence.get('sigma_t', float('nan')):.3f} % of the depth)")
    return c, None


def keep_start(evidence: Dict[str, float], conf: VerificationConfig = VerificationConfig()) -> Optional[str]:
    """For a verified refinement of a start supported by 2D-3D matches: the note saying that the start's
    pose is reported instead, where the refinement raised their chi-square by more than
    ``max_keypoint_chi2`` (it left what they support; the features verified a pose near it); else None."""
    rise = evidence.get("keypoint_chi2")
    if rise is None or conf.max_keypoint_chi2 <= 0 or not conf.enabled or not rise > conf.max_keypoint_chi2:
        return None
    return (f"the start's pose kept: the refinement raised its {evidence.get('keypoints', 0):.0f} keypoints' "
            f"chi-square by {rise:.1f} (> {conf.max_keypoint_chi2:g})")
