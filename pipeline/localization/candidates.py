"""What a query's refinement starts from and ends with: its starts (``Candidate``), what the
starts of one query share (``QueryCache``), and its outcome (``QueryResult``)."""

from dataclasses import dataclass, field
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np

from pipeline.queries import QueryRecord


@dataclass
class QueryResult:
    """The outcome of one query; poses are cam_from_world (3, 4)."""

    name: str
    success: bool
    prior: Optional[np.ndarray]
    refined: Optional[np.ndarray]
    references: List[str] = field(default_factory=list)
    num_points: int = 0
    cost: float = float("nan")
    iterations: int = 0
    reason: str = ""
    timings: Dict[str, float] = field(default_factory=dict)
    per_level: List[Dict] = field(default_factory=list)
    confidence: float = 0.0
    evidence: Dict[str, float] = field(default_factory=dict)
    notes: List[str] = field(default_factory=list)
    filters: Dict[str, int] = field(default_factory=dict)  # what the point filters left out
    body: Dict = field(default_factory=dict)  # the rig frame it was localized with (``pipeline.localization.rigs``)

    @property
    def pose(self) -> Optional[np.ndarray]:
        """The pose to report: refined if successful (verified), else the prior."""
        return self.refined if self.success else self.prior


@dataclass(eq=False)
class QueryCache:
    """What the starts of one query share (``Candidate.cache``): its network pass per image scale
    index (``passes``: the prediction and the image's scale factors, ``Localizer.predict``) and its
    references' features per (image scale, levels, observations) (``references``)."""

    passes: Dict[int, Tuple[Dict, Tuple[float, float]]] = field(default_factory=dict)
    references: Dict[Tuple, Tuple] = field(default_factory=dict)

    def network(self, k: int, run: Callable[[], Tuple[Dict, Tuple[float, float]]]) -> Tuple[Dict, Tuple[float, float]]:
        """The query's network pass at image scale index ``k`` (``run()`` when first asked)."""
        if k not in self.passes:
            self.passes[k] = run()
        return self.passes[k]


@dataclass(frozen=True, eq=False)
class Keypoints:
    """A start's 2D-3D evidence (a PnP pose's inliers): keypoints ``xy`` (M, 2) in COLMAP pixels of the
    query image, their map points ``xyz`` (M, 3), their reprojection error's scale at the start (``scale``,
    pixels: ``pixloc.optim.keypoints.residual_scale``), and the ``weight`` of their reprojection term in the
    refinement's cost (0: the features alone; verification still reads how far the refined pose left them)."""

    xy: np.ndarray
    xyz: np.ndarray
    scale: float
    weight: float = 1.0


@dataclass(frozen=True, eq=False)
class BodyRef:
    """The body a start belongs to (a rig at one instant, a chunk of frames): its ``key`` (the same for the
    starts refined as one body) and this image's camera in the body's frame, ``cam_from_body`` (3 x 4).
    The starts of one body must start from one body pose: prior = cam_from_body @ body_from_world."""

    key: str
    cam_from_body: np.ndarray


@dataclass
class Candidate:
    """One start of a query's refinement: the references ``dbs`` (map image indices), the start
    pose ``prior`` (cam_from_world, 3 x 4) and where it came from (``origin``, e.g. "top-1
    reference"). The starts of one query share its image ``rgb`` and ``cache`` (``QueryCache``: its
    network passes and references' features); ``selected``: (point, reference) pairs that
    restrict the observations (hloc's PnP inliers); ``rival``: a rival start of verification
    (``pipeline.localization.search.rival_starts``), stopped where it joins one of its query's own
    starts (those of the same query; ``Localizer.localize_batch``); ``levels``: the levels this
    start is refined on, of the localizer's (refinement mode for a pose from another method: the two
    finest); it always ends at the localizer's finest level, whose evidence verification reads;
    ``keypoints``: the 2D-3D matches that support the start (``Keypoints``), whose reprojection error the
    refinement adds to its cost and verification reads; ``body``: the body it is refined with (``BodyRef``:
the starts of one body are solved as one pose, ``pixloc.optim.bodies``)."""

    query: QueryRecord
    dbs: List[int]
    prior: np.ndarray
    rgb: Optional[np.ndarray] = None
    cache: Optional[QueryCache] = None
    selected: Optional[np.ndarray] = None
    origin: str = "prior"
    rival: bool = False
    levels: Optional[Sequence[int]] = None
    keypoints: Optional[Keypoints] = None
    body: Optional[BodyRef] = None
