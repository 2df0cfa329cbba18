"""One Levenberg-Marquardt loop for featuremetric pose refinement, batched.

The loop is written once; damping (a module), robust loss and stopping rule
are parts. It is differentiable end to end when unrolled in training mode.
"""

import logging
from dataclasses import dataclass
from typing import Callable, Optional, Tuple

import torch
from torch import Tensor, nn

from ..geometry import Pose
from ..interpolation import Interpolator
from ..losses import get_loss
from .cost import FeaturemetricProblem, Linearization, build_system, linearize, robust_weights, use_cell_products
from .bodies import Bodies
from .damping import ConstantDamping
from .keypoints import KeypointTerm, scaled_system

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class StoppingRule:
    """Official PixLoc early stopping, checked only at iterations 0, every, 2 every, ...

    An element has converged when its gradient norm is below ``grad`` or its
    step is below both ``dt`` (scene units) and ``dR`` (degrees). Only in eval
    mode: a training unroll always runs every iteration.
    """

    every: int = 10
    grad: float = 1e-4
    dt: float = 5e-3
    dR: float = 5e-2

    def converged(self, step: Pose, g: Tensor) -> Tensor:
        dR, dt = step.magnitude()
        return (g.detach().norm(dim=-1) < self.grad) | ((dt < self.dt) & (dR < self.dR))


@dataclass
class LMResult:
    """Result of a batch of B alignments.

    pose: (B,) refined cam_from_world. failed: (B,) fewer than ``min_points``
    valid points at some iteration, or a non-finite step. cost: (B, I) mean
    robust cost over valid points at each of the I iterations run (a problem that
    stopped earlier keeps its last cost in the later columns).
    iterations: (B,) iterations each problem took (until it converged or the
    budget ran out). num_valid: (B,) valid points at the last iteration.
    trajectory: (B, I) pose after each iteration, if asked for. body_pose: (K,) body_from_world of
    each body where the problems were solved as bodies (``pixloc.optim.bodies``).
    """

    pose: Pose
    failed: Tensor
    cost: Tensor
    iterations: Tensor
    num_valid: Tensor
    trajectory: Optional[Pose] = None
    body_pose: Optional[Pose] = None

    @property
    def num_iters(self) -> int:
        """Iterations the loop ran (the maximum over the batch)."""
        return self.cost.shape[-1]


def solve_damped(g: Tensor, H: Tensor, lambda_: Tensor, active: Tensor, eps: float = 1e-6) -> Tensor:
    """delta = -(H + diag(max(lambda * diag(H), eps)))^-1 g, zero where not active.

    Cholesky with an LU fallback for elements where it fails (official PixLoc
    falls back to LU for the whole batch). Runs on the tensors' device.
    """
    diag = (H.diagonal(dim1=-2, dim2=-1) * lambda_).clamp(min=eps)
    H = H + torch.diag_embed(diag)
    eye = torch.eye(6, dtype=H.dtype, device=H.device)
    H = torch.where(active[..., None, None], H, eye)
    g = g.masked_fill(~active[..., None], 0.0)
    L, info = torch.linalg.cholesky_ex(H)
    ok = info == 0
    L = torch.where(ok[..., None, None], L, eye)
    delta = -torch.cholesky_solve(g[..., None], L)[..., 0]
    if not bool(ok.all()):
        logger.debug("Cholesky failed for %d problems, falling back to LU.", int((~ok).sum()))
        lu, _ = torch.linalg.solve_ex(H, -g)
        delta = torch.where(ok[..., None], delta, lu)
    return delta


class LevenbergMarquardt(nn.Module):
    """Featuremetric LM on the query pose, for one pyramid level.

    damping: module returning the 6-vector lambda (ConstantDamping, LearnedDamping).
    loss: robust loss spec (official default ``scaled_barron(0, 0.1)``).
    num_iters: iteration budget. pad: border margin of the interpolation in
    feature-map pixels. min_points: fewer valid points at any iteration fails
    the problem (official: 10). gradient_maps: at levels crowded with points,
    sample precomputed central-difference maps instead of 5 taps per point
    (``pixloc.interpolation.Interpolator``; the same residuals and Jacobians to
    rounding, 1.35x faster per 7-Scenes query end to end).

    chunk_points: on CPU, the batch is linearized in chunks of problems holding
    at most this many points in all (at least one problem per chunk), so that
    the working set of large batches stays in cache. On a GPU the limit is
    ``gpu_chunk_points``, which only bounds memory: there, chunks run one after
    the other and would undo the batching.

    system_builder: a compiled implementation of ``build_system`` (the same arguments and results, e.g.
    ``pipeline.kernels.build_system``) for the normal equations at every iteration, or None.

    Unlike official PixLoc, which stops a batch only when all of it has
    converged, each problem is frozen at the check where it converges, so a
    batched solve gives the same poses as solving the problems one by one; from
    then on it is no longer linearized, so a batch costs the sum of its
    problems' iterations, not its size times the slowest one's.
    """

    def __init__(self, damping: Optional[nn.Module] = None, loss: str = "scaled_barron(0, 0.1)",
                 num_iters: int = 100, pad: int = 2, interpolation: str = "linear",
                 min_points: int = 10, stopping: StoppingRule = StoppingRule(),
                 chunk_points: int = 16384, gpu_chunk_points: int = 1 << 21, gradient_maps: bool = True,
                 system_builder: Optional[Callable[[Linearization, Tensor], Tuple[Tensor, Tensor]]] = None):
        super().__init__()
        self.damping = damping if damping is not None else ConstantDamping(0.0)
        self.loss_spec = loss
        self.loss_fn = get_loss(loss)
        self.num_iters = num_iters
        self.interpolator = Interpolator(interpolation, pad, gradient_maps)
        self.min_points = min_points
        self.stopping = stopping
        self.chunk_points = chunk_points
        self.gpu_chunk_points = gpu_chunk_points
        self.system_builder = system_builder

    def _chunks(self, problem: FeaturemetricProblem, active: Optional[Tensor] = None):
        """(slice of the batch, sub-problem) pairs covering the ``active`` problems (default all):
        runs of consecutive active problems, each cut into chunks of at most the point limit.
        Slices make views: nothing is copied."""
        B, N = problem.p3d_world.shape[:2]
        limit = self.chunk_points if problem.F_ref.device.type == "cpu" else self.gpu_chunk_points
        size = max(1, limit // max(N, 1))
        if active is None or bool(active.all()):
            if size >= B:
                return [(slice(None), problem)]
            runs = [(0, B)]
        else:
            idx = torch.nonzero(active).flatten().tolist()
            runs, start = [], None
            for k, j in enumerate(idx):
                if start is None:
                    start = j
                if k + 1 == len(idx) or idx[k + 1] != j + 1:
                    runs.append((start, j + 1))
                    start = None
        return [(slice(i, min(i + size, stop)), problem.index(slice(i, min(i + size, stop))))
                for begin, stop in runs for i in range(begin, stop, size)]

    def _normal_equations(self, T: Pose, chunks):
        """Per problem: gradient (B, 6), Hessian (B, 6, 6), valid count (B,), mean robust cost (B,), and the
        residuals' scale: the unit-weight variance sum w |r|^2 / valid count (B,), w the LM's weights."""
        out = []
        for sl, part in chunks:
            lin = linearize(T[sl], part, self.interpolator)
            num_valid = lin.valid.sum(-1)
            rho, weights = robust_weights(lin, self.loss_fn)
            g, H = (self.system_builder or build_system)(lin, weights)
            conf = lin.confidence if lin.confidence is not None else lin.valid.to(rho.dtype)
            n = num_valid.clamp(min=1)
            out.append((g, H, num_valid, (rho * conf).sum(-1) / n, (weights * lin.sq).sum(-1) / n))
        return [torch.cat(x) for x in zip(*out)] if len(out) > 1 else out[0]

    def forward(self, problem: FeaturemetricProblem, T_init: Pose,
                num_iters: Optional[int] = None, record_trajectory: bool = False,
                keypoints: Optional[KeypointTerm] = None, bodies: Optional[Bodies] = None) -> LMResult:
        """Refine T_init (B,) cam_from_world poses on ``problem`` (B problems); with ``keypoints``, the
        cost adds their reprojection error, each term normalised by its residual scale
        (``pixloc.optim.keypoints``); with ``bodies``, the problems of one body move as one
        (``pixloc.optim.bodies``: its pose starts from its first problem's T_init, and it converges,
        fails and stops as one)."""
        B = problem.batch_size
        if tuple(T_init.shape) != (B,):
            raise ValueError(f"T_init must have batch shape ({B},), got {tuple(T_init.shape)}.")
        if not bool(T_init.isfinite().all()):
            raise ValueError("T_init contains NaN or infinite values.")
        if bodies is not None and len(bodies.index) != B:
            raise ValueError(f"bodies must give a body to each of the {B} problems, got {len(bodies.index)}.")
        num_iters = self.num_iters if num_iters is None else num_iters
        lambda_ = self.damping().to(problem.F_ref)
        device = problem.F_ref.device

        # the optimised poses: the problems' own, or their bodies'; ``per_problem`` maps (K,) to (B,)
        if bodies is not None:
            bodies = bodies.to(device)
            T_opt = bodies.body_poses(T_init)
            per_problem = bodies.spread
        else:
            T_opt, per_problem = T_init, (lambda x: x)
        T = T_init if bodies is None else bodies.camera_poses(T_opt)
        K = len(T_opt)
        failed = torch.zeros(K, dtype=torch.bool, device=device)
        active = torch.ones(K, dtype=torch.bool, device=device)
        iterations = torch.zeros(K, dtype=torch.long, device=device)
        costs, trajectory = [], []
        if use_cell_products(problem, self.interpolator):  # built once for the batch; its chunks share them
            _ = problem.cell_products
        chunks, linearized = self._chunks(problem), active
        scale_f = None  # with keypoints: the featuremetric residuals' scale at the start
        if keypoints is not None:
            keypoints = keypoints.to(problem.F_ref.device)
        for i in range(num_iters):
            if linearized is active:
                g, H, num_valid, cost, spread = self._normal_equations(T, chunks)
            else:  # only the problems still running are linearized; the others keep their last figures
                rows = torch.cat([torch.arange(B, device=device)[sl] for sl, _ in chunks])
                g_a, H_a, valid_a, cost_a, spread_a = self._normal_equations(T, chunks)
                g = torch.zeros_like(g).index_copy(0, rows, g_a)
                H = torch.zeros_like(H).index_copy(0, rows, H_a)
                num_valid = num_valid.index_copy(0, rows, valid_a)
                cost = cost.index_copy(0, rows, cost_a)
                spread = spread.index_copy(0, rows, spread_a)
            g, H, scale_f = scaled_system(scale_f, g, H, keypoints, T, spread)
            if bodies is None:
                g_opt, H_opt, valid_opt = g, H, num_valid
            else:  # each camera's system through its cam_from_body, summed per body
                g_opt, H_opt = bodies.reduce(g, H)
                valid_opt = bodies.sum(num_valid)
            failed = failed | (valid_opt < self.min_points)

            step_mask = active & ~failed
            delta = solve_damped(g_opt, H_opt, lambda_, step_mask)
            dt, dw = delta.split([3, 3], dim=-1)
            step = Pose.from_aa(dw, dt)
            T_new = step @ T_opt
            # A non-finite step fails its problem and keeps the last pose.
            bad = ~T_new.isfinite()
            failed = failed | bad
            T_opt = Pose(torch.where(bad[:, None], T_opt.data, T_new.data))
            T = T_opt if bodies is None else bodies.camera_poses(T_opt)

            costs.append(cost)
            iterations = iterations + active.long()
            if record_trajectory:
                trajectory.append(T.detach())
            if not self.training and i % self.stopping.every == 0:
                running = active & ~(self.stopping.converged(step, g_opt) | failed)
                if not bool(running.any()):
                    break
                if not bool(torch.equal(running, active)):  # some stopped: linearize only the others
                    active = running
                    chunks, linearized = self._chunks(problem, per_problem(active)), None

        if bool(failed.any()):
            logger.debug("%d of %d problems failed (too few valid points).", int(failed.sum()), K)
        return LMResult(
            pose=T, failed=per_problem(failed), cost=torch.stack(costs, -1), iterations=per_problem(iterations),
            num_valid=num_valid,
            trajectory=Pose.stack(trajectory, dim=1) if record_trajectory else None,
            body_pose=T_opt if bodies is not None else None)
