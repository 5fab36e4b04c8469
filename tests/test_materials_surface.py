"""Bake-time material evaluation, triangle tangents and normal-mapped shading frames."""

import numpy as np
import pytest

from pipeline.scene.surface import (
    evaluate_materials,
    orthonormal_tangent,
    shading_frame,
    tangent_about,
    triangle_tangents,
)
from pipeline.scene.types import Material, MaterialInput, Texture


def constant(*values):
    return MaterialInput(np.array(values, np.float32))


def test_evaluate_constant_and_textured_materials_per_point():
    # 1 x 2 texture (left texel 0.2, right 0.6) driving roughness through its 'g' output.
    pixels = np.array([[[0.0, 0.2, 0.0], [0.0, 0.6, 0.0]]], np.float32)
    textured = Material(
        "/Textured",
        roughness=MaterialInput(np.array([0.5], np.float32), Texture("<memory>", pixels, "clamp", "clamp", output="g")),
        opacity=constant(0.3),
        opacity_threshold=0.5,
    )
    plain = Material(
        "/Plain",
        diffuse_color=constant(0.1, 0.2, 0.3),
        use_specular_workflow=True,
        specular_color=constant(0.04, 0.04, 0.04),
        opacity=constant(0.3),
    )
    material_ids = np.array([1, 0, 1, 0], np.int32)
    uvs = np.array([[0.9, 0.5], [0.25, 0.5], [0.0, 0.0], [0.75, 0.5]], np.float32)
    params = evaluate_materials([textured, plain], material_ids, uvs)
    np.testing.assert_allclose(params["roughness"], [0.5, 0.2, 0.5, 0.6], rtol=1e-6)
    np.testing.assert_allclose(params["diffuse_color"][[0, 2]], [[0.1, 0.2, 0.3]] * 2, rtol=1e-6)
    np.testing.assert_allclose(params["diffuse_color"][[1, 3]], [[0.18] * 3] * 2, rtol=1e-6)
    np.testing.assert_array_equal(params["use_specular_workflow"], [True, False, True, False])
    # Threshold 0.5 turns opacity 0.3 into a cut-out 0; without a threshold it stays 0.3.
    np.testing.assert_allclose(params["opacity"], [0.3, 0.0, 0.3, 0.0], rtol=1e-6)
    np.testing.assert_allclose(params["normal_tangent"], [[0.0, 0.0, 1.0]] * 4)
    for key in ("diffuse_color", "emissive_color", "specular_color", "normal_tangent"):
        assert params[key].shape == (4, 3) and params[key].dtype == np.float32
    for key in ("metallic", "roughness", "clearcoat", "clearcoat_roughness", "ior", "opacity"):
        assert params[key].shape == (4,) and params[key].dtype == np.float32


def test_evaluate_rejects_bad_ids_and_shapes():
    with pytest.raises(ValueError, match="material ids"):
        evaluate_materials([Material("/A")], np.array([0, 1]), np.zeros((2, 2)))
    with pytest.raises(ValueError, match="uvs"):
        evaluate_materials([Material("/A")], np.array([0, 0]), np.zeros((3, 2)))


def test_tangent_of_known_uv_mapping():
    # P = origin + A @ uv: dP/du is A's first column whatever the corner uvs are.
    rng = np.random.default_rng(3)
    a = rng.normal(size=(8, 3, 2))
    origin = rng.normal(size=(8, 1, 3))
    uvs = rng.random((8, 3, 2))
    positions = origin + np.einsum("tij,tkj->tki", a, uvs)
    expected = a[:, :, 0] / np.linalg.norm(a[:, :, 0], axis=-1, keepdims=True)
    tangents = triangle_tangents(positions.astype(np.float32), uvs.astype(np.float32))
    assert tangents.dtype == np.float32
    np.testing.assert_allclose(tangents, expected, atol=1e-4)


def test_tangent_of_simple_triangle():
    # u runs along -y, v along +x: dP/du = (0, -1, 0).
    positions = np.array([[[0, 0, 0], [0, -2, 0], [3, 0, 0]]], np.float32)
    uvs = np.array([[[0, 0], [1, 0], [0, 1]]], np.float32)
    np.testing.assert_allclose(triangle_tangents(positions, uvs), [[0.0, -1.0, 0.0]], atol=1e-6)


def test_degenerate_uvs_fall_back_to_a_perpendicular_unit_tangent():
    positions = np.array([[[0, 0, 0], [1, 0, 0], [0, 0, 1]], [[0, 0, 0], [0, 1, 0], [1, 1, 1]]], np.float32)
    uvs = np.array([np.zeros((3, 2)), [[0, 0], [1, 1], [2, 2]]], np.float32)  # no st; collinear st
    tangents = triangle_tangents(positions, uvs)
    normals = np.cross(positions[:, 1] - positions[:, 0], positions[:, 2] - positions[:, 0])
    np.testing.assert_allclose(np.linalg.norm(tangents, axis=-1), 1.0, rtol=1e-6)
    np.testing.assert_allclose(np.sum(tangents * normals, axis=-1), 0.0, atol=1e-6)


def test_orthonormal_tangent_is_perpendicular():
    normals = np.random.default_rng(5).normal(size=(100, 3))
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    tangents = orthonormal_tangent(normals)
    np.testing.assert_allclose(np.linalg.norm(tangents, axis=-1), 1.0, rtol=1e-6)
    np.testing.assert_allclose(np.sum(tangents * normals, axis=-1), 0.0, atol=1e-6)


def frame_inputs(normal_tangent):
    normal = np.array([[0.0, 0.0, 2.0]])  # not unit on purpose
    tangent = np.array([[1.0, 0.0, 0.5]])  # not orthogonal on purpose: Gram-Schmidt gives (1, 0, 0)
    return normal, tangent, np.array([normal_tangent], np.float32)


def test_unperturbed_normal_map_leaves_the_frame():
    t, b, n = shading_frame(*frame_inputs([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(t, [[1, 0, 0]], atol=1e-6)
    np.testing.assert_allclose(b, [[0, 1, 0]], atol=1e-6)
    np.testing.assert_allclose(n, [[0, 0, 1]], atol=1e-6)


def test_normal_map_tilts_toward_the_tangent():
    _, _, n = shading_frame(*frame_inputs([1.0, 0.0, 1.0]))  # 45 degrees toward t
    np.testing.assert_allclose(n, [[np.sqrt(0.5), 0, np.sqrt(0.5)]], atol=1e-6)
    t, b, n = shading_frame(*frame_inputs([1.0, 0.0, 0.0]))  # all the way: n = t0, t rotates to -N
    np.testing.assert_allclose(n, [[1, 0, 0]], atol=1e-6)
    np.testing.assert_allclose(t, [[0, 0, -1]], atol=1e-6)
    np.testing.assert_allclose(b, [[0, 1, 0]], atol=1e-6)
    _, _, n = shading_frame(*frame_inputs([0.0, 1.0, 0.0]))  # +y is the bitangent cross(N, t)
    np.testing.assert_allclose(n, [[0, 1, 0]], atol=1e-6)


def test_shading_frame_is_right_handed_and_orthonormal():
    rng = np.random.default_rng(11)
    normal = rng.normal(size=(200, 3))
    tangent = rng.normal(size=(200, 3))
    normal_tangent = np.concatenate([rng.normal(size=(200, 2)) * 0.5, rng.random((200, 1)) + 0.1], axis=-1)
    tangent[:3] = normal[:3] * 2.0  # tangent parallel to the normal: fallback tangent
    t, b, n = shading_frame(normal, tangent, normal_tangent)
    frames = np.stack([t, b, n], axis=-1)
    np.testing.assert_allclose(frames.transpose(0, 2, 1) @ frames, np.broadcast_to(np.eye(3), (200, 3, 3)), atol=1e-5)
    np.testing.assert_allclose(np.linalg.det(frames), 1.0, atol=1e-5)
    # The mapped normal stays on the geometric normal's side for z > 0.
    assert np.all(np.sum(n * normal, axis=-1) > 0)


def test_tangent_about_a_normal_is_unit_and_perpendicular_even_along_it():
    rng = np.random.default_rng(5)
    normal = rng.normal(size=(100, 3))
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    tangent = rng.normal(size=(100, 3))
    tangent[:3] = normal[:3] * -3.0  # along the normal (an averaged normal at an edge): a fallback
    tangent[3] = 0.0
    result = tangent_about(normal, tangent)
    np.testing.assert_allclose(np.linalg.norm(result, axis=-1), 1.0, rtol=1e-6)
    np.testing.assert_allclose(np.sum(result * normal, axis=-1), 0.0, atol=1e-6)
    np.testing.assert_allclose(result[:4], orthonormal_tangent(normal[:4]), atol=1e-6)
    # Elsewhere it keeps the tangent's direction within the plane.
    assert np.all(np.sum(result[4:] * tangent[4:], axis=-1) > 0)
