"""Edge-aware upsampling of an image computed at a reduced resolution.

Indirect light is smooth over a surface but not across edges, so the F rows of a transfer cache
may be baked for the pixel centres of a coarse image (`--indirect-scale s`: (H / s) x (W / s))
and brought back to the full image by a joint bilateral filter guided by the full-resolution deep
framebuffer (the chapter upsamples its indirect image to the direct one's resolution the same
way, "while trying to avoid light leaking across the edges"). Each sub-sample of the direct
relighter's G-buffer takes the coarse samples of the 3 x 3 coarse pixels around it, weighted by

    spatial   max(0, 1 - d / 1.5) in both axes, d in coarse pixels (a tent, wider than bilinear so
              that an edge pixel still finds a neighbour on its own surface)
    range     on the sub-sample's object: max(0, n_f . n_c) ^ NORMAL_EXPONENT (geometric normals)
              times exp(-(sin / PLANE_SIN)^2), sin = |(x_c - x_f) . n_f| / |x_c - x_f| (how far
              the coarse point lies off the sub-sample's tangent plane, scale-free: 0 on a flat
              surface); on another object 0; plus FOREIGN_WEIGHT everywhere, a fallback that
              matters only where no neighbour lies on the sub-sample's own surface

normalised per sub-sample, then averaged over each pixel's sub-samples like the direct image. The
weights depend on geometry only: they are built once per cache as a sparse (pixels x coarse rows)
matrix, and upsampling an image is one `embedding_bag` over it.

The transfer method upsamples its indirect image with it; progressive refinement
(`relight_torch.progressive`) its coarse frames, whose samples sit at a corner of their coarse
pixel rather than its centre (`sample_offset`) so that the coarse levels nest.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from relight_torch.gbuffer import GBuffer

FOREIGN_WEIGHT = 1e-3
NORMAL_EXPONENT = 8.0
PLANE_SIN = 0.25
SPATIAL_RADIUS = 1.5


@dataclass(frozen=True)
class EdgeAwareUpsampler:
    """A fixed sparse map from coarse rows to the pixels of the full image.

    Attributes:
        rows: (nnz,) int64 coarse row of each weight, grouped by pixel.
        weights: (nnz,) float weight.
        offsets: (P + 1,) int64: pixel p (row * W + col of the full image) takes entries
            offsets[p] : offsets[p + 1] (none for a pixel no sub-sample covers).
    """

    rows: torch.Tensor
    weights: torch.Tensor
    offsets: torch.Tensor

    def __call__(self, coarse: torch.Tensor) -> torch.Tensor:
        """(R, C) values at the coarse rows -> (P, C) values at the full image's pixels."""
        return torch.nn.functional.embedding_bag(
            self.rows,
            coarse,
            self.offsets,
            mode="sum",
            per_sample_weights=self.weights.to(coarse.dtype),
            include_last_offset=True,
        )


def edge_aware_upsampler(
    fine: GBuffer,
    supersampling: int,
    scale: int,
    coarse_pixels: torch.Tensor,
    coarse_position: torch.Tensor,
    coarse_normal: torch.Tensor,
    coarse_object: torch.Tensor,
    guided: bool = True,
    chunk_samples: int = 1 << 18,
    sample_offset: float = 0.0,
) -> EdgeAwareUpsampler:
    """The upsampler from R coarse samples to the pixels of `fine`'s image.

    Args:
        fine: the direct relighter's G-buffer ((H s_d) x (W s_d) sub-samples).
        supersampling: s_d, its sub-samples per pixel side.
        scale: s, full pixels per coarse pixel side; the coarse image is ceil(H / s) x ceil(W / s).
        coarse_pixels: (R,) int64 coarse pixel (row * (W / s) + col) of each coarse sample.
        coarse_position, coarse_normal: (R, 3) world position and unit geometric normal.
        coarse_object: (R,) int object id.
        guided: False drops the range weights (a plain tent filter, for comparison).
        chunk_samples: sub-samples weighed together (bounds the (chunk, 9, 3) temporaries).
        sample_offset: where each coarse sample lies from its coarse pixel's centre, in coarse
            pixels along both axes (0: at the centre; 0.5 / (s s_d) - 0.5: at the pixel's first
            sub-sample).
    """
    device = fine.device
    sub_height, sub_width = fine.image_size
    height, width = sub_height // supersampling, sub_width // supersampling
    coarse_height, coarse_width = -(-height // scale), -(-width // scale)
    num_rows = coarse_pixels.shape[0]
    if num_rows == 0:  # no coarse sample (a coarse level whose block corners are all uncovered): zeros
        empty = torch.zeros(0, dtype=torch.int64, device=device)
        offsets = torch.zeros(height * width + 1, dtype=torch.int64, device=device)
        return EdgeAwareUpsampler(empty, empty.to(fine.position.dtype), offsets)
    row_of_pixel = torch.full((coarse_height * coarse_width,), -1, dtype=torch.int64, device=device)
    row_of_pixel[coarse_pixels.to(device)] = torch.arange(num_rows, device=device)
    coarse = (coarse_position.to(fine.position), coarse_normal.to(fine.position), coarse_object.to(device))
    keys, weights = [], []
    for start in range(0, fine.num_samples, chunk_samples):
        chunk = slice(start, start + chunk_samples)
        coarse_size = (coarse_height, coarse_width)
        rows, weight = _weights(
            fine, chunk, supersampling, scale, coarse_size, row_of_pixel, coarse, guided, sample_offset
        )
        sub_row = torch.div(fine.pixel_index[chunk], sub_width, rounding_mode="floor")
        sub_col = fine.pixel_index[chunk] % sub_width
        pixel = torch.div(sub_row, supersampling, rounding_mode="floor") * width + torch.div(
            sub_col, supersampling, rounding_mode="floor"
        )
        keep = weight > 0
        keys.append(pixel.unsqueeze(1).expand_as(rows)[keep] * num_rows + rows[keep])
        weights.append(weight[keep])
    keys_all = torch.cat(keys)
    if supersampling == 1 and bool((fine.pixel_index[1:] > fine.pixel_index[:-1]).all()):
        # One sample per pixel, in pixel order: the entries are grouped by pixel already (a coarse
        # row named twice, at a clamped border, is summed twice by the product: the same sum).
        counts = torch.bincount(torch.div(keys_all, num_rows, rounding_mode="floor"), minlength=height * width)
        offsets = torch.zeros(height * width + 1, dtype=torch.int64, device=device)
        offsets[1:] = counts.cumsum(0)
        return EdgeAwareUpsampler(keys_all % num_rows, torch.cat(weights), offsets)
    # Merge the entries of a pixel (its sub-samples) that name the same coarse row.
    unique, inverse = torch.unique(keys_all, return_inverse=True)
    merged = torch.zeros(unique.shape[0], dtype=fine.position.dtype, device=device).index_add_(
        0, inverse, torch.cat(weights)
    )
    counts = torch.bincount(torch.div(unique, num_rows, rounding_mode="floor"), minlength=height * width)
    offsets = torch.zeros(height * width + 1, dtype=torch.int64, device=device)
    offsets[1:] = counts.cumsum(0)
    return EdgeAwareUpsampler(unique % num_rows, merged, offsets)


def _weights(
    fine: GBuffer,
    chunk: slice,
    supersampling: int,
    scale: int,
    coarse_size: tuple[int, int],
    row_of_pixel: torch.Tensor,
    coarse: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
    guided: bool,
    sample_offset: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """(rows (n, 9) int64, weights (n, 9)) of the sub-samples `chunk`: the coarse rows of the 3 x 3
    coarse pixels around each and their weights (see the module doc), each sub-sample's summing to
    1 / supersampling^2 (0 where no coarse pixel around it is covered)."""
    coarse_height, coarse_width = coarse_size
    sub_width = fine.image_size[1]
    index = fine.pixel_index[chunk]
    # Sub-sample centres in coarse pixel units (coarse samples at integers).
    step = 1.0 / (supersampling * scale)
    y = (torch.div(index, sub_width, rounding_mode="floor") + 0.5) * step - 0.5 - sample_offset
    x = (index % sub_width + 0.5) * step - 0.5 - sample_offset
    around = torch.tensor([-1, 0, 1], device=index.device)
    cy = (y.round().long().unsqueeze(1) + around.repeat_interleave(3)).clamp(0, coarse_height - 1)
    cx = (x.round().long().unsqueeze(1) + around.repeat(3)).clamp(0, coarse_width - 1)
    spatial = (1 - (cy - y.unsqueeze(1)).abs() / SPATIAL_RADIUS).clamp(min=0) * (
        1 - (cx - x.unsqueeze(1)).abs() / SPATIAL_RADIUS
    ).clamp(min=0)
    rows = row_of_pixel[cy * coarse_width + cx]
    covered = rows >= 0
    rows = rows.clamp(min=0)
    position, normal, object_id = (values[rows] for values in coarse)
    fine_normal = fine.geometric_normal[chunk].unsqueeze(1)
    normal_weight = (normal * fine_normal).sum(-1).clamp(min=0) ** NORMAL_EXPONENT
    offset = position - fine.position[chunk].unsqueeze(1)
    off_plane = (offset * fine_normal).sum(-1).abs() / offset.norm(dim=-1).clamp(min=1e-12)
    plane_weight = torch.exp(-((off_plane / PLANE_SIN) ** 2))
    same_object = object_id == fine.object_id[chunk].unsqueeze(1)
    range_weight = torch.where(same_object, normal_weight * plane_weight, 0.0) + FOREIGN_WEIGHT if guided else 1.0
    weight = spatial * covered * range_weight
    total = weight.sum(1, keepdim=True)
    return rows, torch.where(total > 0, weight / total.clamp(min=1e-30), 0.0) / supersampling**2
