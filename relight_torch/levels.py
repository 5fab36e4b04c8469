"""Coarse levels of a deep framebuffer, for progressive refinement (`relight_torch.progressive`).

A level of stride p (pixels) keeps one shading point per p x p block of pixels: the block's first
sub-sample (top-left), so that the levels nest (every point of stride 2p is a point of stride p)
and the work of a coarse frame is never done again by a finer one. A coarse frame evaluates light
at those points only and brings them to every pixel with the edge-aware upsampler of
`relight_torch.upsample` (guided by the full deep framebuffer: normals, positions, object ids),
whose weights depend on geometry only and are built once per level. The weights are those of
each pixel's first covered sub-sample (not the mean of its sub-samples' weights, as the transfer
method's upsampling takes): a quarter of the work at 2 x 2 supersampling and no merge of entries
(10 s against ~2.5 s per level at 640 x 480 on a loaded 2-core machine), for frames that are
approximations anyway; a pixel that any sub-sample covers counts as covered in them.

A level of stride 32 or more upsamples to blocks of b x b pixels rather than to every pixel
(`Level.block`, b = p / `PIXELS_PER_BLOCK_STRIDE`): each block takes the weights of its first
covered sub-sample and its value is repeated over the block, for large images, where filtering
every pixel is the largest cost of a first frame. The default levels (16 to 1) filter every pixel:
at 640 x 480 blocks at stride 16 saved a fraction of the first frame's time for a visible loss
(edges placed to 2 pixels; docs/PROGRESSIVE.md).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch

from relight_torch.gbuffer import GBuffer
from relight_torch.upsample import EdgeAwareUpsampler, edge_aware_upsampler

PIXELS_PER_BLOCK_STRIDE = 16
"""A level of stride p upsamples to blocks of p / 16 pixels per side (p = 32: 2 x 2 blocks; the
default levels, 16 and finer, to every pixel)."""


@dataclass(frozen=True)
class Level:
    """The points of one coarse level and the map from them to the image.

    Attributes:
        stride: p, pixels per block side.
        points: (M,) int64 G-buffer indices of the covered block corners, ascending.
        upsampler: (M, C) values at `points` -> (H W / b^2, C) values at the image's b x b pixel
            blocks, row-major.
        block: b, pixels per block side (1: every pixel).
        image_size: (H, W) of the image, pixels.
    """

    stride: int
    points: torch.Tensor
    upsampler: EdgeAwareUpsampler
    block: int = 1
    image_size: tuple[int, int] = (0, 0)

    def add_to(self, image: torch.Tensor, blocks: torch.Tensor) -> torch.Tensor:
        """(H, W, C) `image` plus the (H W / b^2, C) values of the blocks, each repeated over its
        block (broadcast, not materialised)."""
        height, width = self.image_size
        b = self.block
        if b == 1:
            return image + blocks.reshape(height, width, -1)
        total = image.reshape(height // b, b, width // b, b, -1) + blocks.reshape(height // b, 1, width // b, 1, -1)
        return total.reshape(height, width, -1)


def level_points(gbuffer: GBuffer, supersampling: int, stride: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(points (M,) G-buffer indices, blocks (M,) coarse pixel row * ceil(W / p) + col) of the
    covered first sub-samples of the p x p pixel blocks, p = `stride`."""
    if stride < 1:
        raise ValueError(f"stride must be >= 1 pixel, got {stride}")
    sub_width = gbuffer.image_size[1]
    step = stride * supersampling
    coarse_width = -(-sub_width // step)
    row = torch.div(gbuffer.pixel_index, sub_width, rounding_mode="floor")
    col = gbuffer.pixel_index % sub_width
    corner = (row % step == 0) & (col % step == 0)
    points = torch.nonzero(corner).squeeze(-1)
    blocks = torch.div(row[points], step, rounding_mode="floor") * coarse_width + torch.div(
        col[points], step, rounding_mode="floor"
    )
    return points, blocks


def build_level(gbuffer: GBuffer, supersampling: int, stride: int) -> Level:
    """The level of stride `stride` pixels of a G-buffer whose pixels have s x s sub-samples."""
    points, blocks = level_points(gbuffer, supersampling, stride)
    height, width = (size // supersampling for size in gbuffer.image_size)
    block = max(1, stride // PIXELS_PER_BLOCK_STRIDE)
    if height % block or width % block:
        block = 1
    upsampler = edge_aware_upsampler(
        pixel_representatives(gbuffer, supersampling * block),
        1,
        stride // block,
        blocks,
        gbuffer.position[points],
        gbuffer.geometric_normal[points],
        gbuffer.object_id[points],
        sample_offset=0.5 / (supersampling * stride) - 0.5,
    )
    return Level(stride, points, upsampler, block, (height, width))


def pixel_representatives(gbuffer: GBuffer, supersampling: int) -> GBuffer:
    """The G-buffer of the (H / s) x (W / s) pixel image whose each covered pixel holds its first
    covered sub-sample (the lowest G-buffer index)."""
    sub_height, sub_width = gbuffer.image_size
    width = sub_width // supersampling
    row = torch.div(gbuffer.pixel_index, sub_width * supersampling, rounding_mode="floor")
    col = torch.div(gbuffer.pixel_index % sub_width, supersampling, rounding_mode="floor")
    pixel = row * width + col
    order = torch.arange(gbuffer.num_samples, device=gbuffer.device)
    first = torch.full((sub_height // supersampling * width,), gbuffer.num_samples, device=gbuffer.device)
    first.scatter_reduce_(0, pixel, order, reduce="amin")
    chosen = first[first < gbuffer.num_samples]
    fields = {}
    for item in dataclasses.fields(gbuffer):
        value = getattr(gbuffer, item.name)
        if item.name == "pixel_index":
            value = pixel.index_select(0, chosen)
        elif item.name == "params":
            value = value.index(chosen)
        elif isinstance(value, torch.Tensor) and item.name != "camera_position":
            value = value.index_select(0, chosen)
        fields[item.name] = value
    fields["image_size"] = (sub_height // supersampling, width)
    return GBuffer(**fields)
