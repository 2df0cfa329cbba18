"""Base class for batched tensor records (poses, cameras)."""

from typing import Sequence

import torch
from torch import Tensor


class TensorWrapper:
    """A tensor of shape (..., D) seen as a batch of objects of shape (...)."""

    def __init__(self, data: Tensor):
        if not isinstance(data, Tensor):
            raise TypeError(f"{type(self).__name__} expects a torch.Tensor, got {type(data).__name__}.")
        if not data.is_floating_point():
            raise TypeError(f"{type(self).__name__} expects a floating-point tensor, got {data.dtype}.")
        self._data = data

    @property
    def data(self) -> Tensor:
        return self._data

    @property
    def shape(self) -> torch.Size:
        return self._data.shape[:-1]

    @property
    def device(self) -> torch.device:
        return self._data.device

    @property
    def dtype(self) -> torch.dtype:
        return self._data.dtype

    def _new(self, data: Tensor):
        """A new object of the same class (and metadata) around other data."""
        return type(self)(data)

    def __getitem__(self, index):
        if not isinstance(index, tuple):
            index = (index,)
        return self._new(self._data[index + (slice(None),)])

    def __len__(self) -> int:
        return self._data.shape[0]

    def to(self, *args, **kwargs):
        return self._new(self._data.to(*args, **kwargs))

    def cpu(self):
        return self._new(self._data.cpu())

    def float(self):
        return self._new(self._data.float())

    def double(self):
        return self._new(self._data.double())

    def detach(self):
        return self._new(self._data.detach())

    def reshape(self, *shape):
        return self._new(self._data.reshape(*shape, self._data.shape[-1]))

    def unsqueeze(self, dim: int):
        return self._new(self._data.unsqueeze(dim - 1 if dim < 0 else dim))  # skip the data dim

    def expand(self, *shape):
        return self._new(self._data.expand(*shape, self._data.shape[-1]))

    @classmethod
    def stack(cls, objects: Sequence["TensorWrapper"], dim: int = 0):
        if dim < 0:
            dim -= 1  # skip the data dimension
        return objects[0]._new(torch.stack([o._data for o in objects], dim=dim))

    @classmethod
    def cat(cls, objects: Sequence["TensorWrapper"], dim: int = 0):
        """Concatenate along a batch dimension; the result keeps the first object's kind."""
        if dim < 0:
            dim -= 1  # skip the data dimension
        return objects[0]._new(torch.cat([o._data for o in objects], dim=dim))

    def isfinite(self) -> Tensor:
        """(...) True where every parameter is finite."""
        return torch.isfinite(self._data).all(-1)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(shape={tuple(self.shape)}, dtype={self.dtype}, device={self.device})"
