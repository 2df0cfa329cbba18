"""The featuremetric residual of PixLoc and its Jacobian w.r.t. the query pose."""

from dataclasses import dataclass, replace
from functools import cached_property
from typing import Callable, NamedTuple, Optional, Tuple

import torch
from torch import Tensor

from ..geometry import Camera, Pose
from ..interpolation import Interpolator, append_gradient_maps, can_reduce_taps, mask_in_image, reduce_taps


@dataclass(frozen=True)
class FeaturemetricProblem:
    """A batch of B independent alignment problems: find cam_from_world of the query.

    p3d_world: (B, N, 3) 3D points in the world frame.
    F_ref: (B, N, C) reference features of the points, used as given.
    F_query: (B, C, H, W) dense query features at this level, used as given
        (official PixLoc L2-normalises the dense map, not the samples).
    camera: (B,) query camera at the resolution of ``F_query``.
    W_ref: (B, N) reference confidences, or None.
    W_query: (B, H, W) dense query confidences, or None. Both or neither.
    mask: (B, N) bool, observations to use (padding of ragged batches), or None.
    maps: (B, C + 1, H, W), F_query and W_query stacked, when the caller has built them so
        (``new_query_maps``): F_query and W_query are then views of it, and the largest
        tensor of the problem is not copied again.
    fill: maps decoded on demand: ``fill(p2d, rows, gradients)`` decodes the cells that sampling the
        maps of batch rows ``rows`` (a range) at ``p2d`` (len(rows), N, 2) reads, with central
        differences or values only; ``maps_at`` calls it.
    rows: this problem's rows of the batch that ``fill`` serves (None: all of them; a sub-batch's).
    """

    p3d_world: Tensor
    F_ref: Tensor
    F_query: Tensor
    camera: Camera
    W_ref: Optional[Tensor] = None
    W_query: Optional[Tensor] = None
    mask: Optional[Tensor] = None
    maps: Optional[Tensor] = None
    fill: Optional[Callable[[Tensor, range, bool], None]] = None
    rows: Optional[range] = None

    def __post_init__(self):
        p, F, Fq = self.p3d_world, self.F_ref, self.F_query
        if p.dim() != 3 or p.shape[-1] != 3:
            raise ValueError(f"p3d_world must be (B, N, 3), got {tuple(p.shape)}.")
        B, N = p.shape[:2]
        if F.shape[:2] != (B, N) or F.dim() != 3:
            raise ValueError(f"F_ref must be (B, N, C) = ({B}, {N}, C), got {tuple(F.shape)}.")
        if Fq.dim() != 4 or Fq.shape[:2] != (B, F.shape[-1]):
            raise ValueError(f"F_query must be (B, C, H, W) with B={B}, C={F.shape[-1]}, got {tuple(Fq.shape)}.")
        if tuple(self.camera.shape) != (B,):
            raise ValueError(f"camera must have batch shape ({B},), got {tuple(self.camera.shape)}.")
        if (self.W_ref is None) != (self.W_query is None):
            raise ValueError("Give both W_ref and W_query confidences, or neither.")
        if self.W_ref is not None:
            if tuple(self.W_ref.shape) != (B, N):
                raise ValueError(f"W_ref must be (B, N) = ({B}, {N}), got {tuple(self.W_ref.shape)}.")
            if tuple(self.W_query.shape) != (B,) + tuple(Fq.shape[-2:]):
                raise ValueError(f"W_query must be (B, H, W) = ({B}, {Fq.shape[-2]}, {Fq.shape[-1]}), "
                                 f"got {tuple(self.W_query.shape)}.")
        if self.maps is not None and not (self.W_query is not None and self.maps.shape[1] == Fq.shape[1] + 1
                                          and _same_view(self.maps[:, -1], self.W_query)
                                          and _same_view(self.maps[:, :-1], Fq)):
            raise ValueError("maps must be F_query and W_query stacked, (B, C + 1, H, W), with F_query and "
                             "W_query views of it.")
        if self.mask is not None and tuple(self.mask.shape) != (B, N):
            raise ValueError(f"mask must be (B, N) = ({B}, {N}), got {tuple(self.mask.shape)}.")
        if not torch.isfinite(p).all():
            raise ValueError("p3d_world contains NaN or infinite coordinates.")

    @classmethod
    def single(cls, p3d_world, F_ref, F_query, camera, W_ref=None, W_query=None, mask=None):
        """One problem without a batch dim: p3d (N, 3), F_ref (N, C), F_query (C, H, W), W_query (H, W)."""
        def add(x):
            return None if x is None else x[None]
        return cls(p3d_world[None], F_ref[None], F_query[None], camera.reshape(1),
                   add(W_ref), add(W_query), add(mask))

    @cached_property
    def query_maps(self) -> Tensor:
        """(B, C[+1], H, W) query features with the confidence appended as a channel,
        so that one sampling call serves both (official inference does the same).

        Laid out as ``query_maps_layout`` says."""
        if self.maps is not None:
            return self.maps
        if self.W_query is None:
            return self.F_query.contiguous(memory_format=query_maps_layout(self.F_query))
        out = new_query_maps(self.F_query.shape, self.F_query, with_confidence=True)
        C = self.F_query.shape[1]
        out[:, :C] = self.F_query
        out[:, C] = self.W_query
        return out

    def maps_at(self, p2d: Tensor, gradients: bool = True) -> Tensor:
        """``query_maps``, to be sampled at ``p2d`` (B, N, 2), with the official central differences
        (``gradients``) or values only: the cells that sampling reads decoded first where the problem's
        maps are decoded on demand (``fill``)."""
        if self.fill is not None:
            self.fill(p2d, range(self.batch_size) if self.rows is None else self.rows, gradients)
        return self.query_maps

    @cached_property
    def query_maps_with_gradients(self) -> Tensor:
        """``query_maps`` with the central differences of the C feature channels appended (x, then
        y): (B, 3 C [+ 1], H, W), built once per problem, sampled at every LM iteration."""
        C = self.F_query.shape[1]
        maps = self.query_maps
        return append_gradient_maps(maps, C, query_maps_layout(maps, maps.shape[1] + 2 * C))

    @cached_property
    def F_ref_channels_first(self) -> Tensor:
        """F_ref as (B, C, N), contiguous: the layout of the query maps' samples (``linearize``)."""
        return self.F_ref.transpose(1, 2).contiguous()

    @cached_property
    def cell_products(self) -> "CellProducts":
        """``CellProducts`` of the maps with gradients: built once per problem, read at every LM iteration."""
        return CellProducts.of(self)

    @property
    def batch_size(self) -> int:
        return self.p3d_world.shape[0]

    def index(self, i) -> "FeaturemetricProblem":
        """Sub-batch ``i`` (an int keeps a batch of one). An int or a slice gives views, nothing is
        copied (a 1,024 px query's finest maps are 90 MB); a list of indices copies."""
        i = slice(i, i + 1) if isinstance(i, int) else i

        def sel(x):
            return None if x is None else x[i]
        if self.maps is not None:  # the query maps stay views of the stacked maps
            maps = self.maps[i]
            F_query, W_query = maps[:, :-1], maps[:, -1]
        else:
            maps, F_query, W_query = None, self.F_query[i], sel(self.W_query)
        rows = None
        if self.fill is not None:  # fill writes into these maps: a copy would not see it
            if not isinstance(i, slice):
                raise ValueError("A problem whose maps are decoded on demand is indexed by an int or a slice.")
            rows = (range(self.batch_size) if self.rows is None else self.rows)[i]
        sub = replace(self, p3d_world=self.p3d_world[i], F_ref=self.F_ref[i], F_query=F_query,
                      camera=self.camera[i], W_ref=sel(self.W_ref), W_query=W_query,
                      mask=sel(self.mask), maps=maps, rows=rows)
        if "cell_products" in self.__dict__:  # built for the whole batch: the LM's chunks share them
            sub.__dict__["cell_products"] = CellProducts(*(sel(x) for x in self.cell_products))
        if "F_ref_channels_first" in self.__dict__:
            sub.__dict__["F_ref_channels_first"] = sel(self.F_ref_channels_first)
        return sub


def _same_view(a: Tensor, b: Tensor) -> bool:
    """Whether ``a`` and ``b`` are the same view of one storage (not only equal values)."""
    return a.shape == b.shape and a.stride() == b.stride() and a.data_ptr() == b.data_ptr() \
        and a.dtype == b.dtype and a.device == b.device


def query_maps_layout(like: Tensor, channels: Optional[int] = None) -> torch.memory_format:
    """Memory layout of query maps for sampling. On CPU, maps of 64 channels or more are
    channels-last: bilinear sampling then reads each tap's channels contiguously, which made
    it 2.3x faster on the 129 x 175 x 256 maps of a 1024 px query (bitwise the same samples).
    Thinner maps stay as they are, unless they already are channels-last (a network prepared
    for inference gives such maps): there the layout change costs more than it saves."""
    channels = like.shape[1] if channels is None else channels
    if like.device.type == "cpu" and (channels >= 64 or _is_channels_last(like)):
        return torch.channels_last
    return torch.contiguous_format


def _is_channels_last(x: Tensor) -> bool:
    return x.dim() == 4 and x.shape[1] > 1 and not x.is_contiguous() \
        and x.is_contiguous(memory_format=torch.channels_last)


def new_query_maps(shape, like: Tensor, with_confidence: bool = True, dtype: Optional[torch.dtype] = None) -> Tensor:
    """An empty (B, C [+ 1], H, W) buffer for query maps, in ``query_maps_layout``, of ``like``'s dtype
    unless ``dtype`` is given."""
    B, C, H, W = shape
    C = C + int(with_confidence)
    return torch.empty((B, C, H, W), dtype=like.dtype if dtype is None else dtype, device=like.device,
                       memory_format=query_maps_layout(like, C))


class Linearization(NamedTuple):
    """Residuals and Jacobian factors at one pose, reduced over the C feature channels.

    sq: (B, N) squared residual norms |r|^2; valid: (B, N); confidence: (B, N) product of both
    confidences (None without confidences); Jf_r: (B, N, 2) J_f^T r and Jf_Jf: (B, N, 2, 2) J_f^T J_f,
    for J_f (B, N, C, 2) the feature gradients in the query map; J_p2d_pose: (B, N, 2, 6) the
    projection Jacobian. The full Jacobian J_f @ J_p2d_pose is never formed by the solver. Where
    the maps were sampled, also res (B, N, C) and J_f themselves (None from ``CellProducts``).
    """

    sq: Tensor
    valid: Tensor
    confidence: Optional[Tensor]
    Jf_r: Tensor
    Jf_Jf: Tensor
    J_p2d_pose: Tensor
    res: Optional[Tensor] = None
    J_f: Optional[Tensor] = None


# Gradient maps (``append_gradient_maps``) are built when the map has at most this many cells per
# point: building them costs about 8 C per cell and saves about 14 C per point and LM iteration
# (5 taps and a stack against 3 channel blocks), so they pay from the second iteration, and they
# take no more memory than the 5-tap samples. Fine levels with few points keep the 5 taps.
GRADIENT_MAPS_MAX_CELLS_PER_POINT = 2
# Cell products (``CellProducts``) replace the sampling where, besides, the map has at most this many
# cells: built once per level at a cost that grows with cells x (cells + points). Measured with 2,000
# points of 128 channels on one core: 11 x 16 cells (the coarsest level of a 256 px query) took 5-7 ms
# to build and 1.5-1.9 ms per linearization against 3.4-4.0 ms sampled; 21 x 32 cells took 35-45 ms
# to build and saved nothing per linearization.
CELL_PRODUCTS_MAX_CELLS = 256
# ... and where its reference products (points x cells x 3, float32) take at most this many bytes per
# problem: they are kept for the whole level, where the sampling's are transient
CELL_PRODUCTS_MAX_BYTES = 32 * 2**20


def use_compiled_taps(problem: FeaturemetricProblem, interpolator: Interpolator) -> bool:
    """Where the interpolator has a compiled ``reduce_taps`` (``Interpolator.tap_reducer``), at inference
    on channels-last CPU maps: it serves every level, and neither gradient maps nor cell products are
    built (one pass per point over the 12 cells that the taps read, against a dozen tensor ops per
    iteration: docs/benchmarks.md, "The LM's taps and normal equations in one compiled pass per point")."""
    return interpolator.tap_reducer is not None and not torch.is_grad_enabled() \
        and can_reduce_taps(problem.query_maps)


def use_gradient_maps(problem: FeaturemetricProblem, interpolator: Interpolator) -> bool:
    H, W = problem.F_query.shape[-2:]  # (maps decoded on demand are sampled where they are decoded)
    return interpolator.gradient_maps and problem.fill is None \
        and H * W <= GRADIENT_MAPS_MAX_CELLS_PER_POINT * problem.p3d_world.shape[1] \
        and not use_compiled_taps(problem, interpolator)


def use_cell_products(problem: FeaturemetricProblem, interpolator: Interpolator) -> bool:
    """Where the interpolator allows it, at inference only (a training unroll differentiates the
    sampled maps), on CPU only (where it was measured), on maps of at most
    ``CELL_PRODUCTS_MAX_CELLS`` cells sampled with gradient maps, for at most ``CELL_PRODUCTS_MAX_BYTES``
    of reference products per problem."""
    H, W = problem.F_query.shape[-2:]
    points = problem.p3d_world.shape[1]
    return interpolator.cell_products and not torch.is_grad_enabled() and problem.F_query.device.type == "cpu" \
        and H * W <= CELL_PRODUCTS_MAX_CELLS and points * H * W * 12 <= CELL_PRODUCTS_MAX_BYTES \
        and use_gradient_maps(problem, interpolator)


def use_reduced_taps(problem: FeaturemetricProblem, interpolator: Interpolator) -> bool:
    """Where the maps are sampled with the 5 official taps (not gradient maps nor cell products), at
    inference (a training unroll differentiates the samples), on channels-last CPU maps
    (``pixloc.interpolation.can_reduce_taps``): ``reduce_taps`` gives the LM's products without the
    samples."""
    return interpolator.mode == "linear" and not torch.is_grad_enabled() \
        and not use_gradient_maps(problem, interpolator) and can_reduce_taps(problem.query_maps)


# the pairs (j, k), j <= k, of a sample's 4 cells, and the inner products s_p . s_q of its value (p = 0) and
# x and y gradients (1, 2) that ``linearize`` reads, (p, q) = (0, 0), (1, 0), (2, 0), (1, 1), (2, 1), (2, 2)
_CELL_PAIRS = torch.tensor([(j, k) for j in range(4) for k in range(j, 4)]).T  # 2 x 10
_SAMPLE_PRODUCTS = torch.tensor([(0, 0), (1, 0), (2, 0), (1, 1), (2, 1), (2, 2)]).T  # 2 x 6
_JF_JF = torch.tensor([3, 4, 4, 5])  # J_f^T J_f from those 6: (1, 1), (2, 1), (1, 2) = (2, 1), (2, 2)


class CellProducts(NamedTuple):
    """What the bilinear samples of a small map need, computed once per problem.

    A bilinear sample of the maps at a point is a weighted sum of 4 cells, and its gradient maps'
    samples too (``append_gradient_maps``): so the squared residual |v - f|^2, J_f^T r and J_f^T J_f of
    ``linearize`` are sums of inner products of those cells with each other and with the point's
    reference feature f. With e_0, e_1, e_2 the features and their x and y gradient maps, s_p the
    sample of e_p with weights b_j at the 4 cells j0, j0 + 1, j0 + W, j0 + W + 1 of a sample whose
    top-left cell is j0, s_p . s_q = sum over the 10 pairs j <= k of b_j b_k c_jk, with c_jj =
    e_p(j) . e_q(j) and c_jk = e_p(j) . e_q(k) + e_p(k) . e_q(j):
    ``patches`` (B, HW, 10 x 6): c_jk for the pairs (``_CELL_PAIRS``) and the 6 products (p, q) that
    ``linearize`` reads (``_SAMPLE_PRODUCTS``; s_1 . s_2 = s_2 . s_1);
    ``ref`` (B, N, HW x 3): f_i . e_p(j) for every cell j; ``ref_sq`` (B, N): |f_i|^2;
    ``confidence`` (B, HW) or None. An LM iteration then reads 60 + 12 numbers per point instead
    of sampling 3 C + 1 channels at 4 cells: the same figures to float rounding. (The 144 products of
    every (j, k, p, q) and a ``take`` of flat indices, before: a linearization of 5 x 2,349 points on
    the 10 x 16 cells of a 256 px query took 7.2 ms, 4.1 ms since, on one core.)"""

    patches: Tensor
    ref: Tensor
    ref_sq: Tensor
    confidence: Optional[Tensor]

    @classmethod
    def of(cls, problem: FeaturemetricProblem) -> "CellProducts":
        C = problem.F_ref.shape[-1]
        maps = problem.query_maps_with_gradients  # (B, K + 2 C, H, W): features [, confidence], x, y gradients
        B, total, H, W = maps.shape
        k = total - 2 * C
        cells = maps.permute(0, 2, 3, 1).reshape(B, H * W, total)
        e = torch.stack([cells[..., :C], cells[..., k:k + C], cells[..., k + C:]], 2).reshape(B, H * W * 3, C)
        gram = (e @ e.transpose(1, 2)).reshape(B, H * W, 3, H * W, 3).permute(0, 1, 3, 2, 4)  # B x j x k x p x q
        corners = (torch.arange(H * W, device=maps.device)[:, None]
                   + torch.tensor([0, 1, W, W + 1], device=maps.device)).clamp(max=H * W - 1)  # HW x 4
        j, k_ = _CELL_PAIRS.to(maps.device)
        p, q = _SAMPLE_PRODUCTS.to(maps.device)
        cj, ck = corners[:, j, None], corners[:, k_, None]  # HW x 10 x 1
        pairs = gram[:, cj, ck, p, q]  # B x HW x 10 x 6: e_p(j) . e_q(k)
        pairs = pairs + torch.where((j == k_)[:, None], 0.0, gram[:, ck, cj, p, q])  # + e_p(k) . e_q(j), j < k
        ref = problem.F_ref @ e.transpose(1, 2)  # B x N x (HW x 3)
        confidence = cells[..., C].contiguous() if k > C else None
        return cls(pairs.reshape(B, H * W, 60).contiguous(), ref, (problem.F_ref ** 2).sum(-1), confidence)

    def linearize(self, p2d: Tensor, size: Tuple[int, int]) -> Tuple[Tensor, Tensor, Tensor, Optional[Tensor]]:
        """At points p2d (B, N, 2) of a map of ``size`` (H, W): |r|^2 (B, N), J_f^T r (B, N, 2),
        J_f^T J_f (B, N, 2, 2) and the sampled query confidence (B, N) or None. Points outside the
        map get finite values from its border cells (grid_sample gives zeros): they are not valid."""
        H, W = size
        B, N = p2d.shape[:2]
        p = torch.nan_to_num(p2d, nan=0.0, posinf=0.0, neginf=0.0)
        x, y = p[..., 0].clamp(0, W - 1), p[..., 1].clamp(0, H - 1)
        x0, y0 = x.floor().clamp(max=max(W - 2, 0)), y.floor().clamp(max=max(H - 2, 0))
        fx, fy = (x - x0).clamp(0, 1), (y - y0).clamp(0, 1)
        j0 = (y0 * W + x0).long()  # B x N, the top-left cell
        b = torch.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], -1)  # B x N x 4
        rows = j0 + (torch.arange(B, device=p.device) * (H * W))[:, None]
        patch = self.patches.reshape(B * H * W, 60).index_select(0, rows.reshape(-1)).reshape(B, N, 10, 6)
        j, k = _CELL_PAIRS.to(p.device)
        bb = b.index_select(-1, j) * b.index_select(-1, k)  # B x N x 10: b_j b_k
        q = (patch * bb[..., None]).sum(2)  # s_p . s_q, B x N x 6 (_SAMPLE_PRODUCTS)
        # f . s_p for the samples s_0 = v, s_1 = d v / dx, s_2 = d v / dy: cells j0, j0 + 1 and j0 + W, j0 + W + 1
        # (a gather along the rows: 3-10x faster than a take of flat indices into the whole batch)
        offsets = torch.cat([torch.arange(6), torch.arange(6) + 3 * W]).to(p.device)
        at = (3 * j0[..., None] + offsets).clamp(max=self.ref.shape[-1] - 1)
        r = (b[..., None] * self.ref.gather(2, at).reshape(B, N, 4, 3)).sum(2)
        sq = (q[..., 0] - 2 * r[..., 0] + self.ref_sq).clamp(min=0)
        Jf_r = torch.stack([q[..., 1] - r[..., 1], q[..., 2] - r[..., 2]], -1)
        Jf_Jf = q.index_select(-1, _JF_JF.to(p.device)).reshape(B, N, 2, 2)
        confidence = None
        if self.confidence is not None:
            corners = (j0[..., None] + torch.tensor([0, 1, W, W + 1], device=p.device)).clamp(max=H * W - 1)
            confidence = (b * self.confidence.gather(1, corners.reshape(B, N * 4)).reshape(B, N, 4)).sum(-1)
        return sq, Jf_r, Jf_Jf, confidence


def linearize(cam_from_world: Pose, problem: FeaturemetricProblem,
              interpolator: Interpolator) -> Linearization:
    """Residuals r_i = F_q(pi(T P_i)) - F_ref,i and their Jacobian factors."""
    p3d_cam = cam_from_world.transform(problem.p3d_world)
    p2d, visible, J_p2d_cam = problem.camera.cam2image_with_J(p3d_cam)
    C = problem.F_ref.shape[-1]
    res = J_f = None
    if use_cell_products(problem, interpolator):  # small maps: inner products of their cells, once per level
        H, W = problem.F_query.shape[-2:]
        valid = mask_in_image(p2d, p2d.new_tensor([W, H]), interpolator.pad)
        sq, Jf_r, Jf_Jf, w_query = problem.cell_products.linearize(p2d, (H, W))
    elif use_reduced_taps(problem, interpolator):  # the 5 taps' cells gathered and reduced at once
        maps = problem.maps_at(p2d)
        H, W = maps.shape[-2:]
        valid = mask_in_image(p2d, p2d.new_tensor([W, H]), interpolator.pad)
        sq, Jf_r, Jf_Jf, rest = (interpolator.tap_reducer or reduce_taps)(maps, p2d, problem.F_ref)
        w_query = rest[..., 0] if problem.W_ref is not None else None
    else:
        if use_gradient_maps(problem, interpolator):  # one sampling of maps and gradient maps: the same gradients
            values, valid, J_f = interpolator.sample_with_gradients(problem.query_maps_with_gradients, p2d, C)
        else:
            values, valid, grads = interpolator(problem.maps_at(p2d), p2d, gradients=True)
            J_f = grads[..., :C, :]
        w_query = values[..., C] if problem.W_ref is not None else None
        if torch.is_grad_enabled():  # a training unroll: batched 2 x C matmuls, faster to differentiate
            res = values[..., :C] - problem.F_ref
            J_fT = J_f.transpose(-1, -2).contiguous()  # B x N x 2 x C, rows contiguous
            sq = (res ** 2).sum(-1)
            Jf_r = (J_fT @ res[..., None])[..., 0]  # B x N x 2
            Jf_Jf = J_fT @ J_fT.transpose(-1, -2)  # B x N x 2 x 2
        else:
            # the samplers give values and gradients channels first, as grid_sample writes them (B x C x N
            # and B x 2 x C x N, rows of points contiguous): the sums over C run along those rows, with no
            # transpose (the matmuls of the points' rows took twice as long, their transposes included)
            r = values.transpose(1, 2)[:, :C] - problem.F_ref_channels_first  # B x C x N
            G = J_f.permute(0, 3, 2, 1)  # B x 2 x C x N
            res = r.transpose(1, 2)
            sq = (r * r).sum(1)
            Jf_r = (G * r[:, None]).sum(2).transpose(1, 2)  # B x N x 2
            xx_yy, xy = (G * G).sum(2), (G[:, 0] * G[:, 1]).sum(1)  # the 3 products of J_f^T J_f, not 4
            Jf_Jf = torch.stack([xx_yy[:, 0], xy, xy, xx_yy[:, 1]], -1).reshape(*xy.shape, 2, 2)  # B x N x 2 x 2
    valid = valid & visible
    if problem.mask is not None:
        valid = valid & problem.mask
    confidence = None
    if problem.W_ref is not None:
        confidence = (problem.W_ref * w_query).masked_fill(~valid, 0.0)
    J_p2d_pose = Pose.J_left(J_p2d_cam, p3d_cam)
    return Linearization(sq, valid, confidence, Jf_r, Jf_Jf, J_p2d_pose, res, J_f)


def robust_weights(lin: Linearization, loss_fn) -> Tuple[Tensor, Tensor]:
    """Per point (B, N): the robust cost rho of its squared residual, and its weight in the normal
    equations: rho' x validity x the product of both confidences (where there are confidences)."""
    rho, w_loss, _ = loss_fn(lin.sq)
    weights = w_loss * lin.valid
    if lin.confidence is not None:
        weights = weights * lin.confidence
    return rho, weights


def build_system(lin: Linearization, weights: Tensor):
    """Gradient g = sum w J^T r (B, 6) and Gauss-Newton Hessian H = sum w J^T J (B, 6, 6).

    J = J_f @ J_p2d_pose is factored so that the C-dim contraction happens in
    2D first (``Linearization``): O(N C) instead of official PixLoc's O(N C 36) per-point 6x6.
    """
    B = weights.shape[0]
    Jp_w = (lin.J_p2d_pose * weights[..., None, None]).reshape(B, -1, 6)  # B x 2N x 6
    g = (Jp_w * lin.Jf_r.reshape(B, -1, 1)).sum(1)
    H = Jp_w.transpose(1, 2) @ (lin.Jf_Jf @ lin.J_p2d_pose).reshape(B, -1, 6)
    return g, H
