"""The reference renderer: an unbiased wavefront path tracer over the Embree tracer.

Ground truth for every accuracy figure in the project. It shades with the same kernels as the
relighter (`relight_torch.brdf`, `relight_torch.lights.emission`, `relight_torch.shading`) and the
same shading points as the bakers (`pipeline.shading_points`), so approximations differ from it
only in what they approximate.

Estimator: next-event estimation towards every light at each vertex, combined with BSDF sampling
by multiple importance sampling (power heuristic); Russian roulette from `roulette_depth` on.
`max_bounces = 0` is direct light only (light -> surface -> camera), 1 adds one indirect bounce...
Lights are not seen by camera rays (Karma's default `renderlightgeo = 0`): they show through
reflection only, as in the relighter, whose deep framebuffer holds surfaces only.
Lights are not occluders either: a ray passes through a light's surface to whatever lies behind
it (so an area light mounted just below a ceiling lets that ceiling patch show through it).
Surfaces are shaded on both sides. Opacity (`relight_torch.visibility.opacity`, in the tracer):
camera, path and shadow rays pass through cut-out holes; a partially opaque surface is met with
probability equal to its opacity (stochastic presence: transmission without refraction).
UsdLux linking: a light reaches only the objects of its light link (next-event estimation and
BSDF-sampled hits of the light are both dropped at vertices on other objects), and only the
objects of its shadow link block it (its shadow rays, and the surfaces a BSDF-sampled ray must
not meet before the light, are traced against those objects' triangles alone).

Speed (see `pipeline.reference.bench`): batches of passes are traced on `num_workers` Python
threads with torch held to one intra-op thread while rendering. Torch's OpenMP pool spin-waits
at every op barrier; on a shared machine where its threads get descheduled, two OpenMP threads ran
the Cornell box 25x slower than one (4 k vs 136 k paths/s), whereas independent batches on
threads never wait for each other (torch, numpy and Embree release the GIL in their kernels).
"""

from __future__ import annotations

import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import torch

from pipeline.scene.camera import camera_rays
from pipeline.scene.types import Camera, Scene
from pipeline.shading_points import ShadingPoints, shading_points
from pipeline.tracing import shared_tracer
from relight_torch.brdf import preview_surface
from relight_torch.lights.emission import emitted_radiance, intersect_light, is_delta_light, light_pdf, sample_light
from relight_torch.lights.light import Light, LightKind
from relight_torch.lights.linking import linked_objects
from relight_torch.math.frame import to_local, to_world
from relight_torch.parallel import torch_threads
from relight_torch.shading import reflected_radiance
from relight_torch.visibility.embree import ShadowLinkCasters

_INFINITE_KINDS = (LightKind.DOME, LightKind.DISTANT)


FULL_FRAME_BOUNCES = 64
"""The bounce cap of the full frame: Russian roulette (from `roulette_depth`) ends paths long before it."""


@dataclass(frozen=True)
class ReferenceSettings:
    """How the reference is rendered.

    Attributes:
        spp: samples (paths) per pixel.
        max_bounces: indirect bounces; 0 = direct light only; the default is the full frame.
        seed: the image is a deterministic function of the scene, camera, settings and seed
            (not of `num_workers` or the machine's thread count).
        roulette_depth: vertex index from which Russian roulette may end paths.
        paths_per_batch: paths traced together by one worker (memory ~ 1 KB per path).
        num_workers: batches traced concurrently; None: the CPUs this process may use.
    """

    spp: int = 64
    max_bounces: int = FULL_FRAME_BOUNCES
    seed: int = 0
    roulette_depth: int = 3
    paths_per_batch: int = 1 << 16
    num_workers: int | None = None


@dataclass(frozen=True)
class ReferenceImage:
    """A rendered reference.

    Attributes:
        mean: (H, W, 3) float32 linear radiance (camera exposure applied).
        variance: (H, W, 3) float32 variance of `mean` itself (sample variance / spp).
        seconds: wall-clock render time.
        num_paths: paths traced (camera rays).
        num_vertices: surface points shaded along them (next-event estimation and BSDF sampling
            at each): the work done, beside `num_paths`.
    """

    mean: np.ndarray
    variance: np.ndarray
    seconds: float
    num_paths: int
    num_vertices: int = 0


@dataclass
class _Vertex:
    """The shading points of the live paths at one depth, with their torch views.

    Attributes:
        points: the shading points (numpy, for the tracer).
        frame: (tangent, bitangent, normal), each (N, 3) float32 tensors.
        wo_local: (N, 3) direction to the previous vertex in the shading frame.
        position, geometric_normal: (N, 3) float32 tensors.
    """

    points: ShadingPoints
    frame: tuple[torch.Tensor, torch.Tensor, torch.Tensor]
    wo_local: torch.Tensor
    position: torch.Tensor
    geometric_normal: torch.Tensor

    @staticmethod
    def of(points: ShadingPoints) -> _Vertex:
        frame = tuple(torch.from_numpy(a) for a in (points.tangent, points.bitangent, points.normal))
        return _Vertex(
            points,
            frame,
            to_local(torch.from_numpy(points.wo_world), *frame),
            torch.from_numpy(points.position),
            torch.from_numpy(points.geometric_normal),
        )


_Batch = tuple[int, int, tuple[int, int]]
"""A batch of the image's paths: (first pass, passes, pixel rows [first, last))."""


def _power_heuristic(pdf_a: torch.Tensor, pdf_b: torch.Tensor) -> torch.Tensor:
    a2, b2 = pdf_a * pdf_a, pdf_b * pdf_b
    return torch.where(a2 > 0, a2 / (a2 + b2), torch.zeros_like(a2))


class PathTracer:
    """Renders one scene from any of its cameras; Embree BVH and tangents built once."""

    def __init__(self, scene: Scene, settings: ReferenceSettings = ReferenceSettings()):
        if settings.spp < 1 or settings.max_bounces < 0 or settings.paths_per_batch < 1:
            raise ValueError(f"spp and paths_per_batch must be >= 1 and max_bounces >= 0, got {settings}")
        self.scene = scene
        self.settings = settings
        self.num_workers = settings.num_workers or len(os.sched_getaffinity(0))
        # Parallelism comes from the workers; one Embree thread each.
        self.tracer = shared_tracer(scene, num_threads=1 if self.num_workers > 1 else None)
        self.tangents = self.tracer.tangents
        self.area_lights = [light for light in scene.lights if not is_delta_light(light)]
        object_paths = [obj.path for obj in scene.objects]
        # Per light with a light link: (num_objects,) float32, 1 for the objects it lights.
        self.light_link_masks = {
            light.path: torch.from_numpy(linked_objects(object_paths, light.light_link)).float()
            for light in scene.lights
            if light.light_link is not None
        }
        self.shadow_link_casters = ShadowLinkCasters(
            self.tracer.corners,
            scene.geometry.object_ids,
            object_paths,
            self.tracer.epsilon,
            self.tracer.num_threads,
            self.tracer.opacity,
        )

    def render(self, camera: Camera, progress=None) -> ReferenceImage:
        """Render `camera`'s image. `progress(done_paths, total_paths)` is called after each batch."""
        start = time.perf_counter()
        height, width = camera.height, camera.width
        num_pixels = height * width
        total = num_pixels * self.settings.spp
        total_sum = np.zeros((num_pixels, 3), np.float64)
        total_sq = np.zeros((num_pixels, 3), np.float64)
        batches = list(enumerate(self._batches(height, width)))

        def trace_batch(batch: tuple[int, _Batch]) -> tuple[np.ndarray, int]:
            """((passes, pixels, 3) float64 radiance, vertices shaded) of one batch."""
            batch_index, (_, num_passes, rows) = batch
            tile = (rows[1] - rows[0], width)
            rng = np.random.default_rng([self.settings.seed, batch_index])
            rays = [camera_rays(camera, rng.random(tile + (2,), dtype=np.float32), rows) for _ in range(num_passes)]
            origins = np.concatenate([o.reshape(-1, 3) for o, _ in rays])
            directions = np.concatenate([d.reshape(-1, 3) for _, d in rays])
            radiance, num_vertices = self._trace(origins, directions, rng)
            radiance = radiance.numpy().astype(np.float64).reshape(num_passes, tile[0] * tile[1], 3)
            return radiance * camera.exposure_scale, num_vertices

        done = num_vertices = 0
        with torch_threads(1), ThreadPoolExecutor(self.num_workers) as pool:
            # Batches are summed in order (the image does not depend on scheduling), a window of
            # num_workers at a time so that memory stays bounded.
            for window in range(0, len(batches), self.num_workers):
                chunk = batches[window : window + self.num_workers]
                for (_, (_, _, rows)), (radiance, batch_vertices) in zip(
                    chunk, pool.map(trace_batch, chunk), strict=True
                ):
                    pixels = slice(rows[0] * width, rows[1] * width)
                    num_vertices += batch_vertices
                    total_sum[pixels] += radiance.sum(axis=0)
                    total_sq[pixels] += np.einsum("pnc,pnc->nc", radiance, radiance)
                    done += radiance.shape[0] * radiance.shape[1]
                    if progress is not None:
                        progress(done, total)
        spp = self.settings.spp
        mean = total_sum / spp
        sample_variance = np.maximum(total_sq / spp - mean**2, 0.0) * spp / max(spp - 1, 1)
        return ReferenceImage(
            mean=mean.reshape(height, width, 3).astype(np.float32),
            variance=(sample_variance / spp).reshape(height, width, 3).astype(np.float32),
            seconds=time.perf_counter() - start,
            num_paths=total,
            num_vertices=num_vertices,
        )

    def _batches(self, height: int, width: int) -> list[_Batch]:
        """The batches of an H x W image, about `paths_per_batch` paths each: whole passes
        while a pass fits, else each pass cut into bands of rows, so that a film-size image
        takes no more memory than a small one (about 1 KB per path in flight)."""
        spp, paths = self.settings.spp, self.settings.paths_per_batch
        if height * width <= paths:
            step = paths // (height * width)
            return [(first, min(step, spp - first), (0, height)) for first in range(0, spp, step)]
        band = max(1, paths // width)
        return [(first, 1, (row, min(row + band, height))) for first in range(spp) for row in range(0, height, band)]

    def _trace(self, origins: np.ndarray, directions: np.ndarray, rng: np.random.Generator) -> tuple[torch.Tensor, int]:
        """(radiance (N, 3) float32 carried back along N camera rays, surface vertices shaded)."""
        num_paths = origins.shape[0]
        num_vertices = 0
        radiance = torch.zeros((num_paths, 3))
        throughput = torch.ones((num_paths, 3))
        path = torch.arange(num_paths)  # which path each live ray belongs to
        bsdf_pdf = torch.zeros(num_paths)  # pdf of the direction just sampled (solid angle)
        previous_points = torch.from_numpy(origins)
        previous_objects = torch.zeros(num_paths, dtype=torch.int64)  # unused at depth 0
        for depth in range(self.settings.max_bounces + 2):
            if depth == self.settings.max_bounces + 1 and not self.area_lights:
                break  # the last segment only looks for lights that BSDF rays can hit
            hits = self.tracer.intersect(origins, directions)
            if depth > 0 and self.area_lights:
                emitted = self._emitters_hit(
                    previous_points,
                    torch.from_numpy(directions),
                    torch.from_numpy(hits.distance),
                    bsdf_pdf,
                    previous_objects,
                    origins,
                )
                radiance.index_add_(0, path, throughput * emitted)
            if depth == self.settings.max_bounces + 1:
                break
            keep = torch.from_numpy(hits.hit)
            path, throughput = path[keep], throughput[keep]
            if path.numel() == 0:
                break
            vertex = _Vertex.of(shading_points(self.scene, self.tangents, hits, directions))
            num_vertices += path.numel()
            direct = vertex.points.params.emissive_color + self._next_event(vertex, rng)
            radiance.index_add_(0, path, throughput * direct)
            wi_world, weight, bsdf_pdf = self._sample_bsdf(vertex, rng)
            throughput = throughput * weight
            survive = bsdf_pdf > 0
            if depth + 1 >= self.settings.roulette_depth:
                survive_probability = throughput.amax(dim=-1).clamp(max=0.95)
                survive &= torch.from_numpy(rng.random(path.numel(), dtype=np.float32)) < survive_probability
                throughput = throughput / survive_probability.clamp(min=1e-8)[:, None]
            path, throughput, bsdf_pdf = path[survive], throughput[survive], bsdf_pdf[survive]
            previous_points = vertex.position[survive]
            previous_objects = torch.from_numpy(vertex.points.object_id).long()[survive]
            directions = wi_world[survive].numpy()
            origins = self.tracer.offset_origins(
                previous_points.numpy(), vertex.points.geometric_normal[survive.numpy()], directions
            )
            if path.numel() == 0:
                break
        return radiance, num_vertices

    def _emitters_hit(
        self,
        points: torch.Tensor,
        directions: torch.Tensor,
        surface_distance: torch.Tensor,
        bsdf_pdf: torch.Tensor,
        objects: torch.Tensor,
        origins: np.ndarray,
    ) -> torch.Tensor:
        """Light (N, 3) seen along BSDF-sampled rays, MIS-weighted against next-event estimation.

        Every light met before the surface counts: lights do not occlude one another, exactly as
        next-event estimation's shadow rays test the scene's surfaces only. `objects` (N,) are the
        object ids of the rays' vertices (for light links) and `origins` (N, 3) the rays' offset
        origins (to trace a light's shadow-link occluders).
        """
        total = torch.zeros_like(directions)
        for light in self.area_lights:
            blocker_distance = surface_distance
            if light.shadow_link is not None:
                caster = self.shadow_link_casters(light.shadow_link)
                blocker_distance = torch.from_numpy(caster.intersect(origins, directions.numpy()).distance)
            if light.kind in _INFINITE_KINDS:
                reached = torch.isinf(blocker_distance)
            else:
                reached = intersect_light(light, points, directions) < blocker_distance
            idx = torch.nonzero(reached).squeeze(1)
            if idx.numel() == 0:
                continue
            p, d = points[idx], directions[idx]
            weight = _power_heuristic(bsdf_pdf[idx], light_pdf(light, p, d)) * self._linked(light, objects[idx])
            total.index_add_(0, idx, emitted_radiance(light, p, d) * weight[:, None])
        return total

    def _next_event(self, vertex: _Vertex, rng: np.random.Generator) -> torch.Tensor:
        """Direct light (N, 3) from one sample of every light, shadow-tested, MIS-weighted."""
        points = vertex.points
        total = torch.zeros_like(vertex.position)
        for light in self.scene.lights:
            u = torch.from_numpy(rng.random((total.shape[0], 1, 2), dtype=np.float32))
            sample = sample_light(light, vertex.position, u)
            direction, pdf, arriving = sample.direction[:, 0], sample.pdf[:, 0], sample.radiance[:, 0]
            usable = (pdf > 0) & ((direction * vertex.geometric_normal).sum(-1) > 0) & (arriving.amax(-1) > 0)
            idx = torch.nonzero(usable).squeeze(1)
            if idx.numel() == 0:
                continue
            idx_numpy = idx.numpy()
            direction = direction[idx]
            shadow_distance = sample.distance[idx, 0].numpy()
            origins = self.tracer.offset_origins(
                points.position[idx_numpy], points.geometric_normal[idx_numpy], direction.numpy()
            )
            t_far = np.where(
                np.isfinite(shadow_distance), shadow_distance * (1.0 - 1e-4) - self.tracer.epsilon, np.inf
            ).astype(np.float32)
            caster = self.tracer if light.shadow_link is None else self.shadow_link_casters(light.shadow_link)
            visible = torch.from_numpy(~caster.occluded(origins, direction.numpy(), t_far))
            wi_local = to_local(direction, *(f[idx] for f in vertex.frame))
            wo_local = vertex.wo_local[idx]
            params = points.params.index(idx)
            contribution = reflected_radiance(params, wo_local, wi_local, arriving[idx], light.diffuse, light.specular)
            scale = (
                visible.float() * self._linked(light, torch.from_numpy(points.object_id[idx_numpy]).long()) / pdf[idx]
            )
            if not sample.is_delta:
                scale = scale * _power_heuristic(pdf[idx], preview_surface.pdf(params, wo_local, wi_local))
            total.index_add_(0, idx, contribution * scale[:, None])
        return total

    def _linked(self, light: Light, objects: torch.Tensor) -> torch.Tensor | float:
        """(M,) 1 where the light's light link includes the objects (ids (M,)), else 0; 1.0 without a link."""
        mask = self.light_link_masks.get(light.path)
        return 1.0 if mask is None else mask[objects]

    def _sample_bsdf(self, vertex: _Vertex, rng: np.random.Generator):
        """Sample the next direction: (wi_world (N, 3), weight f cos / pdf (N, 3), pdf (N,)), tensors."""
        params = vertex.points.params
        u = torch.from_numpy(rng.random((vertex.wo_local.shape[0], 2), dtype=np.float32))
        wi_local, pdf = preview_surface.sample(params, vertex.wo_local, u)
        wi_world = to_world(wi_local, *vertex.frame)
        valid = (pdf > 0) & ((wi_world * vertex.geometric_normal).sum(-1) > 0) & (wi_local[..., 2] > 0)
        f_cos = reflected_radiance(params, vertex.wo_local, wi_local, torch.ones_like(wi_local))
        weight = torch.where(valid[:, None], f_cos / pdf.clamp(min=1e-20)[:, None], torch.zeros_like(f_cos))
        pdf = torch.where(valid, pdf, torch.zeros_like(pdf))
        return wi_world.contiguous(), weight, pdf
