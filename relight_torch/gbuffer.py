"""The deep framebuffer as the relighter holds it: covered sub-samples as flat tensors.

Only covered sub-samples are kept (N of them); `pixel_index` scatters them back into the
(H, W) sub-sample image. All tensors share one device; geometry is float32 world space.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
import torch

from relight_torch.brdf.preview_surface import PreviewSurfaceParams


@dataclass(frozen=True)
class GBuffer:
    """N covered sub-samples of an (H, W) sub-sample image.

    Attributes:
        image_size: (H, W) of the sub-sample image.
        pixel_index: (N,) int64 flat index (row * W + col) of each sub-sample.
        position: (N, 3) world position.
        normal, tangent, bitangent: (N, 3) unit shading frame (normal map applied).
        geometric_normal: (N, 3) unit, on the camera's side.
        params: UsdPreviewSurface parameters per sub-sample.
        material_id, object_id: (N,) int32.
        depth: (N,) distance along the camera's viewing axis.
        camera_position: (3,) world position of the camera.
    """

    image_size: tuple[int, int]
    pixel_index: torch.Tensor
    position: torch.Tensor
    normal: torch.Tensor
    tangent: torch.Tensor
    bitangent: torch.Tensor
    geometric_normal: torch.Tensor
    params: PreviewSurfaceParams
    material_id: torch.Tensor
    object_id: torch.Tensor
    depth: torch.Tensor
    camera_position: torch.Tensor

    @property
    def num_samples(self) -> int:
        return int(self.pixel_index.shape[0])

    @property
    def device(self) -> torch.device:
        return self.position.device

    def wo_world(self) -> torch.Tensor:
        """(N, 3) unit directions from each sample towards the camera."""
        return torch.nn.functional.normalize(self.camera_position - self.position, dim=-1)

    def to(self, device: torch.device | str, dtype: torch.dtype = torch.float32) -> GBuffer:
        """Move to `device`; floating tensors to `dtype`, integer tensors keep theirs."""
        moved = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, torch.Tensor):
                value = value.to(device, dtype) if value.is_floating_point() else value.to(device)
            elif isinstance(value, PreviewSurfaceParams):
                value = value.to(device, dtype)
            moved[f.name] = value
        return GBuffer(**moved)

    @staticmethod
    def from_numpy(
        image_size: tuple[int, int],
        pixel_index: np.ndarray,
        params: PreviewSurfaceParams,
        camera_position: np.ndarray,
        **arrays: np.ndarray,
    ) -> GBuffer:
        """Build from numpy arrays named as the fields (position, normal, ..., depth)."""
        tensors = {name: torch.from_numpy(np.ascontiguousarray(a)) for name, a in arrays.items()}
        return GBuffer(
            image_size=(int(image_size[0]), int(image_size[1])),
            pixel_index=torch.from_numpy(np.asarray(pixel_index, np.int64)),
            params=params,
            camera_position=torch.from_numpy(np.asarray(camera_position, np.float32)),
            **tensors,
        )

    def scatter(self, values: torch.Tensor, background: float = 0.0) -> torch.Tensor:
        """Place per-sample values (N, C) into the sub-sample image (H, W, C)."""
        return scatter_points(self.image_size, self.pixel_index, values, background)


def scatter_points(
    image_size: tuple[int, int], pixel_index: torch.Tensor, values: torch.Tensor, background: float = 0.0
) -> torch.Tensor:
    """Place per-point values (N, C) at their flat `pixel_index` (N,) of an (H, W, C) image."""
    height, width = image_size
    image = values.new_full((height * width, values.shape[-1]), background)
    image.index_copy_(0, pixel_index, values)  # on the CPU 2-3x faster than image[index] = values
    return image.reshape(height, width, values.shape[-1])
