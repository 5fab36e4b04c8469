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
Surfaces are shaded on both sides; opacity is ignored (opaque), with a warning.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from pipeline.errors import warn
from pipeline.scene.camera import camera_rays
from pipeline.scene.surface import triangle_tangents
from pipeline.scene.types import Camera, Scene
from pipeline.shading_points import ShadingPoints, shading_points
from pipeline.tracing import Tracer
from relight_torch.brdf import preview_surface
from relight_torch.lights.emission import emitted_radiance, intersect_light, light_pdf, sample_light
from relight_torch.lights.light import Light, LightKind
from relight_torch.math.frame import to_local, to_world
from relight_torch.shading import reflected_radiance

_INFINITE_KINDS = (LightKind.DOME, LightKind.DISTANT)


@dataclass(frozen=True)
class ReferenceSettings:
    """How the reference is rendered.

    Attributes:
        spp: samples (paths) per pixel.
        max_bounces: indirect bounces; 0 = direct light only.
        seed: the image is a deterministic function of the scene, camera, settings and seed.
        roulette_depth: vertex index from which Russian roulette may end paths.
        paths_per_batch: paths traced together (memory ~ 1 KB per path).
    """

    spp: int = 64
    max_bounces: int = 4
    seed: int = 0
    roulette_depth: int = 3
    paths_per_batch: int = 1 << 17


@dataclass(frozen=True)
class ReferenceImage:
    """A rendered reference.

    Attributes:
        mean: (H, W, 3) float32 linear radiance (camera exposure applied).
        variance: (H, W, 3) float32 variance of `mean` itself (sample variance / spp).
        seconds: wall-clock render time.
        num_paths: paths traced.
    """

    mean: np.ndarray
    variance: np.ndarray
    seconds: float
    num_paths: int


def _power_heuristic(pdf_a: torch.Tensor, pdf_b: torch.Tensor) -> torch.Tensor:
    a2, b2 = pdf_a * pdf_a, pdf_b * pdf_b
    return torch.where(a2 > 0, a2 / (a2 + b2), torch.zeros_like(a2))


class PathTracer:
    """Renders one scene from any of its cameras; Embree BVH and tangents built once."""

    def __init__(self, scene: Scene, settings: ReferenceSettings = ReferenceSettings()):
        if settings.spp < 1 or settings.max_bounces < 0:
            raise ValueError(f"spp must be >= 1 and max_bounces >= 0, got {settings}")
        self.scene = scene
        self.settings = settings
        self.tracer = Tracer(scene.geometry)
        self.tangents = triangle_tangents(scene.geometry.positions, scene.geometry.uvs)
        if any(m.opacity.texture is not None or float(m.opacity.value[0]) < 1.0 for m in scene.materials):
            warn("reference: opacity is ignored; every surface is rendered opaque", scene.warnings)

    def render(self, camera: Camera, progress=None) -> ReferenceImage:
        """Render `camera`'s image. `progress(done_paths, total_paths)` is called after each batch."""
        start = time.perf_counter()
        height, width = camera.height, camera.width
        num_pixels = height * width
        total = num_pixels * self.settings.spp
        total_sum = np.zeros((num_pixels, 3), np.float64)
        total_sq = np.zeros((num_pixels, 3), np.float64)
        passes_per_batch = max(1, self.settings.paths_per_batch // num_pixels)
        for batch_index, first in enumerate(range(0, self.settings.spp, passes_per_batch)):
            num_passes = min(passes_per_batch, self.settings.spp - first)
            rng = np.random.default_rng([self.settings.seed, batch_index])
            rays = [camera_rays(camera, rng.random((height, width, 2), dtype=np.float32)) for _ in range(num_passes)]
            origins = np.concatenate([o.reshape(-1, 3) for o, _ in rays])
            directions = np.concatenate([d.reshape(-1, 3) for _, d in rays])
            radiance = self._trace(origins, directions, rng).reshape(num_passes, num_pixels, 3) * camera.exposure_scale
            total_sum += radiance.sum(axis=0)
            total_sq += (radiance**2).sum(axis=0)
            if progress is not None:
                progress((first + num_passes) * num_pixels, total)
        spp = self.settings.spp
        mean = total_sum / spp
        sample_variance = np.maximum(total_sq / spp - mean**2, 0.0) * spp / max(spp - 1, 1)
        return ReferenceImage(
            mean=mean.reshape(height, width, 3).astype(np.float32),
            variance=(sample_variance / spp).reshape(height, width, 3).astype(np.float32),
            seconds=time.perf_counter() - start,
            num_paths=total,
        )

    def _trace(self, origins: np.ndarray, directions: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Radiance (N, 3) float64 carried back along N camera rays."""
        num_paths = origins.shape[0]
        radiance = np.zeros((num_paths, 3), np.float64)
        throughput = torch.ones((num_paths, 3), dtype=torch.float32)
        path = np.arange(num_paths)             # which path each live ray belongs to
        bsdf_pdf = torch.zeros(num_paths)       # pdf of the direction just sampled (solid angle)
        previous_points = origins               # where the live rays start
        for depth in range(self.settings.max_bounces + 2):
            hits = self.tracer.intersect(origins, directions)
            if depth > 0:
                self._add_emitters_hit(radiance, path, throughput, previous_points, directions, hits.distance, bsdf_pdf)
            if depth == self.settings.max_bounces + 1:
                break
            keep = hits.hit
            path, throughput = path[keep], throughput[torch.from_numpy(keep)]
            if path.size == 0:
                break
            points = shading_points(self.scene, self.tangents, hits, directions)
            radiance[path] += (throughput * points.params.emissive_color).double().numpy()
            radiance[path] += self._next_event(points, throughput, rng)
            wi_world, weight, bsdf_pdf = self._sample_bsdf(points, rng)
            throughput = throughput * weight
            if depth + 1 >= self.settings.roulette_depth:
                survive_probability = throughput.max(dim=-1).values.clamp(max=0.95)
                survive = torch.from_numpy(rng.random(path.size, dtype=np.float32)) < survive_probability
                throughput = throughput / survive_probability.clamp(min=1e-8)[:, None]
                survive &= bsdf_pdf > 0
            else:
                survive = bsdf_pdf > 0
            alive = survive.numpy()
            path, throughput, bsdf_pdf = path[alive], throughput[survive], bsdf_pdf[survive]
            directions = wi_world[alive]
            origins = self.tracer.offset_origins(points.position[alive], points.geometric_normal[alive], directions)
            previous_points = points.position[alive]
            if path.size == 0:
                break
        return radiance

    def _add_emitters_hit(self, radiance, path, throughput, points, directions, surface_distance, bsdf_pdf) -> None:
        """Add light seen along BSDF-sampled rays, MIS-weighted against next-event estimation."""
        p = torch.from_numpy(points)
        d = torch.from_numpy(directions)
        nearest = np.full(path.size, np.inf)
        for light in self.scene.lights:
            if _is_delta(light):
                continue
            if light.kind in _INFINITE_KINDS:
                reached = ~np.isfinite(surface_distance)
            else:
                distance = intersect_light(light, p, d).numpy()
                reached = (distance < surface_distance) & (distance < nearest)
                nearest = np.where(reached, distance, nearest)
            if not reached.any():
                continue
            mask = torch.from_numpy(reached)
            emitted = emitted_radiance(light, p[mask], d[mask])
            weight = _power_heuristic(bsdf_pdf[mask], light_pdf(light, p[mask], d[mask]))
            radiance[path[reached]] += (throughput[mask] * emitted * weight[:, None]).double().numpy()

    def _next_event(self, points: ShadingPoints, throughput: torch.Tensor, rng: np.random.Generator) -> np.ndarray:
        """Direct light (N, 3) from one sample of every light, shadow-tested, MIS-weighted."""
        num_points = points.position.shape[0]
        total = torch.zeros((num_points, 3))
        position = torch.from_numpy(points.position)
        frame = [torch.from_numpy(a) for a in (points.tangent, points.bitangent, points.normal)]
        wo_local = to_local(torch.from_numpy(points.wo_world), *frame)
        geometric = torch.from_numpy(points.geometric_normal)
        for light in self.scene.lights:
            u = torch.from_numpy(rng.random((num_points, 1, 2), dtype=np.float32))
            sample = sample_light(light, position, u)
            direction = sample.direction[:, 0]
            pdf = sample.pdf[:, 0]
            usable = (pdf > 0) & ((direction * geometric).sum(-1) > 0) & (sample.radiance[:, 0].amax(-1) > 0)
            if not bool(usable.any()):
                continue
            idx = torch.nonzero(usable).squeeze(1)
            shadow_distance = sample.distance[idx, 0].numpy()
            origins = self.tracer.offset_origins(points.position[idx.numpy()], points.geometric_normal[idx.numpy()],
                                                 direction[idx].numpy())
            t_far = np.where(np.isfinite(shadow_distance), shadow_distance * (1.0 - 1e-4) - self.tracer.epsilon, np.inf)
            visible = torch.from_numpy(~self.tracer.occluded(origins, direction[idx].numpy(), t_far))
            wi_local = to_local(direction[idx], *(f[idx] for f in frame))
            params = points.params.index(idx)
            contribution = reflected_radiance(params, wo_local[idx], wi_local, sample.radiance[idx, 0],
                                              light.diffuse, light.specular)
            if sample.is_delta:
                weight = torch.ones_like(pdf[idx])
            else:
                weight = _power_heuristic(pdf[idx], preview_surface.pdf(params, wo_local[idx], wi_local))
            total[idx] += contribution * (visible.float() * weight / pdf[idx])[:, None]
        return (throughput * total).double().numpy()

    def _sample_bsdf(self, points: ShadingPoints, rng: np.random.Generator):
        """Sample the next direction: (wi_world (N, 3) float32 numpy, weight f cos / pdf (N, 3), pdf (N,))."""
        frame = [torch.from_numpy(a) for a in (points.tangent, points.bitangent, points.normal)]
        wo_local = to_local(torch.from_numpy(points.wo_world), *frame)
        u = torch.from_numpy(rng.random((wo_local.shape[0], 2), dtype=np.float32))
        wi_local, pdf = preview_surface.sample(points.params, wo_local, u)
        wi_world = to_world(wi_local, *frame)
        geometric = torch.from_numpy(points.geometric_normal)
        valid = (pdf > 0) & ((wi_world * geometric).sum(-1) > 0) & (wi_local[..., 2] > 0)
        f_cos = reflected_radiance(points.params, wo_local, wi_local, torch.ones_like(wo_local))
        weight = torch.where(valid[:, None], f_cos / pdf.clamp(min=1e-20)[:, None], torch.zeros_like(f_cos))
        pdf = torch.where(valid, pdf, torch.zeros_like(pdf))
        return wi_world.numpy().astype(np.float32), weight, pdf


def _is_delta(light: Light) -> bool:
    """Lights that BSDF sampling can never hit (zero size)."""
    if light.kind == LightKind.DISTANT:
        return light.angle <= 0.0
    if light.kind == LightKind.SPHERE:
        return light.radius <= 0.0
    return False
