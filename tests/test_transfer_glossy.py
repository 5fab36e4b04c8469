"""F rows of glossy view samples (`pipeline.bake.transfer.lobe`): a near-mirror sphere in a closed room
reflects one lit wall as the BRDF integrated over the directions that meet it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree

from pipeline.bake.deep_framebuffer import bake_deep_framebuffer
from pipeline.bake.gather_cloud import create_gathers
from pipeline.bake.transfer import lobe
from pipeline.bake.transfer.rows import disc_support, final_gather_rows
from pipeline.scene import find_camera, load_scene
from pipeline.tracing import Tracer
from relight_torch.brdf import preview_surface
from relight_torch.indirect_samples import GatherSamples
from relight_torch.math.frame import to_local

ROUGHNESS = 0.2  # the glossy scene's gold sphere
TRUTH_SAMPLES = 1 << 12


def _wall(name: str, axis: int, side: float) -> str:
    """A Mesh quad of the room [-1, 1]^3 on plane `axis` = `side`, wound to face inward."""
    u, v = (axis + 1) % 3, (axis + 2) % 3
    corners = []
    for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
        point = [0.0, 0.0, 0.0]
        point[axis], point[u], point[v] = side, a, b
        corners.append(point)
    c = np.array(corners)
    if np.dot(np.cross(c[1] - c[0], c[2] - c[0]), -c[0] * (np.arange(3) == axis)) < 0:
        corners.reverse()
    return f"""    def Mesh "{name}" (prepend apiSchemas = ["MaterialBindingAPI"])
    {{
        int[] faceVertexCounts = [4]
        int[] faceVertexIndices = [0, 1, 2, 3]
        point3f[] points = [{", ".join(f"({x}, {y}, {z})" for x, y, z in corners)}]
        uniform token subdivisionScheme = "none"
        rel material:binding = </Room/Matte>
    }}"""


def _mirror_room(directory: Path) -> Path:
    """A closed room [-1, 1]^3 of matte walls, a metal sphere of roughness ROUGHNESS inside, a camera facing it."""
    walls = "\n".join(_wall(f"Wall{axis}{int(side > 0)}", axis, side) for axis in range(3) for side in (-1.0, 1.0))
    material = """    def Material "{name}"
    {{
        token outputs:surface.connect = </Room/{name}/Surface.outputs:surface>
        def Shader "Surface"
        {{
            uniform token info:id = "UsdPreviewSurface"
            color3f inputs:diffuseColor = ({colour}, {colour}, {colour})
            float inputs:metallic = {metallic}
            float inputs:roughness = {roughness}
            token outputs:surface
        }}
    }}"""
    path = directory / "mirror_room.usda"
    path.write_text(
        f"""#usda 1.0
(
    defaultPrim = "Room"
    upAxis = "Y"
)

def Xform "Room"
{{
{material.format(name="Matte", colour=0.5, metallic=0, roughness=0.9)}
{material.format(name="Mirror", colour=0.9, metallic=1, roughness=ROUGHNESS)}
{walls}
    def Sphere "Ball" (prepend apiSchemas = ["MaterialBindingAPI"])
    {{
        double radius = 0.3
        double3 xformOp:translate = (0, 0, -0.3)
        uniform token[] xformOpOrder = ["xformOp:translate"]
        rel material:binding = </Room/Mirror>
    }}
    def Camera "Camera"
    {{
        double3 xformOp:translate = (0, 0, 0.9)
        uniform token[] xformOpOrder = ["xformOp:translate"]
    }}
}}
"""
    )
    return path


def _reflected_wall(view, rows: torch.Tensor, tracer: Tracer, lit_wall: int, num_samples: int) -> torch.Tensor:
    """(R, 3) the radiance view samples `rows` reflect from a wall of unit radiance (object `lit_wall`):
    the BRDF's own sampler (whole mixture), each ray traced to its first hit, no gathers."""
    generator = torch.Generator().manual_seed(5)
    u = torch.rand(rows.shape[0], num_samples, 2, generator=generator, dtype=torch.float32).clamp(max=1 - 1e-6)
    frame = (view.tangent[rows, None], view.bitangent[rows, None], view.normal[rows, None])
    wo_local = to_local(view.wo_world()[rows], *(f[:, 0] for f in frame)).unsqueeze(1).expand(-1, num_samples, -1)
    params = view.params.index(rows).with_sample_axis()
    wi_local, pdf = preview_surface.sample(params, wo_local, u)
    value = preview_surface.eval(params, wo_local, wi_local) * wi_local[..., 2:].clamp(min=0.0)
    weight = torch.where(pdf[..., None] > 0, value / pdf.clamp(min=1e-30)[..., None], 0.0)
    wi_world = sum(wi_local[..., k, None] * frame[k] for k in range(3))
    directions = wi_world.reshape(-1, 3).numpy().astype(np.float32)
    starts = view.position[rows, None].expand(-1, num_samples, -1).reshape(-1, 3).numpy().astype(np.float32)
    normals = view.geometric_normal[rows, None].expand(-1, num_samples, -1).reshape(-1, 3).numpy().astype(np.float32)
    hits = tracer.intersect(tracer.offset_origins(starts, normals, directions), directions)
    front = np.einsum("nk,nk->n", hits.geometric_normal, directions) < 0
    seen = torch.from_numpy((hits.object_id == lit_wall) & front).reshape(rows.shape[0], num_samples)
    return (weight * seen[..., None]).mean(1)


def test_glossy_rows_reflect_a_lit_wall_as_the_brdf_integrates_it(tmp_path):
    # The gold sphere of the glossy scene (roughness 0.2) reflected the lit room through rows built
    # from the gathers alone, whose discs its narrow lobe falls between: on this room (1,024 gathers)
    # the reflected wall's radiance was 48 % RMS off per pixel (its mean within 2 %). Lobe-sampled
    # rows (`lobe.lobe_rows`) integrate the lobe: 8 % RMS when written, the rest the gathers' spacing
    # at the wall's edges (the lookup blurs them over a gather) and 64 directions per pixel.
    scene = load_scene(_mirror_room(tmp_path), width=12, height=12)
    camera = find_camera(scene, "/Room/Camera")
    tracer = Tracer.for_scene(scene)
    view = bake_deep_framebuffer(scene, camera, 1, 1, tracer=tracer).gbuffer
    objects = [o.path for o in scene.objects]
    ball, lit_wall = objects.index("/Room/Ball"), objects.index("/Room/Wall01")
    rows = torch.nonzero(view.object_id == ball, as_tuple=True)[0]
    assert rows.numel() > 60 and bool(preview_surface.glossy(view.params.index(rows)).all())
    gathers = create_gathers(scene, 1024, seed=0)
    light = (gathers.object_id == lit_wall).to(torch.float32)  # unit radiance leaving the lit wall's gathers
    block = final_gather_rows(view, slice(0, view.num_samples), gathers, tracer, disc_support(gathers, tracer))
    relit = (block[rows] * light[None, :, None]).sum(1)
    truth = _reflected_wall(view, rows, tracer, lit_wall, TRUTH_SAMPLES)
    seen = truth.mean(-1) > 0.05  # pixels that reflect the wall
    assert seen.sum() > 10
    relative = (relit - truth).norm(dim=-1) / truth.norm(dim=-1).clamp(min=1e-6)
    assert abs(float(relit.mean() / truth.mean()) - 1.0) < 0.05
    assert float(relative[seen].square().mean().sqrt()) < 0.2


def test_hit_gathers_take_the_facing_gathers_of_the_hit_surface():
    # Two parallel walls 0.1 apart facing each other, and a hit on the lower one seen from above: only
    # the lower wall's gathers (facing up, towards the ray's origin) stand for it, weighted to sum to one.
    grid = torch.stack(torch.meshgrid(torch.arange(4.0), torch.arange(4.0), indexing="ij"), -1).reshape(-1, 2) / 4
    lower = torch.cat((grid, torch.zeros(16, 1)), -1)
    upper = torch.cat((grid, torch.full((16, 1), 0.1)), -1)
    up, down = torch.tensor([0.0, 0.0, 1.0]), torch.tensor([0.0, 0.0, -1.0])
    # Padded to 64 (a power of 4) with far-away gathers.
    far = torch.full((32, 3), 100.0)
    gathers = GatherSamples(
        position=torch.cat((lower, upper, far)),
        normal=torch.cat((up.expand(16, 3), down.expand(16, 3), up.expand(32, 3))),
        albedo=torch.full((64, 3), 0.5),
        emission=torch.zeros(64, 3),
        area=torch.full((64,), 1 / 16),
    )
    tree = cKDTree(gathers.position.numpy())
    position = np.array([[0.3, 0.3, 0.0]])
    index, weight = lobe.hit_gathers(gathers, tree, position, up.numpy()[None], down.numpy()[None])
    assert abs(float(weight.sum()) - 1.0) < 1e-6
    assert np.all(index[weight > 0] < 16)
    # The same point hit from below (the back of the lower wall): no gather emits that way.
    _, weight = lobe.hit_gathers(gathers, tree, position, up.numpy()[None], up.numpy()[None])
    assert np.all(weight == 0)
