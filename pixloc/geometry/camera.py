"""Batched cameras: pinhole intrinsics plus a COLMAP lens distortion model."""

from functools import cached_property
from typing import Optional, Sequence, Tuple, Union

import torch
from torch import Tensor

from .distortion import DISTORTIONS
from .wrapper import TensorWrapper

# COLMAP model name -> (distortion kind, how to read COLMAP params into
# fx, fy, cx, cy, distortion params).
COLMAP_MODELS = {
    "SIMPLE_PINHOLE": "none",
    "PINHOLE": "none",
    "SIMPLE_RADIAL": "radial",
    "RADIAL": "radial",
    "OPENCV": "opencv",
    "FULL_OPENCV": "full_opencv",
    "OPENCV_FISHEYE": "fisheye",
}
NUM_COLMAP_PARAMS = {"SIMPLE_PINHOLE": 3, "PINHOLE": 4, "SIMPLE_RADIAL": 4, "RADIAL": 5,
                      "OPENCV": 8, "FULL_OPENCV": 12, "OPENCV_FISHEYE": 8}
# Official PixLoc infers the model from the parameter count.
_KIND_FROM_LENGTH = {6: "none", 8: "radial", 10: "opencv", 14: "full_opencv"}


def _one_distortion(cameras: Sequence["Camera"], what: str) -> None:
    kinds = {c.distortion for c in cameras}
    if len(kinds) > 1:
        raise ValueError(f"Cannot {what} cameras with different distortion models: {sorted(kinds)}.")


class Camera(TensorWrapper):
    """A batch of cameras, stored as (..., 6 + D) = [w, h, fx, fy, cx, cy, dist...].

    The pixel origin is the centre of the top-left pixel (official PixLoc),
    i.e. ``c = c_colmap - 0.5``. All cameras of a batch share one distortion
    kind (``none``, ``radial``, ``opencv``, ``full_opencv``, ``fisheye``).
    """

    eps = 1e-3  # minimum depth, as official PixLoc

    def __init__(self, data: Tensor, distortion: Optional[str] = None):
        super().__init__(data)
        n = data.shape[-1]
        if distortion is None:
            if n not in _KIND_FROM_LENGTH:
                raise ValueError(
                    f"Cannot infer the camera model from {n} parameters; expected 6, 8, 10 or 14, "
                    "or pass distortion= explicitly.")
            distortion = _KIND_FROM_LENGTH[n]
        if distortion not in DISTORTIONS:
            raise ValueError(f"Unknown distortion kind {distortion!r}; known: {sorted(DISTORTIONS)}.")
        if n != 6 + DISTORTIONS[distortion].num_params:
            raise ValueError(f"Distortion {distortion!r} needs {6 + DISTORTIONS[distortion].num_params} "
                             f"camera values, got {n}.")
        self.distortion = distortion

    def _new(self, data: Tensor) -> "Camera":
        return Camera(data, self.distortion)

    @classmethod
    def stack(cls, objects: Sequence["Camera"], dim: int = 0) -> "Camera":
        _one_distortion(objects, "stack")
        return super().stack(objects, dim)

    @classmethod
    def cat(cls, objects: Sequence["Camera"], dim: int = 0) -> "Camera":
        _one_distortion(objects, "concatenate")
        return super().cat(objects, dim)

    @classmethod
    def from_colmap(cls, model: str, width: float, height: float,
                    params: Sequence[float], dtype=torch.float32) -> "Camera":
        """From a COLMAP camera (model name, size, params in COLMAP's convention)."""
        if model not in COLMAP_MODELS:
            raise ValueError(f"Unsupported camera model {model!r}; supported: {', '.join(COLMAP_MODELS)}.")
        params = [float(p) for p in params]
        if len(params) != NUM_COLMAP_PARAMS[model]:
            raise ValueError(f"Camera model {model} has {NUM_COLMAP_PARAMS[model]} parameters, "
                             f"got {len(params)}.")
        if model.startswith("SIMPLE") or model == "RADIAL":
            f, cx, cy, *dist = params
            fx = fy = f
        else:
            fx, fy, cx, cy, *dist = params
        if model == "SIMPLE_RADIAL":
            dist = dist + [0.0]
        data = torch.tensor([width, height, fx, fy, cx - 0.5, cy - 0.5, *dist], dtype=dtype)
        return cls(data, COLMAP_MODELS[model])

    @property
    def size(self) -> Tensor:
        """(..., 2) image width and height in pixels."""
        return self._data[..., :2]

    @property
    def f(self) -> Tensor:
        """(..., 2) focal lengths fx, fy in pixels."""
        return self._data[..., 2:4]

    @property
    def c(self) -> Tensor:
        """(..., 2) principal point in pixels (origin at the top-left pixel's centre)."""
        return self._data[..., 4:6]

    @property
    def dist(self) -> Tensor:
        """(..., D) distortion parameters."""
        return self._data[..., 6:]

    def K(self) -> Tensor:
        """(..., 3, 3) calibration matrices (pixel-centre origin)."""
        K = torch.zeros(self.shape + (3, 3), dtype=self.dtype, device=self.device)
        K[..., 0, 0], K[..., 1, 1] = self.f[..., 0], self.f[..., 1]
        K[..., 0, 2], K[..., 1, 2] = self.c[..., 0], self.c[..., 1]
        K[..., 2, 2] = 1
        return K

    def scale(self, scales: Union[float, Tuple[float, float]]) -> "Camera":
        """The camera of the image resized by ``scales`` (new / old, per axis)."""
        if isinstance(scales, (int, float)):
            scales = (scales, scales)
        s = self._data.new_tensor(scales)
        return self._new(torch.cat([self.size * s, self.f * s, (self.c + 0.5) * s - 0.5, self.dist], -1))

    def crop(self, left_top: Tuple[float, float], size: Tuple[int, int]) -> "Camera":
        """The camera of the crop of ``size`` (w, h) starting at pixel ``left_top`` (x, y)."""
        lt = self._data.new_tensor(left_top).expand(self.shape + (2,))
        sz = self._data.new_tensor(size).expand(self.shape + (2,))
        return self._new(torch.cat([sz, self.f, self.c - lt, self.dist], -1))

    def in_image(self, p2d: Tensor) -> Tensor:
        """p2d: (..., N, 2) pixels -> (..., N) inside [0, size - 1]."""
        size = self.size[..., None, :]
        return ((p2d >= 0) & (p2d <= size - 1)).all(-1)

    def project(self, p3d: Tensor) -> Tuple[Tensor, Tensor]:
        """Pinhole projection. p3d: (..., N, 3) camera frame -> (..., N, 2) normalized, (..., N) z > eps."""
        z = p3d[..., -1]
        valid = z > self.eps
        return p3d[..., :-1] / z.clamp(min=self.eps)[..., None], valid

    @cached_property
    def _distortion_terms(self) -> tuple:
        """What the distortion model computes from the parameters alone (the radial models' validity
        limit), once per camera object: the LM projects through the same camera at every iteration."""
        prepare = DISTORTIONS[self.distortion].prepare
        return () if prepare is None else (prepare(self.dist),)

    def distort(self, p: Tensor) -> Tuple[Tensor, Tensor]:
        """p: (..., N, 2) normalized -> distorted (..., N, 2) and model validity (..., N)."""
        return DISTORTIONS[self.distortion].distort(p, self.dist, *self._distortion_terms)

    def J_distort(self, p: Tensor) -> Tensor:
        """(..., N, 2, 2) Jacobian of ``distort`` w.r.t. p."""
        return DISTORTIONS[self.distortion].J_distort(p, self.dist)

    def undistort(self, p: Tensor, num_iters: int = 20) -> Tensor:
        """Inverse of ``distort`` by Newton's method. p: (..., N, 2) distorted normalized."""
        if self.distortion == "none":
            return p
        x = p.clone()
        for _ in range(num_iters):
            fx, _ = self.distort(x)
            J = self.J_distort(x)
            x = x - torch.linalg.solve(J, (fx - p)[..., None])[..., 0]
        return x

    def denormalize(self, p: Tensor) -> Tensor:
        """Normalized (..., N, 2) -> pixels (..., N, 2)."""
        return p * self.f[..., None, :] + self.c[..., None, :]

    def J_denormalize(self) -> Tensor:
        """(..., 1, 2, 2) Jacobian of ``denormalize``."""
        return torch.diag_embed(self.f)[..., None, :, :]

    def normalize(self, p2d: Tensor) -> Tensor:
        """Pixels (..., N, 2) -> normalized (..., N, 2)."""
        return (p2d - self.c[..., None, :]) / self.f[..., None, :]

    def cam2image(self, p3d: Tensor) -> Tuple[Tensor, Tensor]:
        """Camera-frame points (..., N, 3) -> pixels (..., N, 2) and validity (..., N).

        Valid = in front of the camera, inside the distortion model's domain,
        and inside the image. (Official PixLoc: ``world2image``.)
        """
        p, visible = self.project(p3d)
        p, valid_model = self.distort(p)
        p2d = self.denormalize(p)
        return p2d, visible & valid_model & self.in_image(p2d)

    def cam2image_with_J(self, p3d: Tensor) -> Tuple[Tensor, Tensor, Tensor]:
        """``cam2image`` and its Jacobian (..., N, 2, 3) at once, as an LM linearization needs them: the
        projection is shared, and the Jacobian is formed elementwise, J_distort times [I | -p] / z
        scaled by the focal lengths (the depth clamped as ``project`` clamps it)."""
        p, visible = self.project(p3d)
        p_d, valid_model = self.distort(p)
        p2d = self.denormalize(p_d)
        valid = visible & valid_model & self.in_image(p2d)
        scale = (self.f[..., None, :] / p3d[..., -1:].clamp(min=self.eps))[..., None]  # (..., N, 2, 1): f / z per row
        if self.distortion == "none":
            J = torch.cat([torch.diag_embed(scale[..., 0]), -(scale * p[..., None])], -1)
        else:
            J_d = self.J_distort(p)
            J = torch.cat([J_d, -(J_d * p[..., None, :]).sum(-1, keepdim=True)], -1) * scale
        return p2d, valid, J

    def J_cam2image(self, p3d: Tensor) -> Tensor:
        """(..., N, 2, 3) Jacobian of ``cam2image``."""
        return self.cam2image_with_J(p3d)[2]

    def image2cam(self, p2d: Tensor) -> Tensor:
        """Pixels (..., N, 2) -> camera-frame points on the plane z = 1, (..., N, 3)."""
        p = self.undistort(self.normalize(p2d))
        return torch.cat([p, torch.ones_like(p[..., :1])], -1)
