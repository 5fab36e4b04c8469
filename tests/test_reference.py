"""The reference path tracer on its own: determinism, its variance output, closed-form radiometry,
and the `relight reference` command's EXR.

The closed forms use a plane seen straight down by a narrow camera (2 degree field of view), so
every pixel sees (nearly) the same point and the same view direction.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from pipeline.cli import main
from pipeline.reference.path_tracer import PathTracer, ReferenceSettings
from pipeline.scene import Camera, Geometry, Material, MaterialInput, Scene, SceneObject, find_camera, load_scene
from pipeline.scenes import SCENES
from relight_torch.brdf import preview_surface
from relight_torch.brdf.preview_surface import PreviewSurfaceParams
from relight_torch.io.exr import read_exr
from relight_torch.lights.light import Light, LightKind

PLANE_HALF_SIZE = 1000.0
CAMERA_HEIGHT = 5.0
FIELD_OF_VIEW_DEGREES = 2.0
# Rotation taking the camera's -Z (view) to world -Y (down) and its +Y to world -Z.
WORLD_FROM_LOOKING_DOWN = np.array([[1, 0, 0, 0], [0, 0, 1, CAMERA_HEIGHT], [0, -1, 0, 0], [0, 0, 0, 1]], np.float64)


def _constant(*values: float) -> MaterialInput:
    return MaterialInput(np.array(values, np.float32))


def _plane_scene(material: Material, lights: list[Light], size: int = 8) -> Scene:
    """A plane y = 0 facing +Y, under `lights`, seen straight down from (0, CAMERA_HEIGHT, 0)."""
    h = PLANE_HALF_SIZE
    corners = np.array([[[-h, 0, -h], [-h, 0, h], [h, 0, h]], [[-h, 0, -h], [h, 0, h], [h, 0, -h]]], np.float32)
    geometry = Geometry(
        positions=corners,
        normals=np.broadcast_to(np.float32([0, 1, 0]), (2, 3, 3)).copy(),
        uvs=np.zeros((2, 3, 2), np.float32),
        material_ids=np.zeros(2, np.int32),
        object_ids=np.zeros(2, np.int32),
    )
    aperture = 2.0 * 50.0 * math.tan(math.radians(FIELD_OF_VIEW_DEGREES) / 2.0)
    camera = Camera(
        path="/Camera",
        world_from_camera=WORLD_FROM_LOOKING_DOWN,
        focal_length=50.0,
        horizontal_aperture=aperture,
        vertical_aperture=aperture,
        horizontal_aperture_offset=0.0,
        vertical_aperture_offset=0.0,
        clipping_range=(0.01, 1e6),
        width=size,
        height=size,
    )
    return Scene(
        source="<test>",
        geometry=geometry,
        objects=[SceneObject("/Plane", True)],
        materials=[material],
        lights=lights,
        cameras={camera.path: camera},
    )


def _render(scene: Scene, **settings):
    return PathTracer(scene, ReferenceSettings(**settings)).render(scene.cameras["/Camera"])


def _assert_mean_matches(image, expected: np.ndarray, relative_floor: float) -> None:
    """Image mean per channel within 4 standard errors (+ a relative floor for the geometry's
    approximations) of `expected` (3,)."""
    mean = image.mean.reshape(-1, 3).mean(axis=0)
    standard_error = np.sqrt(image.variance.reshape(-1, 3).sum(axis=0)) / image.mean[..., 0].size
    tolerance = 4.0 * standard_error + relative_floor * np.abs(expected)
    assert np.all(np.abs(mean - expected) <= tolerance), f"mean {mean}, expected {expected}, +- {tolerance}"


def test_sphere_light_over_diffuse_plane_gives_closed_form_irradiance():
    """E = pi L (r/d)^2 under a sphere light of radius r at distance d; with specularColor 0 and the
    view and light both along the normal, Schlick F(E.h) < 1e-12 and the surface reflects
    diffuseColor / pi * E exactly. Direct light only."""
    albedo, radiance, radius, distance = 0.6, 40.0, 1.0, 10.0
    material = Material(
        path="/Matte",
        diffuse_color=_constant(albedo, albedo / 2, albedo / 4),
        use_specular_workflow=True,
        specular_color=_constant(0, 0, 0),
        roughness=_constant(1.0),
    )
    world_from_light = np.eye(4)
    world_from_light[1, 3] = distance
    light = Light(
        path="/Sphere", kind=LightKind.SPHERE, world_from_light=world_from_light, intensity=radiance, radius=radius
    )
    image = _render(_plane_scene(material, [light]), spp=64, max_bounces=0)
    irradiance = math.pi * radiance * (radius / distance) ** 2
    expected = np.array([albedo, albedo / 2, albedo / 4]) / math.pi * irradiance
    # Over the 0.17-wide patch E falls by < 2e-4 (cos / d^2 off axis).
    _assert_mean_matches(image, expected, relative_floor=5e-4)


def _directional_albedo(params: PreviewSurfaceParams, wo_local: torch.Tensor, num: int = 1024) -> np.ndarray:
    """(3,) integral of f_r cos over the hemisphere at wo, by the midpoint rule in (cos theta, phi)."""
    cos_theta = (torch.arange(num, dtype=torch.float64) + 0.5) / num
    phi = (torch.arange(2 * num, dtype=torch.float64) + 0.5) / (2 * num) * 2 * math.pi
    c, p = torch.meshgrid(cos_theta, phi, indexing="ij")
    s = torch.sqrt(1 - c * c)
    wi = torch.stack([s * torch.cos(p), s * torch.sin(p), c], dim=-1).reshape(-1, 3)
    rows = params.index(torch.zeros(wi.shape[0], dtype=torch.long))
    f_cos = preview_surface.eval(rows, wo_local.expand_as(wi), wi) * wi[:, 2:]
    return (f_cos.mean(dim=0) * 2 * math.pi).numpy()


@pytest.mark.parametrize("max_bounces", [0, 2])
def test_plane_under_uniform_dome_reflects_its_directional_albedo(max_bounces):
    """Furnace: under a uniform dome of radiance 1 an open plane reflects exactly its directional
    albedo rho(wo) (no interreflection, so extra bounces add nothing). Exercises dome sampling,
    BSDF sampling and their MIS weights on a glossy plastic; rho by quadrature of the BRDF."""
    material = Material(path="/Plastic", diffuse_color=_constant(0.8, 0.5, 0.2), roughness=_constant(0.3))
    dome = Light(path="/Dome", kind=LightKind.DOME, intensity=1.0)
    image = _render(_plane_scene(material, [dome]), spp=64, max_bounces=max_bounces)
    params = PreviewSurfaceParams.from_numpy(
        {
            "diffuse_color": np.float32([[0.8, 0.5, 0.2]]),
            "emissive_color": np.zeros((1, 3), np.float32),
            "specular_color": np.zeros((1, 3), np.float32),
            "metallic": np.zeros(1, np.float32),
            "roughness": np.float32([0.3]),
            "clearcoat": np.zeros(1, np.float32),
            "clearcoat_roughness": np.float32([0.01]),
            "ior": np.float32([1.5]),
            "opacity": np.ones(1, np.float32),
            "use_specular_workflow": np.zeros(1, bool),
        }
    ).to("cpu", torch.float64)
    expected = _directional_albedo(params, torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64))
    _assert_mean_matches(image, expected, relative_floor=1e-3)


@pytest.fixture(scope="module")
def cornell_box(tmp_path_factory):
    bundled = SCENES["cornell_box"]
    path = bundled.write(tmp_path_factory.mktemp("cornell"))
    scene = load_scene(str(path), width=12, height=12)
    return path, scene, find_camera(scene, bundled.camera)


def test_same_seed_same_image_whatever_the_worker_count(cornell_box):
    _, scene, camera = cornell_box
    settings = dict(spp=6, max_bounces=2, paths_per_batch=300)
    one = PathTracer(scene, ReferenceSettings(seed=3, num_workers=1, **settings)).render(camera)
    two = PathTracer(scene, ReferenceSettings(seed=3, num_workers=2, **settings)).render(camera)
    other = PathTracer(scene, ReferenceSettings(seed=4, num_workers=2, **settings)).render(camera)
    np.testing.assert_array_equal(one.mean, two.mean)
    np.testing.assert_array_equal(one.variance, two.variance)
    assert not np.array_equal(one.mean, other.mean)
    assert one.num_paths == 12 * 12 * 6 and one.num_vertices >= one.num_paths


def test_a_pass_larger_than_a_batch_is_cut_into_bands_of_rows(cornell_box):
    """A film-size pass does not fit a batch: it is traced in bands of rows, so a batch holds at
    most `paths_per_batch` paths whatever the image size, and the image is the same whatever the
    worker count and agrees with whole-pass batches within its noise."""
    _, scene, camera = cornell_box
    banded = ReferenceSettings(spp=8, max_bounces=2, paths_per_batch=50, seed=3)
    tracer = PathTracer(scene, banded)
    batches = tracer._batches(camera.height, camera.width)
    assert all(passes * (rows[1] - rows[0]) * camera.width <= 50 for _, passes, rows in batches)
    covered = np.zeros((banded.spp, camera.height), int)
    for first, passes, rows in batches:
        covered[first : first + passes, rows[0] : rows[1]] += 1
    np.testing.assert_array_equal(covered, 1)
    one = PathTracer(scene, replace(banded, num_workers=1)).render(camera)
    two = PathTracer(scene, replace(banded, num_workers=2)).render(camera)
    np.testing.assert_array_equal(one.mean, two.mean)
    whole = PathTracer(scene, replace(banded, paths_per_batch=1 << 16)).render(camera)
    assert not np.array_equal(one.mean, whole.mean)  # other random streams
    difference = one.mean.mean() - whole.mean.mean()
    sigma = np.sqrt((one.variance.sum() + whole.variance.sum()) / one.mean.size**2)
    assert abs(difference) < 4 * sigma


def test_variance_is_the_spread_of_independent_renders(cornell_box):
    """The reported variance of the mean matches the scatter of the means of independent seeds:
    the ratio of the two image-wide averages is 1 within its sampling error (~ sqrt(2 / K))."""
    _, scene, camera = cornell_box
    num_seeds = 24
    renders = [
        PathTracer(scene, ReferenceSettings(spp=8, max_bounces=1, seed=seed)).render(camera)
        for seed in range(num_seeds)
    ]
    scatter = np.var([r.mean for r in renders], axis=0, ddof=1)
    reported = np.mean([r.variance for r in renders], axis=0)
    assert np.all(np.isfinite(reported)) and np.all(reported >= 0)
    ratio = scatter.mean() / reported.mean()
    assert 0.7 < ratio < 1.4, ratio


def test_cli_writes_an_exr_with_colour_and_variance(cornell_box, tmp_path):
    path, _, camera = cornell_box
    out = tmp_path / "reference.exr"
    code = main(
        [
            "reference",
            str(path),
            "--camera",
            camera.path,
            "-o",
            str(out),
            "--spp",
            "4",
            "--max-bounces",
            "1",
            "--width",
            "10",
            "--height",
            "8",
            "--seed",
            "2",
        ]
    )
    assert code == 0
    channels, header = read_exr(out)
    assert set(channels) == {"R", "G", "B", "variance.R", "variance.G", "variance.B"}
    for pixels in channels.values():
        assert pixels.shape == (8, 10) and pixels.dtype == np.float32
        assert np.all(np.isfinite(pixels)) and np.all(pixels >= 0)
    assert channels["R"].mean() > 0
    assert header["relight:spp"] == 4 and header["relight:maxBounces"] == 1


def test_cli_rejects_zero_samples(cornell_box, tmp_path, capsys):
    path, _, camera = cornell_box
    out = tmp_path / "reference.exr"
    code = main(["reference", str(path), "--camera", camera.path, "-o", str(out), "--spp", "0"])
    assert code == 2 and "--spp" in capsys.readouterr().err and not out.exists()
