"""The base of every BRDF's parameter dataclass: frozen, tensors only, one row per shading point.

A subclass declares its fields with `colour()` ((N, 3) linear RGB), `scalar()` ((N,)) or
`flag()` ((N,) bool); all fields share the same rows (N, or any row shape, () for one value).
Rows broadcast against the batch axes of the directions: params of N rows shade directions
(N, 3); for S directions per point, (N, S, 3), use `params.with_sample_axis()`, whose rows are
(N, 1).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, Self

import numpy as np
import torch

_CHANNELS = "channels"


def colour() -> Any:
    """Field of (N, 3) linear RGB values.

    Typed `Any`, as `dataclasses.field` itself is, so that `rho: torch.Tensor = colour()` type-checks.
    """
    return dataclasses.field(metadata={_CHANNELS: 3})


def scalar() -> Any:
    """Field of (N,) floating values."""
    return dataclasses.field(metadata={_CHANNELS: 0})


def flag() -> Any:
    """Field of (N,) booleans (never cast by `.to(dtype=...)`)."""
    return dataclasses.field(metadata={_CHANNELS: 0, "bool": True})


@dataclasses.dataclass(frozen=True)
class BrdfParams:
    """Frozen dataclass of tensors with a shared row axis; see the module docstring."""

    def __post_init__(self) -> None:
        row_shape = None
        for item in dataclasses.fields(self):
            value = getattr(self, item.name)
            name = f"{type(self).__name__}.{item.name}"
            if not isinstance(value, torch.Tensor):
                raise ValueError(f"{name} must be a torch.Tensor; got {type(value).__name__}")
            channels = item.metadata[_CHANNELS]
            if channels and (value.dim() < 1 or value.shape[-1] != channels):
                raise ValueError(f"{name} must have shape (N, {channels}); got {tuple(value.shape)}")
            rows = value.shape[:-1] if channels else value.shape
            if row_shape is None:
                row_shape = rows
            elif rows != row_shape:
                raise ValueError(f"{name} has rows {tuple(rows)}; the fields before it have {tuple(row_shape)}")

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> Self:
        """Copy onto `device`, casting floating fields to `dtype` (boolean fields keep theirs)."""
        changes = {}
        for item in dataclasses.fields(self):
            value = getattr(self, item.name)
            changes[item.name] = value.to(device=device, dtype=None if item.metadata.get("bool") else dtype)
        return dataclasses.replace(self, **changes)

    def index(self, rows: torch.Tensor | slice) -> Self:
        """The rows selected by a boolean mask (N,) or an index tensor / slice."""
        if isinstance(rows, torch.Tensor) and rows.dtype != torch.bool:
            # index_select: the advanced index of a few rows of a large tensor is ~100x slower on the CPU.
            return dataclasses.replace(
                self, **{f.name: getattr(self, f.name).index_select(0, rows) for f in dataclasses.fields(self)}
            )
        return dataclasses.replace(self, **{f.name: getattr(self, f.name)[rows] for f in dataclasses.fields(self)})

    def with_sample_axis(self) -> Self:
        """The same parameters with rows (N, 1), to shade directions (N, S, 3)."""
        fields = dataclasses.fields(self)
        return dataclasses.replace(self, **{f.name: _insert_axis(getattr(self, f.name), f) for f in fields})

    @classmethod
    def zeros(cls, rows: int) -> Self:
        """`rows` rows of zeros (False for boolean fields), float32, on the CPU."""
        return cls(
            **{
                item.name: torch.zeros(
                    (rows, item.metadata[_CHANNELS]) if item.metadata[_CHANNELS] else (rows,),
                    dtype=torch.bool if item.metadata.get("bool") else torch.float32,
                )
                for item in dataclasses.fields(cls)
            }
        )

    @classmethod
    def from_numpy(
        cls,
        arrays: Mapping[str, np.ndarray],
        device: torch.device | str | None = None,
        dtype: torch.dtype = torch.float32,
    ) -> Self:
        """Build from a dict of numpy arrays keyed by field name; other keys are ignored.

        Raises:
            ValueError: a field is missing or has the wrong shape.
        """
        values = {}
        for item in dataclasses.fields(cls):
            if item.name not in arrays:
                raise ValueError(f"{cls.__name__}.from_numpy: missing array {item.name!r}")
            field_dtype = torch.bool if item.metadata.get("bool") else dtype
            values[item.name] = torch.as_tensor(np.asarray(arrays[item.name]), device=device).to(field_dtype)
        return cls(**values)


def _insert_axis(value: torch.Tensor, item: dataclasses.Field[Any]) -> torch.Tensor:
    return value.unsqueeze(-2) if item.metadata[_CHANNELS] else value.unsqueeze(-1)
