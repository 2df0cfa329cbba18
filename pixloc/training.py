"""End-to-end training of the network and the per-level damping through the unrolled LM.

As official PixLoc (pixlib/train.py, configs): Adam, the damping parameters at 100x the
learning rate, gradient clipping at 1.0, the two-view refiner's loss. The trainer holds
no file paths: callers save ``state_dict()`` where they want and resume with
``load_state_dict()`` to the identical state (model, optimiser, step, RNG).
"""

import math
from dataclasses import dataclass
from typing import Dict

import torch

from .geometry import Pose
from .refiner import PairBatch, TwoViewRefiner, masked_mean


@dataclass(frozen=True)
class TrainConfig:
    """lr: base learning rate (official MegaDepth 5e-6, CMU 1e-5). damping_lr_scale: official 100.
    clip_grad: max gradient norm (official 1.0). num_iters: LM iterations per level (official 15).
    freeze_batchnorm: keep BatchNorm statistics fixed (batches of one or two pairs are too small
    to estimate them). grad_checkpointing: recompute the network's activations in backward."""

    lr: float = 1e-5
    damping_lr_scale: float = 100.0
    clip_grad: float = 1.0
    num_iters: int = 15
    freeze_batchnorm: bool = True
    grad_checkpointing: bool = False


def reprojection_px(T: Pose, batch: PairBatch) -> torch.Tensor:
    """(B,) mean distance in pixels between the points projected into the query at ``T``
    and at the true pose (points valid at the truth and in the mask)."""
    cam = batch.camera_query
    p_gt, valid = cam.cam2image(batch.query_from_ref_gt.transform(batch.p3d_ref))
    p, _ = cam.cam2image(T.transform(batch.p3d_ref))
    if batch.mask_points is not None:
        valid = valid & batch.mask_points
    err = (p - p_gt).norm(dim=-1)
    return masked_mean(err, valid, -1)


class Trainer:
    def __init__(self, model: TwoViewRefiner, conf: TrainConfig = TrainConfig()):
        self.model, self.conf = model, conf
        damping = [p for n, p in model.named_parameters() if n.startswith("solvers.")]
        others = [p for n, p in model.named_parameters() if not n.startswith("solvers.")]
        self.optimizer = torch.optim.Adam([
            {"params": others, "lr": conf.lr},
            {"params": damping, "lr": conf.lr * conf.damping_lr_scale}])
        for s in model.solvers:
            s.num_iters = conf.num_iters
        if hasattr(model.extractor, "grad_checkpointing"):
            model.extractor.grad_checkpointing = conf.grad_checkpointing
        self.step_count = 0

    def train_mode(self) -> None:
        self.model.train()
        if self.conf.freeze_batchnorm:
            for m in self.model.modules():
                if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
                    m.eval()

    def step(self, batch: PairBatch) -> Dict[str, float]:
        """One optimisation step; returns the batch's metrics (losses in pixels)."""
        self.train_mode()
        pred = self.model(batch)
        losses = self.model.loss(pred, batch)
        loss = losses["total"].mean()
        metrics = {k: float(v.detach().mean()) for k, v in losses.items()}
        with torch.no_grad():
            metrics["error_px/init"] = float(reprojection_px(batch.query_from_ref_init, batch).mean())
            metrics["error_px"] = float(reprojection_px(pred["query_from_ref"][-1], batch).mean())
        self.optimizer.zero_grad()
        if torch.isfinite(loss) and loss.requires_grad:
            loss.backward()
            norm = torch.nn.utils.clip_grad_norm_(self.model.parameters(), self.conf.clip_grad)
            metrics["grad_norm"] = float(norm)
            if math.isfinite(metrics["grad_norm"]):
                self.optimizer.step()
        self.step_count += 1
        metrics["step"] = self.step_count
        return metrics

    def state_dict(self) -> Dict:
        return {"model": self.model.state_dict(), "optimizer": self.optimizer.state_dict(),
                "step": self.step_count, "rng": torch.get_rng_state()}

    def load_state_dict(self, state: Dict) -> None:
        self.model.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.step_count = int(state["step"])
        torch.set_rng_state(state["rng"])
