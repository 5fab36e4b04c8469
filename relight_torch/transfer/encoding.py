"""How wavelet row values are stored: float16 or 8-bit, each with a per-row, per-channel scale.

Coefficients of one row span many magnitudes and rows differ by orders of magnitude (a view
sample in a corner against one in the open), so both encodings normalise per row and channel
(the chapter quantises per block with a scale and an offset at the quad's vertices; a row is our
block):

    float16: stored = value / scale,               scale = max |value| of the row's channel
    uint8:   stored = round(255 (value - low) / scale), scale = max - min, low = min

Decoding gives float values again; the relighter decodes once at load time.

On disk (`EncodedRows.arrays`) a matrix is the parts Values, Scale, Low, Indices, Offsets and,
for colour-factored rows, Colour (R, 3) float32. Indices are stored as uint16 when the rows have
at most 65,536 columns (every gather count up to the chapter's 256 x 256), else int32: at
640 x 480 x 100 coefficients this halves the 123 MB the indices took, and they are widened to
int32 (what `embedding_bag` takes) at load time.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from relight_torch.transfer.sparse import SparseRows, entry_rows

ENCODINGS = ("float16", "uint8")
PARTS = ("Values", "Scale", "Low", "Indices", "Offsets", "Colour")


@dataclass(frozen=True)
class EncodedValues:
    """Stored values of R rows.

    Attributes:
        stored: (nnz, C) float16 or uint8.
        scale: (R, C) float32 per-row, per-channel scale.
        low: (R, C) float32 per-row, per-channel offset (zero for float16).
    """

    stored: torch.Tensor
    scale: torch.Tensor
    low: torch.Tensor


def _segment_reduce(
    values: torch.Tensor, row: torch.Tensor, num_rows: int, reduce: str, initial: float
) -> torch.Tensor:
    out = values.new_full((num_rows, values.shape[1]), initial)
    return out.scatter_reduce(0, row.unsqueeze(-1).expand_as(values), values, reduce, include_self=False)


def encode(values: torch.Tensor, offsets: torch.Tensor, encoding: str) -> EncodedValues:
    """Encode (nnz, C) float values of rows laid out by (R + 1,) offsets."""
    if encoding not in ENCODINGS:
        raise ValueError(f"encoding must be one of {ENCODINGS}, got {encoding!r}")
    values = values.float()
    row, num_rows = entry_rows(offsets), offsets.shape[0] - 1
    if encoding == "float16":
        scale = _segment_reduce(values.abs(), row, num_rows, "amax", 0.0)
        scale = torch.where(scale > 0, scale, torch.ones_like(scale))
        return EncodedValues((values / scale[row]).half(), scale, torch.zeros_like(scale))
    low = _segment_reduce(values, row, num_rows, "amin", 0.0)
    high = _segment_reduce(values, row, num_rows, "amax", 0.0)
    scale = torch.where(high > low, high - low, torch.ones_like(high))
    stored = torch.round(255.0 * (values - low[row]) / scale[row]).clamp(0, 255).to(torch.uint8)
    return EncodedValues(stored, scale, low)


def decode(encoded: EncodedValues, offsets: torch.Tensor, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """(nnz, C) values of `dtype` back from their encoding."""
    row = entry_rows(offsets)
    scale, low = encoded.scale.to(dtype), encoded.low.to(dtype)
    if encoded.stored.dtype == torch.uint8:
        return low[row] + scale[row] * (encoded.stored.to(dtype) / 255.0)
    return encoded.stored.to(dtype) * scale[row]


@dataclass(frozen=True)
class EncodedRows:
    """`SparseRows` as stored: encoded values beside the layout (see the module doc).

    Attributes:
        values: the encoded (nnz, C) values.
        indices: (nnz,) int32; offsets: (R + 1,) int64; num_columns: D.
        row_colour: (R, 3) float32 for colour-factored rows, else None.
    """

    values: EncodedValues
    indices: torch.Tensor
    offsets: torch.Tensor
    num_columns: int
    row_colour: torch.Tensor | None = None

    def arrays(self) -> dict[str, np.ndarray]:
        """Payload part name -> array to store (indices narrowed to uint16 where they fit)."""
        index_dtype = np.uint16 if self.num_columns <= 1 << 16 else np.int32
        tensors = {
            "Values": self.values.stored,
            "Scale": self.values.scale,
            "Low": self.values.low,
            "Indices": self.indices,
            "Offsets": self.offsets,
        }
        if self.row_colour is not None:
            tensors["Colour"] = self.row_colour
        arrays = {name: tensor.cpu().numpy() for name, tensor in tensors.items()}
        arrays["Indices"] = arrays["Indices"].astype(index_dtype)
        return arrays

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], num_columns: int) -> EncodedRows:
        """The inverse of `arrays` (Colour optional); indices widened to int32."""
        tensors = {name: torch.from_numpy(np.array(array)) for name, array in arrays.items() if name != "Indices"}
        indices = torch.from_numpy(np.asarray(arrays["Indices"]).astype(np.int32))
        return cls(
            EncodedValues(tensors["Values"], tensors["Scale"], tensors["Low"]),
            indices,
            tensors["Offsets"],
            num_columns,
            tensors.get("Colour"),
        )


def encode_rows(rows: SparseRows, encoding: str) -> EncodedRows:
    """Encode the values of `rows` ('float16' or 'uint8'); the layout and row colours are kept."""
    colour = None if rows.row_colour is None else rows.row_colour.float()
    return EncodedRows(
        encode(rows.values, rows.offsets, encoding), rows.indices, rows.offsets, rows.num_columns, colour
    )


def decode_rows(encoded: EncodedRows, dtype: torch.dtype = torch.float32) -> SparseRows:
    """The `SparseRows` back, values of `dtype` (on the encoded tensors' device)."""
    colour = None if encoded.row_colour is None else encoded.row_colour.to(dtype)
    return SparseRows(
        decode(encoded.values, encoded.offsets, dtype), encoded.indices, encoded.offsets, encoded.num_columns, colour
    )
