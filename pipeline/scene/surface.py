"""Bake-time evaluation of materials at surface points, and the tangent frames normal maps need.

`evaluate_materials` turns (material id, uv) per shading point into the per-point UsdPreviewSurface
parameters the relighter edits (the field names of `relight_torch.brdf.preview_surface.
PreviewSurfaceParams`), sampling textures once here so that nothing downstream sees a texture.

Tangent frame convention (the normal map's tangent space, OpenGL / UsdPreviewSurface style): t is
dP/du orthogonalised against the normal, b = cross(n, t), so (t, b, n) is right-handed and b points
along +dP/dv when the uv layout is not mirrored (mirrored islands would need a per-triangle sign,
which the soup does not carry). A normal-map value (x, y, z) maps to t*x + b*y + n*z.
"""

from __future__ import annotations

import numpy as np

from pipeline.scene.textures import fit_channels, sample_texture, select_output
from pipeline.scene.types import Material, MaterialInput
from relight_torch.visibility.opacity import cut_out

# Output key -> (Material field, channels). 'normal_tangent' is the tangent-space normal map value.
_TEXTURED_FIELDS = {
    "diffuse_color": ("diffuse_color", 3),
    "emissive_color": ("emissive_color", 3),
    "specular_color": ("specular_color", 3),
    "metallic": ("metallic", 1),
    "roughness": ("roughness", 1),
    "clearcoat": ("clearcoat", 1),
    "clearcoat_roughness": ("clearcoat_roughness", 1),
    "ior": ("ior", 1),
    "opacity": ("opacity", 1),
    "normal_tangent": ("normal", 3),
}
# Triangles per chunk of `triangle_tangents`.
_TANGENT_CHUNK = 1 << 18
# Below this squared length a vector is treated as zero (float32 unit-vector arithmetic).
_DEGENERATE_SQUARED = 1e-12


def _evaluate_input(material_input: MaterialInput, uvs: np.ndarray, num_channels: int) -> np.ndarray:
    """(M, C) values of one input at M points: the texture sample, else the broadcast constant."""
    if material_input.texture is None:
        return np.broadcast_to(fit_channels(material_input.value, num_channels), (uvs.shape[0], num_channels))
    rgba = sample_texture(material_input.texture, uvs)
    return fit_channels(select_output(rgba, material_input.texture.output), num_channels)


def evaluate_materials(materials: list[Material], material_ids: np.ndarray, uvs: np.ndarray) -> dict[str, np.ndarray]:
    """Evaluate every material input at its points.

    Args:
        materials: the scene's materials.
        material_ids: (N,) int index into `materials` per point.
        uvs: (N, 2) 'st' texture coordinates per point.

    Returns:
        float32 arrays: diffuse_color, emissive_color, specular_color (N, 3); metallic, roughness,
        clearcoat, clearcoat_roughness, ior, opacity (N,); use_specular_workflow (N,) bool;
        normal_tangent (N, 3) tangent-space normal ((0, 0, 1) = unperturbed, not normalised).
        Opacity is clamped to [0, 1]; where the material's opacityThreshold > 0 it is the cut-out
        mask 1 (opacity >= threshold) or 0, as Storm renders it.

    Raises:
        ValueError: mismatched shapes or a material id outside [0, len(materials)).
    """
    material_ids = np.asarray(material_ids).reshape(-1)
    uvs = np.asarray(uvs, np.float32)
    num_points = material_ids.shape[0]
    if uvs.shape != (num_points, 2):
        raise ValueError(f"uvs must be ({num_points}, 2) to match material_ids, got {uvs.shape}")
    if num_points and (material_ids.min() < 0 or material_ids.max() >= len(materials)):
        raise ValueError(
            f"material ids must lie in [0, {len(materials)}), got [{material_ids.min()}, {material_ids.max()}]"
        )
    result = {
        key: np.empty((num_points, num_channels), np.float32) for key, (_, num_channels) in _TEXTURED_FIELDS.items()
    }
    use_specular_workflow = np.empty(num_points, bool)
    # Group points by material once (sort) instead of one full mask per material.
    order = np.argsort(material_ids, kind="stable")
    unique_ids, starts = np.unique(material_ids[order], return_index=True)
    for material_id, rows in zip(unique_ids, np.split(order, starts)[1:], strict=True):
        material = materials[material_id]
        material_uvs = uvs[rows]
        for key, (field_name, num_channels) in _TEXTURED_FIELDS.items():
            result[key][rows] = _evaluate_input(getattr(material, field_name), material_uvs, num_channels)
        result["opacity"][rows] = cut_out(result["opacity"][rows], material.opacity_threshold)
        use_specular_workflow[rows] = material.use_specular_workflow
    evaluated = {key: (values if values.shape[1] == 3 else values[:, 0]) for key, values in result.items()}
    evaluated["use_specular_workflow"] = use_specular_workflow
    return evaluated


def _normalize(vectors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(unit vectors, squared lengths) of (..., 3) vectors; zero vectors stay zero."""
    squared = np.sum(vectors * vectors, axis=-1)
    safe = np.where(squared > _DEGENERATE_SQUARED, squared, 1.0)
    return vectors / np.sqrt(safe)[..., None], squared


def orthonormal_tangent(normal: np.ndarray) -> np.ndarray:
    """A unit vector perpendicular to each unit normal (Duff et al. 2017, branchless basis).

    Args:
        normal: (N, 3) unit normals.

    Returns:
        (N, 3) unit tangents, continuous except across the z = 0 plane.
    """
    sign = np.where(normal[:, 2] >= 0.0, 1.0, -1.0).astype(normal.dtype)
    a = -1.0 / (sign + normal[:, 2])
    b = normal[:, 0] * normal[:, 1] * a
    return np.stack([1.0 + sign * normal[:, 0] ** 2 * a, sign * b, -sign * normal[:, 0]], axis=-1)


def triangle_tangents(positions: np.ndarray, uvs: np.ndarray) -> np.ndarray:
    """Per-triangle tangent dP/du from the uv parameterisation.

    Solving [e1 e2] = [dP/du dP/dv] [[du1 du2] [dv1 dv2]] gives
    dP/du = (e1 dv2 - e2 dv1) / (du1 dv2 - du2 dv1), e_k = P_k - P_0.
    Where the uv mapping is degenerate (zero or tiny uv area relative to the uv edge lengths, e.g.
    a mesh without st) an orthonormal tangent of the face normal is used instead.

    Args:
        positions: (T, 3, 3) corner positions [triangle, corner, xyz].
        uvs: (T, 3, 2) corner uvs.

    Returns:
        (T, 3) float32 unit tangents (not yet orthogonal to any normal).
    """
    tangents = np.empty((positions.shape[0], 3), np.float32)
    # In chunks: the float64 temporaries (about 300 bytes a triangle) stay bounded on big soups.
    for start in range(0, positions.shape[0], _TANGENT_CHUNK):
        chunk = slice(start, start + _TANGENT_CHUNK)
        tangents[chunk] = _tangents(positions[chunk], uvs[chunk])
    return tangents


def _tangents(positions: np.ndarray, uvs: np.ndarray) -> np.ndarray:
    """`triangle_tangents` of one chunk of triangles."""
    positions = np.asarray(positions, np.float64)
    uvs = np.asarray(uvs, np.float64)
    edges = positions[:, 1:] - positions[:, :1]
    duv = uvs[:, 1:] - uvs[:, :1]
    du1, dv1, du2, dv2 = duv[:, 0, 0], duv[:, 0, 1], duv[:, 1, 0], duv[:, 1, 1]
    determinant = du1 * dv2 - du2 * dv1
    edge_scale = np.sum(duv[:, 0] ** 2, axis=-1) * np.sum(duv[:, 1] ** 2, axis=-1)
    usable = determinant**2 > 1e-10 * edge_scale
    safe_determinant = np.where(usable, determinant, 1.0)
    dp_du = (edges[:, 0] * dv2[:, None] - edges[:, 1] * dv1[:, None]) / safe_determinant[:, None]
    tangent, squared = _normalize(dp_du)
    face_normal, normal_squared = _normalize(np.cross(edges[:, 0], edges[:, 1]))
    face_normal[normal_squared <= _DEGENERATE_SQUARED] = (0.0, 0.0, 1.0)
    usable &= squared > _DEGENERATE_SQUARED
    tangent[~usable] = orthonormal_tangent(face_normal[~usable])
    return tangent.astype(np.float32)


def tangent_about(normal: np.ndarray, tangent: np.ndarray) -> np.ndarray:
    """(N, 3) unit tangents: `tangent` (N, 3) made perpendicular to the unit `normal` (N, 3)
    (Gram-Schmidt), or `orthonormal_tangent(normal)` where it is parallel to it or zero."""
    result, squared = _normalize(tangent - normal * np.sum(normal * tangent, axis=-1, keepdims=True))
    degenerate = squared <= _DEGENERATE_SQUARED
    result[degenerate] = orthonormal_tangent(normal[degenerate])
    return result


def shading_frame(
    normal: np.ndarray, tangent: np.ndarray, normal_tangent: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The orthonormal shading frame at each point, with the normal map applied.

    Gram-Schmidt: t0 = normalize(tangent - N (N.tangent)), b0 = cross(N, t0); the mapped normal is
    n = normalize(t0 x + b0 y + N z). The returned frame is re-orthogonalised around n:
    t = normalize(t0 - n (n.t0)), b = cross(n, t), so (t, b, n) is right-handed and orthonormal, and
    equals (t0, b0, N) for the unperturbed value (0, 0, 1). A tangent parallel to N or a zero normal
    map value falls back to an orthonormal tangent / the unmapped normal.

    Args:
        normal: (N, 3) interpolated shading normals (need not be unit).
        tangent: (N, 3) tangents (e.g. `triangle_tangents` per hit triangle).
        normal_tangent: (N, 3) tangent-space normal-map values (`evaluate_materials`).

    Returns:
        (t, b, n), each (N, 3) float32 unit vectors.
    """
    normal, _ = _normalize(np.asarray(normal, np.float32))
    tangent = np.asarray(tangent, np.float32)
    normal_tangent = np.asarray(normal_tangent, np.float32)
    t0 = tangent_about(normal, tangent)
    b0 = np.cross(normal, t0)
    mapped = t0 * normal_tangent[:, :1] + b0 * normal_tangent[:, 1:2] + normal * normal_tangent[:, 2:3]
    n, mapped_squared = _normalize(mapped)
    unmapped = mapped_squared <= _DEGENERATE_SQUARED
    n[unmapped] = normal[unmapped]
    t, t_squared = _normalize(t0 - n * np.sum(n * t0, axis=-1, keepdims=True))
    # The mapped normal lies along t0 only for a tangent-space value of (+-1, 0, 0) exactly.
    along_t0 = t_squared <= _DEGENERATE_SQUARED
    t[along_t0] = -normal[along_t0] * np.sign(normal_tangent[along_t0, :1])
    b = np.cross(n, t)
    return t.astype(np.float32), b.astype(np.float32), n.astype(np.float32)
