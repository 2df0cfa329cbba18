"""The training-time two-view refiner of PixLoc and its loss.

Features of a reference and a query image, then LM per level from coarse to
fine on the pose query_from_ref, starting each level from the detached pose
of the previous one (Sarlin et al. 2021, Sec. 3.3; official
``TwoViewRefiner``).
"""

import hashlib
from dataclasses import dataclass
from typing import TYPE_CHECKING, Dict, List, Optional, Sequence

import torch
from torch import Tensor, nn
from torch.nn.functional import normalize

from .geometry import Camera, Pose
from .losses import scaled_barron
from .optim import FeaturemetricProblem, LevenbergMarquardt

if TYPE_CHECKING:  # importing pixloc.nets here would be circular (nets.registry builds refiners)
    from .nets.unet import UNet


@dataclass
class PairBatch:
    """B image pairs. Images (B, 3, H, W) RGB in [0, 1]; cameras (B,) at image resolution.

    p3d_ref: (B, N, 3) points in the reference camera frame; mask_points:
    (B, N) valid points (padding); query_from_ref_init / _gt: (B,) poses.
    """

    image_ref: Tensor
    image_query: Tensor
    camera_ref: Camera
    camera_query: Camera
    p3d_ref: Tensor
    query_from_ref_init: Pose
    query_from_ref_gt: Pose
    mask_points: Tensor | None = None

    def to(self, device) -> "PairBatch":
        return PairBatch(*(None if v is None else v.to(device) for v in (
            self.image_ref, self.image_query, self.camera_ref, self.camera_query, self.p3d_ref,
            self.query_from_ref_init, self.query_from_ref_gt, self.mask_points)))

    @staticmethod
    def stack(batches: Sequence["PairBatch"]) -> "PairBatch":
        """One batch of several, all with the same image sizes and number of points."""
        cat = lambda k: torch.cat([getattr(b, k) for b in batches])
        # the wrappers' own concatenation: a camera keeps its distortion model (a FISHEYE batch
        # rebuilt from its 10 values alone would be read as OPENCV)
        wrapped = lambda k: type(getattr(batches[0], k)).cat([getattr(b, k) for b in batches])
        return PairBatch(cat("image_ref"), cat("image_query"), wrapped("camera_ref"), wrapped("camera_query"),
                         cat("p3d_ref"), wrapped("query_from_ref_init"), wrapped("query_from_ref_gt"),
                         cat("mask_points") if batches[0].mask_points is not None else None)

    def shape_key(self) -> tuple:
        return tuple(self.image_ref.shape[1:]) + tuple(self.image_query.shape[1:]) + tuple(self.p3d_ref.shape[1:])


def masked_mean(x: Tensor, mask: Tensor, dim: int) -> Tensor:
    """Mean of ``x`` where ``mask`` holds; a masked-out value never reaches it, not even an inf or
    NaN (official PixLoc multiplies by the mask: a point far outside a RADIAL camera's valid radius
    made a whole pair's loss NaN)."""
    return torch.where(mask, x, torch.zeros_like(x)).sum(dim) / mask.to(x.dtype).sum(dim).clamp(min=1)


class TwoViewRefiner(nn.Module):
    """Network + one LM solver per level (index 0 = finest, as the network's levels).

    normalize_features: L2-normalise the dense query maps and the sampled
    reference features (official default True). success_thresh: a level
    counts in the loss only if the previous one ended below this many pixels
    times its stride. clamp_error: pixels.
    """

    def __init__(self, extractor: "UNet", solvers: Sequence[LevenbergMarquardt],
                 normalize_features: bool = True, success_thresh: float = 3.0, clamp_error: float = 50.0):
        super().__init__()
        if len(solvers) != len(extractor.strides):
            raise ValueError(f"Need one solver per level ({len(extractor.strides)}), got {len(solvers)}.")
        self.extractor = extractor
        self.solvers = nn.ModuleList(solvers)
        self.normalize_features = normalize_features
        self.success_thresh = success_thresh
        self.clamp_error = clamp_error
        self.autocast_dtype = None  # e.g. torch.bfloat16: the network (not the LM) in mixed precision

    def feature_digest(self) -> str:
        """What identifies the feature network's weights (a map store records it of its features):
        SHA-256 (first 16 hex digits) of its parameters and buffers, by name."""
        h = hashlib.sha256()
        for name, tensor in sorted(self.extractor.state_dict().items()):
            h.update(name.encode())
            h.update(tensor.detach().cpu().contiguous().numpy().tobytes())
        return h.hexdigest()[:16]

    def extract(self, image: Tensor) -> Dict[str, List[Tensor]]:
        if self.autocast_dtype is None:
            return self.extractor(image)
        with torch.autocast(image.device.type, dtype=self.autocast_dtype):
            pred = self.extractor(image)
        return {k: [x.float() for x in v] if isinstance(v, list) else v for k, v in pred.items()}

    def forward(self, batch: PairBatch, num_iters: Optional[int] = None) -> Dict[str, List]:
        """Returns ``query_from_ref`` (poses after each level, coarse to fine) and ``failed``;
        ``num_iters``: the LM iterations per level (default: each solver's own budget)."""
        pred_ref = self.extract(batch.image_ref)
        pred_q = self.extract(batch.image_query)
        T = batch.query_from_ref_init
        poses, failed, inits = [], [], []
        for level in reversed(range(len(self.extractor.strides))):
            solver = self.solvers[level]
            s = 1 / self.extractor.strides[level]
            cam_ref, cam_q = batch.camera_ref.scale(s), batch.camera_query.scale(s)
            p2d_ref, visible = cam_ref.cam2image(batch.p3d_ref)
            F_ref, mask, _ = solver.interpolator(pred_ref["features"][level], p2d_ref)
            mask = mask & visible
            if batch.mask_points is not None:
                mask = mask & batch.mask_points
            F_q = pred_q["features"][level]
            W_ref = W_q = None
            if self.extractor.compute_confidence:
                W_ref = solver.interpolator(pred_ref["confidences"][level], p2d_ref)[0][..., 0]
                W_q = pred_q["confidences"][level][:, 0]
            if self.normalize_features:
                F_ref, F_q = normalize(F_ref, dim=-1), normalize(F_q, dim=1)
            problem = FeaturemetricProblem(batch.p3d_ref, F_ref, F_q, cam_q, W_ref, W_q, mask)
            result = solver(problem, T, num_iters=num_iters)
            inits.append(T)
            poses.append(result.pose)
            failed.append(result.failed)
            T = result.pose.detach()
        return {"query_from_ref_init": inits, "query_from_ref": poses, "failed": failed}

    def loss(self, pred: Dict[str, List], batch: PairBatch) -> Dict[str, Tensor]:
        """Official loss: robust reprojection error of the 3D points in the query, per level.

        Barron (alpha 1, scale 2) / 4 on squared pixel errors, clamped, a level
        counted only if the previous one succeeded; averaged over levels.
        Errors are in pixels of the query image at full resolution.
        """
        cam_q = batch.camera_query

        def project(T: Pose):
            return cam_q.cam2image(T.transform(batch.p3d_ref))

        p2d_gt, mask = project(batch.query_from_ref_gt)
        mask = mask & project(batch.query_from_ref_init)[1]
        if batch.mask_points is not None:
            mask = mask & batch.mask_points
        too_few = mask.sum(-1) < 10

        def reprojection_error(T: Pose) -> Tensor:
            err = ((p2d_gt - project(T)[0]) ** 2).sum(-1)
            return masked_mean(scaled_barron(1.0, 2.0)(err)[0] / 4, mask, -1)

        num_levels = len(self.extractor.strides)
        losses: Dict[str, Tensor] = {}
        total, success = 0.0, None
        for i, T in enumerate(pred["query_from_ref"]):
            err = reprojection_error(T).clamp(max=self.clamp_error)
            loss = err / num_levels
            if i > 0:
                loss = loss * success.to(loss.dtype)
            success = err < self.success_thresh * self.extractor.strides[-1 - i]
            losses[f"reprojection_error/{i}"] = err
            total = total + loss
        losses["reprojection_error"] = err
        losses["total"] = total * (~too_few).to(err.dtype)
        losses["reprojection_error/init"] = reprojection_error(pred["query_from_ref_init"][0])
        return losses
