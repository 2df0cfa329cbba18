"""End-to-end training of the network and the per-level damping through the unrolled LM.

As official PixLoc (pixlib/train.py, configs): Adam, the damping parameters at 100x the
learning rate, gradient clipping at 1.0, the two-view refiner's loss. The trainer holds
no file paths: callers save ``state_dict()`` where they want and resume with
``load_state_dict()`` to the identical state (model, optimiser, step, RNG).
"""

import contextlib
import math
from dataclasses import dataclass
from typing import Dict, List, Sequence, Union

import torch

from .geometry import Pose
from .nets.unet import UNet
from .refiner import PairBatch, TwoViewRefiner, masked_mean


@dataclass(frozen=True)
class TrainConfig:
    """lr: base learning rate (official MegaDepth 5e-6, CMU 1e-5). damping_lr_scale: official 100;
    0 keeps the damping as it is (a fine-tune of the features alone).
    clip_grad: max gradient norm (official 1.0). num_iters: LM iterations per level (official 15).
    freeze_batchnorm: keep BatchNorm statistics fixed (batches of one or two pairs are too small
    to estimate them). grad_checkpointing: recompute the network's activations in backward.
    lr_schedule: ``constant``, or ``cosine`` from ``lr`` at step ``decay_start`` down to
    ``lr * lr_min_factor`` at ``total_steps`` (a function of the step alone, so a resumed
    run follows the same schedule). device: where the model trains (``cuda`` on a GPU).
    amp: the network in bfloat16 autocast on a GPU (the LM and the loss stay in float32).
    ema: decay of an exponential moving average of the weights (0: none), the model that is
    validated and saved (``Trainer.averaged``). It starts at the initial weights, so a fine-tune's
    average stays near the model it starts from until the steps have moved it (about 1 / (1 - ema)
    steps).
    freeze_encoder_steps: the encoder's weights stay fixed for this many steps (no gradient is
    computed for them: those steps are cheaper), the decoder, confidences and damping train; after
    them the encoder trains at ``lr * encoder_lr_scale``."""

    lr: float = 1e-5
    damping_lr_scale: float = 100.0
    clip_grad: float = 1.0
    num_iters: int = 15
    freeze_batchnorm: bool = True
    grad_checkpointing: bool = False
    lr_schedule: str = "constant"
    total_steps: int = 0
    decay_start: int = 0
    lr_min_factor: float = 0.1
    device: str = "cpu"
    amp: bool = False
    ema: float = 0.0
    freeze_encoder_steps: int = 0
    encoder_lr_scale: float = 1.0

    def lr_factor(self, step: int) -> float:
        """The learning rate of ``step`` (counted from 0) as a fraction of ``lr``."""
        if self.lr_schedule == "constant":
            return 1.0
        if self.lr_schedule != "cosine":
            raise ValueError(f"Unknown lr_schedule {self.lr_schedule!r}: constant or cosine.")
        span = max(1, self.total_steps - self.decay_start)
        progress = min(1.0, max(0.0, (step - self.decay_start) / span))
        return self.lr_min_factor + (1 - self.lr_min_factor) * 0.5 * (1 + math.cos(math.pi * progress))


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
    def __init__(self, model: TwoViewRefiner, conf: TrainConfig = TrainConfig(), channels_last: bool = True):
        """channels_last: the network's activations in channels-last layout (the same gradients to
        rounding; 1.1x the steps per CPU hour: docs/model_card.md, "Steps per CPU hour")."""
        self.model, self.conf = model.to(conf.device), conf
        if channels_last and isinstance(model.extractor, UNet):
            model.extractor.channels_last()
        self.device = torch.device(conf.device)
        if conf.amp and self.device.type == "cuda":
            model.autocast_dtype = torch.bfloat16
        named = list(model.named_parameters())
        damping = [p for n, p in named if n.startswith("solvers.")]
        # the encoder has a group of its own only when the config treats it apart (older
        # checkpoints hold two groups and resume as they were)
        self.encoder = [p for n, p in named if n.startswith("extractor.encoder.")] if (
            conf.freeze_encoder_steps or conf.encoder_lr_scale != 1.0) else []
        apart = {id(p) for p in damping + self.encoder}
        others = [p for _, p in named if id(p) not in apart]
        self.lr_scales = (1.0, conf.damping_lr_scale) + ((conf.encoder_lr_scale,) if self.encoder else ())
        self.optimizer = torch.optim.Adam([
            {"params": others, "lr": conf.lr},
            {"params": damping, "lr": conf.lr * conf.damping_lr_scale}]
            + ([{"params": self.encoder, "lr": conf.lr * conf.encoder_lr_scale}] if self.encoder else []))
        if hasattr(model.extractor, "grad_checkpointing"):
            model.extractor.grad_checkpointing = conf.grad_checkpointing
        self.step_count = 0
        # the moving average of the trained parameters (float copies), when conf.ema > 0
        self.ema = {n: p.detach().clone() for n, p in model.named_parameters()} if conf.ema > 0 else None

    @torch.no_grad()
    def _update_ema(self) -> None:
        if self.ema is None:
            return
        d = self.conf.ema
        for n, p in self.model.named_parameters():
            self.ema[n].mul_(d).add_(p.detach(), alpha=1 - d)

    @contextlib.contextmanager
    def averaged(self):
        """Within this block the model holds the averaged weights (``conf.ema``; the trained ones
        when there is no average); they are swapped back after it."""
        if self.ema is None:
            yield self.model
            return
        params = dict(self.model.named_parameters())
        trained = {n: p.detach().clone() for n, p in params.items()}
        with torch.no_grad():
            for n, p in params.items():
                p.copy_(self.ema[n])
        try:
            yield self.model
        finally:
            with torch.no_grad():
                for n, p in params.items():
                    p.copy_(trained[n])

    def train_mode(self) -> None:
        self.model.train()
        if self.conf.freeze_batchnorm:
            for m in self.model.modules():
                if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
                    m.eval()

    def step(self, batch: Union[PairBatch, Sequence[PairBatch]]) -> Dict[str, float]:
        """One optimisation step on one batch, or on several pairs (stacked where their image sizes
        agree, gradients accumulated across sizes: the mean loss over all pairs); returns the
        metrics (means over the pairs; losses in pixels)."""
        self.train_mode()
        groups: Dict[tuple, List[PairBatch]] = {}
        for b in ([batch] if isinstance(batch, PairBatch) else batch):
            groups.setdefault(b.shape_key(), []).append(b)
        total = sum(len(b.image_ref) for g in groups.values() for b in g)
        factor = self.conf.lr_factor(self.step_count)
        for group, base in zip(self.optimizer.param_groups, self.lr_scales):
            group["lr"] = self.conf.lr * base * factor
        frozen = self.step_count < self.conf.freeze_encoder_steps
        for p in self.encoder:
            p.requires_grad_(not frozen)
        self.optimizer.zero_grad()
        sums: Dict[str, float] = {}
        finite = True
        for parts in groups.values():
            b = (parts[0] if len(parts) == 1 else PairBatch.stack(parts)).to(self.device)
            pred = self.model(b, num_iters=self.conf.num_iters)
            losses = self.model.loss(pred, b)
            with torch.no_grad():
                losses["error_px/init"] = reprojection_px(b.query_from_ref_init, b)
                losses["error_px"] = reprojection_px(pred["query_from_ref"][-1], b)
            for k, v in losses.items():
                sums[k] = sums.get(k, 0.0) + float(v.detach().sum())
            loss = losses["total"].sum() / total
            finite &= bool(torch.isfinite(loss))
            if finite and loss.requires_grad:
                loss.backward()
        metrics = {k: v / total for k, v in sums.items()}
        metrics["lr"] = self.conf.lr * factor
        if finite and any(p.grad is not None for p in self.model.parameters()):
            norm = torch.nn.utils.clip_grad_norm_(self.model.parameters(), self.conf.clip_grad)
            metrics["grad_norm"] = float(norm)
            if math.isfinite(metrics["grad_norm"]):
                self.optimizer.step()
        self._update_ema()
        self.step_count += 1
        metrics["step"] = self.step_count
        return metrics

    def state_dict(self) -> Dict:
        state = {"model": self.model.state_dict(), "optimizer": self.optimizer.state_dict(),
                 "step": self.step_count, "rng": torch.get_rng_state()}
        if self.ema is not None:
            state["ema"] = self.ema
        return state

    def load_state_dict(self, state: Dict) -> None:
        self.model.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.step_count = int(state["step"])
        torch.set_rng_state(state["rng"])
        if self.ema is not None:
            if "ema" not in state:
                raise ValueError("This checkpoint has no weight average (ema): resume it with the config it "
                                 "was trained with, or restart.")
            for n, v in state["ema"].items():
                self.ema[n].copy_(v)
