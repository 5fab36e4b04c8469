"""Whether a ray hit is opaque: UsdPreviewSurface `opacity` and `opacityThreshold` at the hit's uv.

One function, `OpacityTable.opacity` (and `OpacityTable.present` on top of it), answers for
everything that traces or rasterises: the baker's and the reference's camera, path and shadow rays
(`relight_torch.visibility.embree.EmbreeCaster`, which `pipeline.tracing.Tracer` is), the
relighter's Embree shadow rays over a cache's occluders, and the torch shadow maps
(`relight_torch.visibility.raster`). The table is built from a scene's materials by
`pipeline.scene.opacity.scene_opacity` and stored in a cache beside the occluders
(`to_arrays` / `from_arrays`).

Semantics (Storm's, UsdPreviewSurface 2.5):
    * opacity is the material's constant or its texture's sample (bilinear, the texture's wrap
      modes, scale and bias: `relight_torch.math.texture.sample_bilinear`, the sampler the
      material evaluation uses too),
      clamped to [0, 1];
    * opacityThreshold > 0 makes a cut-out: opacity < threshold is a hole (0), anything else 1;
    * a partial opacity a in (0, 1) is stochastic presence: the hit is there for a fraction a of
      the rays (a hash of the ray and the triangle, `presence_random`, so it is deterministic and
      independent of batching), and the rest continue behind it unrefracted. Averaged over rays
      this is alpha compositing ('presence' mode exactly). For opacityMode 'transparent' Storm also
      keeps the specular lobe of the missing fraction (clear glass keeps its highlights): that
      part is not modelled (the mode is read and treated as 'presence').
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from relight_torch.math.texture import WRAP_MODES, sample_bilinear

OPACITY_MODES = ("transparent", "presence")
# The cache payloads of a table (`OpacityTable.to_arrays`), the first one naming it.
OPACITY_PAYLOADS = ("opacityTriangles", "opacityUvs", "opacityMaps", "opacityTexels")
# Columns of the (M, _MAP_COLUMNS) float64 map table a cache stores (`to_arrays`).
_MAP_COLUMNS = 16


def cut_out(opacity, threshold: float):
    """Opacity (numpy or torch, any shape) clamped to [0, 1], then Storm's cut-out: where
    `threshold` > 0, 1 for opacity >= threshold and 0 below it."""
    opacity = opacity.clip(0.0, 1.0)
    if threshold > 0.0:
        return (
            (opacity >= threshold).astype(np.float32)
            if isinstance(opacity, np.ndarray)
            else (opacity >= threshold).to(opacity.dtype)
        )
    return opacity


@dataclass(frozen=True)
class OpacityMap:
    """One material's opacity: a constant, or one channel of a texture.

    Attributes:
        constant: the opacity where there is no texture.
        threshold: opacityThreshold (0: no cut-out).
        mode: opacityMode, one of `OPACITY_MODES`.
        texels: (H, W) float32 channel of the image the opacity input reads (row 0 the top), or None.
        wrap_s, wrap_t: the texture's wrap modes.
        scale, bias: opacity = sample * scale + bias.
        st_from_uv: (2, 3) float64 affine map from the triangles' uvs to the texture's st, or
            None for the identity.
    """

    constant: float
    threshold: float = 0.0
    mode: str = "transparent"
    texels: torch.Tensor | None = None
    wrap_s: str = "repeat"
    wrap_t: str = "repeat"
    scale: float = 1.0
    bias: float = 0.0
    st_from_uv: torch.Tensor | None = None

    def opaque(self) -> bool:
        """Whether every point with this material is opaque (no lookup needed)."""
        return self.texels is None and float(cut_out(torch.tensor(self.constant), self.threshold)) >= 1.0

    def evaluate(self, uv: torch.Tensor) -> torch.Tensor:
        """(N,) float32 opacity in [0, 1], cut-out applied, at (N, 2) uvs."""
        if self.texels is None:
            value = torch.full(uv.shape[:1], self.constant, dtype=torch.float32, device=uv.device)
        else:
            st = uv.to(torch.float64)
            if self.st_from_uv is not None:
                st_from_uv = self.st_from_uv.to(uv.device, torch.float64)
                st = st @ st_from_uv[:, :2].T + st_from_uv[:, 2]
            texels = self.texels.to(uv.device)
            value = sample_bilinear(texels[..., None], st, self.wrap_s, self.wrap_t)[:, 0] * self.scale + self.bias
        return cut_out(value.to(torch.float32), self.threshold)


@dataclass(frozen=True)
class OpacityTable:
    """The non-opaque triangles of a soup and their opacity maps.

    Attributes:
        triangles: (K,) int64 sorted ids of the triangles that are not opaque everywhere.
        map_index: (K,) int64 index into `maps` of each.
        uvs: (K, 3, 2) float32 the triangles' corner uvs (the primvar their textures read).
        maps: the opacity maps.
    """

    triangles: torch.Tensor
    map_index: torch.Tensor
    uvs: torch.Tensor
    maps: tuple[OpacityMap, ...]

    @property
    def num_triangles(self) -> int:
        return int(self.triangles.shape[0])

    def transparent_mask(self, num_triangles: int) -> np.ndarray:
        """(T,) bool over a soup of T triangles: True for the triangles that may let light through."""
        mask = np.zeros(num_triangles, bool)
        mask[self.triangles.numpy()] = True
        return mask

    def opacity(self, triangle_id: torch.Tensor, barycentrics: torch.Tensor) -> torch.Tensor:
        """Opacity at ray hits: the one 'is this hit opaque' lookup everything shares.

        Args:
            triangle_id: (N,) long ids into the soup (-1, a miss, and triangles not in the table
                are opaque).
            barycentrics: (N, 2) Embree (u, v) of the hits (weights of corners 1 and 2).

        Returns:
            (N,) float32 opacity in [0, 1] (cut-outs are 0 or 1), on `barycentrics`' device.
        """
        device = barycentrics.device
        result = torch.ones(triangle_id.shape[0], dtype=torch.float32, device=device)
        triangles = self.triangles.to(device)
        if triangles.numel() == 0 or triangle_id.numel() == 0:
            return result
        slot = torch.searchsorted(triangles, triangle_id.long()).clamp(max=triangles.numel() - 1)
        listed = triangles[slot] == triangle_id
        rows, slot = torch.nonzero(listed).squeeze(1), slot[listed]
        b = barycentrics[rows].to(torch.float32)
        weights = torch.stack([1.0 - b[:, 0] - b[:, 1], b[:, 0], b[:, 1]], dim=-1)
        uv = torch.einsum("nc,nck->nk", weights, self.uvs.to(device)[slot])
        map_index = self.map_index.to(device)[slot]
        for index in torch.unique(map_index).tolist():
            mine = map_index == index
            result[rows[mine]] = self.maps[index].evaluate(uv[mine])
        return result

    def present(self, triangle_id: torch.Tensor, barycentrics: torch.Tensor, random: torch.Tensor) -> torch.Tensor:
        """(N,) bool: whether each hit stops its ray (stochastic presence: random < opacity).

        Args:
            triangle_id, barycentrics: as `opacity`.
            random: (N,) uniform numbers in [0, 1) (`presence_random`).
        """
        return random < self.opacity(triangle_id, barycentrics)

    def subset(self, keep: np.ndarray) -> OpacityTable:
        """The table of the sub-soup of triangles where the (T,) bool `keep` holds, renumbered."""
        new_id = np.cumsum(keep) - 1
        triangles = self.triangles.numpy()
        kept = keep[triangles]
        return OpacityTable(
            torch.from_numpy(new_id[triangles[kept]].astype(np.int64)),
            self.map_index[torch.from_numpy(kept)],
            self.uvs[torch.from_numpy(kept)],
            self.maps,
        )

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The table as plain arrays for a cache (no pickling): 'opacityTriangles' (K, 2) int32
        [triangle, map]; 'opacityUvs' (K, 3, 2) float32; 'opacityMaps' (M, 16) float64 [constant,
        threshold, mode, scale, bias, wrap_s, wrap_t, height, width, texel offset, st_from_uv (6)];
        'opacityTexels' (sum H W,) float32."""
        rows, texels, offset = [], [], 0
        for opacity_map in self.maps:
            height, width = (0, 0) if opacity_map.texels is None else opacity_map.texels.shape
            st = (
                torch.tensor([[1.0, 0, 0], [0, 1.0, 0]], dtype=torch.float64)
                if opacity_map.st_from_uv is None
                else opacity_map.st_from_uv
            )
            rows.append(
                [
                    opacity_map.constant,
                    opacity_map.threshold,
                    OPACITY_MODES.index(opacity_map.mode),
                    opacity_map.scale,
                    opacity_map.bias,
                    WRAP_MODES.index(opacity_map.wrap_s),
                    WRAP_MODES.index(opacity_map.wrap_t),
                    height,
                    width,
                    offset,
                    *st.reshape(-1).tolist(),
                ]
            )
            if opacity_map.texels is not None:
                texels.append(opacity_map.texels.reshape(-1).numpy())
                offset += height * width
        return {
            "opacityTriangles": np.stack([self.triangles.numpy(), self.map_index.numpy()], -1).astype(np.int32),
            "opacityUvs": self.uvs.numpy().astype(np.float32),
            "opacityMaps": np.array(rows, np.float64).reshape(-1, _MAP_COLUMNS),
            "opacityTexels": np.concatenate(texels).astype(np.float32) if texels else np.zeros(0, np.float32),
        }

    @staticmethod
    def from_arrays(arrays: dict[str, np.ndarray]) -> OpacityTable:
        """The table `to_arrays` wrote.

        Raises:
            ValueError: an array of the wrong shape, or an index out of range.
        """
        pairs, uvs = np.asarray(arrays["opacityTriangles"]), np.asarray(arrays["opacityUvs"], np.float32)
        rows, texels = np.asarray(arrays["opacityMaps"], np.float64), np.asarray(arrays["opacityTexels"], np.float32)
        if pairs.ndim != 2 or pairs.shape[1] != 2 or uvs.shape != (pairs.shape[0], 3, 2):
            raise ValueError(f"opacity tables must be (K, 2) and (K, 3, 2), got {pairs.shape} and {uvs.shape}")
        if rows.ndim != 2 or rows.shape[1] != _MAP_COLUMNS:
            raise ValueError(f"opacityMaps must be (M, {_MAP_COLUMNS}), got {rows.shape}")
        maps = []
        for row in rows:
            height, width, offset = int(row[7]), int(row[8]), int(row[9])
            if offset < 0 or offset + height * width > texels.size:
                raise ValueError(f"opacity texels [{offset}, {offset + height * width}) outside {texels.size}")
            texture = (
                torch.from_numpy(texels[offset : offset + height * width].reshape(height, width).copy())
                if height * width
                else None
            )
            maps.append(
                OpacityMap(
                    float(row[0]),
                    float(row[1]),
                    OPACITY_MODES[int(row[2])],
                    texture,
                    WRAP_MODES[int(row[5])],
                    WRAP_MODES[int(row[6])],
                    float(row[3]),
                    float(row[4]),
                    torch.from_numpy(row[10:16].reshape(2, 3).copy()),
                )
            )
        if pairs.size and (pairs[:, 1].min() < 0 or pairs[:, 1].max() >= len(maps) or pairs[:, 0].min() < 0):
            raise ValueError("opacityTriangles names a negative triangle or a missing map")
        return OpacityTable(
            torch.from_numpy(pairs[:, 0].astype(np.int64)),
            torch.from_numpy(pairs[:, 1].astype(np.int64)),
            torch.from_numpy(uvs.copy()),
            tuple(maps),
        )


def presence_random(keys: torch.Tensor) -> torch.Tensor:
    """(N,) float32 uniform numbers in [0, 1) from (N, K) int64 keys (each < 2^32): a hash, so that
    the same ray meeting the same triangle always decides the same way, whatever the batching.

    The keys are mixed by a 32-bit multiply-xorshift (the finaliser of Murmur3, Appleby 2008),
    with products kept below 2^63 so that int64 arithmetic does not overflow.
    """
    state = torch.full(keys.shape[:1], 0x9E3779B9, dtype=torch.int64, device=keys.device)
    for column in range(keys.shape[1]):
        state = _mix32(state ^ (keys[:, column] & 0xFFFFFFFF))
    return (state >> 8).to(torch.float32) / float(1 << 24)


def _mix32(x: torch.Tensor) -> torch.Tensor:
    """Murmur3's fmix32 on values in [0, 2^32), as int64; multiplies split in 16-bit halves."""
    x = x ^ (x >> 16)
    x = _multiply32(x, 0x85EBCA6B)
    x = x ^ (x >> 13)
    x = _multiply32(x, 0xC2B2AE35)
    return x ^ (x >> 16)


def _multiply32(x: torch.Tensor, constant: int) -> torch.Tensor:
    """(x * constant) mod 2^32 for x, constant in [0, 2^32) without leaving int64's range."""
    low, high = constant & 0xFFFF, constant >> 16
    return ((x * low) + (((x * high) & 0xFFFF) << 16)) & 0xFFFFFFFF


def ray_keys(origins: np.ndarray, directions: np.ndarray, triangle_id: np.ndarray) -> torch.Tensor:
    """(N, 7) int64 hash keys of rays (float32 (N, 3) origins and directions, their bits) and the
    (N,) triangles they hit, for `presence_random`."""
    bits = np.concatenate(
        [
            np.ascontiguousarray(origins, np.float32).view(np.uint32),
            np.ascontiguousarray(directions, np.float32).view(np.uint32),
            np.asarray(triangle_id, np.int64).astype(np.uint32)[:, None],
        ],
        axis=1,
    )
    return torch.from_numpy(bits.astype(np.int64))
