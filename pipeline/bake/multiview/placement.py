"""Caching-camera placement (Kim et al. 2009, section III.1): the paper's four steps.

1. Primary cameras: omni-directional (six 90-degree faces) at the centres of the largest maximal
   empty spheres (`spheres`), taken while each adds at least `min_primary_gain` of the samples'
   importance to the covered set (at most `max_primary`). A face that sees no sample is dropped.
2. Secondary cameras: at the winning cell of the voting grid of the uncovered samples (`voting`).
3. Attributes: a secondary camera looks at the importance-weighted centre p_c of the uncovered
   samples it sees (eq. 3); its field of view is twice the largest angle between p_c and them,
   at most `max_fov` (eq. 4: samples outside stay uncovered); near and far clip at half the
   nearest and 1.5 x the farthest covered sample (recorded only: the deep framebuffer is traced
   unclipped, as the correspondence depth test needs every occluder); the square resolution
   follows the importance share the camera covers (`cameras.resolution_from_coverage`).
4. Repeat 2-3 while the uncovered importance fraction is at least `coverage`.
Samples no camera in the box can see are counted as unreachable and left out of the fractions:
those whose whole front hemisphere is blocked within one grid cell (under an object resting on
another), and those facing out of the box (one cell along the normal leaves it: the outside of a
set's walls and roof when the box is the set's bounds).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.bake.multiview.cameras import CUBE_FORWARD, look_camera, resolution_from_coverage
from pipeline.bake.multiview.samples import SurfaceSamples, object_importance, sample_surfaces, seen_from
from pipeline.bake.multiview.spheres import maximal_spheres
from pipeline.bake.multiview.voting import hemisphere_directions, vote
from pipeline.errors import RelightError
from pipeline.scene.types import Camera, Scene
from pipeline.tracing import Tracer, shared_tracer
from relight_torch.multiview.views import PRIMARY, SECONDARY

CUBE_UP = np.array([[0, 1, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1], [0, 1, 0], [0, 1, 0]], np.float64)
"""Up vectors of the cube faces (`CUBE_FORWARD` order)."""


@dataclass(frozen=True)
class PlacementSettings:
    """Parameters of the placement (defaults: the paper's where it gives them).

    Attributes:
        coverage: stop when the uncovered fraction of importance falls below this.
        num_samples: surface samples.
        patience: k, consecutive sphere searches finding nothing new (paper: 50).
        max_primary: most primary (omni) cameras.
        min_primary_gain: least importance fraction a further primary camera must add.
        max_secondary: most secondary cameras.
        grid_size: n, voting grid cells along the box's longest side (paper: 128).
        num_rays: rays per uncovered sample in the vote.
        max_voters: uncovered samples voting per round (a random subset beyond it).
        max_fov: widest secondary field of view, degrees (paper: 120).
        min_fov: narrowest secondary field of view, degrees.
        min_resolution, max_resolution: caching image sizes (powers of two).
        seed: the placement is a deterministic function of the scene, box and settings.
    """

    coverage: float = 0.02
    num_samples: int = 20000
    patience: int = 50
    max_primary: int = 2
    min_primary_gain: float = 0.05
    max_secondary: int = 16
    grid_size: int = 64
    num_rays: int = 32
    max_voters: int = 2000
    max_fov: float = 120.0
    min_fov: float = 10.0
    min_resolution: int = 64
    max_resolution: int = 1024
    seed: int = 0

    def check(self) -> None:
        """Raise ValueError on a setting out of range."""
        if not 0.0 <= self.coverage < 1.0:
            raise ValueError(f"coverage must be in [0, 1), got {self.coverage}")
        if not 0.0 < self.min_fov <= self.max_fov <= 120.0:
            raise ValueError(f"need 0 < min_fov <= max_fov <= 120 degrees, got {self.min_fov}, {self.max_fov}")
        if (
            min(self.num_samples, self.patience, self.grid_size, self.num_rays, self.max_voters, self.min_resolution)
            < 1
            or self.max_resolution < self.min_resolution
        ):
            raise ValueError(f"sample, ray, grid and resolution settings must be positive: {self}")


@dataclass(frozen=True)
class CachingCamera:
    """One placed camera: a cube face (kind PRIMARY, group = its cube) or a SECONDARY camera."""

    camera: Camera
    kind: int
    group: int
    num_covered: int


@dataclass(frozen=True)
class Placement:
    """The cameras and the coverage they reach.

    Attributes:
        cameras: in placement order.
        num_samples, num_unreachable: surface samples, and those no camera can see (left out below).
        primary_fraction: importance fraction the primary cameras cover.
        uncovered_fraction: importance fraction no camera covers at the end.
        num_spheres: maximal spheres found.
        box: (lo, hi) the workspace.
    """

    cameras: list[CachingCamera]
    num_samples: int
    num_unreachable: int
    primary_fraction: float
    uncovered_fraction: float
    num_spheres: int
    box: tuple[np.ndarray, np.ndarray]

    @property
    def num_primary(self) -> int:
        return len({c.group for c in self.cameras if c.kind == PRIMARY})

    @property
    def num_secondary(self) -> int:
        return sum(c.kind == SECONDARY for c in self.cameras)


def _unreachable(
    tracer: Tracer, samples: SurfaceSamples, reach: float, box: tuple[np.ndarray, np.ndarray], rng: np.random.Generator
) -> np.ndarray:
    """(M,) bool: samples facing out of the box, or whose 16 hemisphere rays are all blocked within `reach`."""
    ahead = samples.position + reach * samples.normal
    outward = np.any((ahead < box[0]) | (ahead > box[1]), axis=-1)
    directions = hemisphere_directions(samples.normal, 16, rng).reshape(-1, 3)
    normals = np.repeat(samples.normal, 16, axis=0)
    origins = tracer.offset_origins(np.repeat(samples.position, 16, axis=0), normals, directions)
    blocked = tracer.occluded(origins, directions, np.full(len(directions), reach, np.float32))
    return outward | blocked.reshape(-1, 16).all(axis=1)


def _clip_range(samples: SurfaceSamples, seen: np.ndarray, position: np.ndarray) -> tuple[float, float]:
    distance = np.linalg.norm(samples.position[seen] - position, axis=-1)
    return 0.5 * float(distance.min()), 1.5 * float(distance.max())


def _up(scene: Scene) -> np.ndarray:
    return np.array([0.0, 0.0, 1.0]) if scene.up_axis == "Z" else np.array([0.0, 1.0, 0.0])


def _primary(tracer, samples, spheres, total, covered, settings) -> list[CachingCamera]:
    """Cube cameras at the largest spheres, while each adds enough coverage (updates `covered`)."""
    cameras: list[CachingCamera] = []
    for sphere in spheres:
        if len({c.group for c in cameras}) >= settings.max_primary:
            break
        seen = seen_from(tracer, samples, sphere.centre)
        if samples.weight[seen & ~covered].sum() < settings.min_primary_gain * total:
            continue
        group = len({c.group for c in cameras})
        direction = samples.position - sphere.centre
        axis = np.abs(direction).argmax(axis=-1)
        face = 2 * axis + (np.take_along_axis(direction, axis[:, None], -1)[:, 0] < 0)
        for f in range(6):
            face_seen = seen & (face == f)
            if not face_seen.any():
                continue
            resolution = resolution_from_coverage(
                samples.weight[face_seen].sum() / total, settings.min_resolution, settings.max_resolution
            )
            camera = look_camera(
                f"/Caching/Primary{group}_{f}",
                sphere.centre,
                CUBE_FORWARD[f],
                CUBE_UP[f],
                90.0,
                resolution,
                *_clip_range(samples, face_seen, sphere.centre),
            )
            cameras.append(CachingCamera(camera, PRIMARY, group, int(face_seen.sum())))
        covered |= seen
    return cameras


def _secondary(
    tracer, samples, candidates, total, up, box, settings, rng, index
) -> tuple[CachingCamera | None, np.ndarray]:
    """One secondary camera for the uncovered `candidates` (indices) and the samples it covers;
    (None, empty) when the vote finds none."""
    voters = candidates
    if voters.size > settings.max_voters:
        voters = rng.choice(voters, settings.max_voters, replace=False)
    centre, votes = vote(tracer, samples.subset(voters), *box, settings.grid_size, settings.num_rays, rng)
    if votes <= 0:
        return None, np.zeros(0, np.int64)
    uncovered = samples.subset(candidates)
    seen = seen_from(tracer, uncovered, centre)
    if not seen.any():
        return None, np.zeros(0, np.int64)
    weight = uncovered.weight[seen]
    target = (weight[:, None] * uncovered.position[seen]).sum(0) / weight.sum()  # eq. 3
    axis = target - centre
    axis /= np.linalg.norm(axis)
    rays = uncovered.position - centre
    angle = np.degrees(np.arccos(np.clip(rays @ axis / np.linalg.norm(rays, axis=-1), -1.0, 1.0)))
    half = min(float(angle[seen].max()), settings.max_fov / 2)  # eq. 4
    inside = seen & (angle <= half)
    if not inside.any():
        return None, np.zeros(0, np.int64)
    resolution = resolution_from_coverage(
        uncovered.weight[inside].sum() / total, settings.min_resolution, settings.max_resolution
    )
    camera = look_camera(
        f"/Caching/Secondary{index}",
        centre,
        axis,
        up,
        max(2 * half, settings.min_fov),
        resolution,
        *_clip_range(uncovered, inside, centre),
    )
    return CachingCamera(camera, SECONDARY, index, int(inside.sum())), candidates[inside]


def place_cameras(
    scene: Scene,
    settings: PlacementSettings = PlacementSettings(),
    box: tuple[np.ndarray, np.ndarray] | None = None,
    tracer: Tracer | None = None,
) -> Placement:
    """Place the caching cameras of `scene` within `box` (default: the scene's bounds)."""
    settings.check()
    tracer = tracer or shared_tracer(scene)
    rng = np.random.default_rng(settings.seed)
    lo, hi = (np.asarray(b, np.float64) for b in (box or scene.bounds))
    samples = sample_surfaces(scene, settings.num_samples, rng, object_importance(scene), (lo, hi))
    delta = float(np.max(hi - lo)) / settings.grid_size
    unreachable = _unreachable(tracer, samples, delta, (lo, hi), rng)
    total = float(samples.weight[~unreachable].sum())
    if total <= 0:
        raise RelightError(f"{scene.source}: no surface sample can be seen from inside the box")
    covered = unreachable.copy()
    spheres = maximal_spheres(samples.subset(~unreachable), lo, hi, delta, settings.patience, rng)
    cameras = _primary(tracer, samples, spheres, total, covered, settings)
    primary_fraction = float(samples.weight[covered & ~unreachable].sum()) / total
    up = _up(scene)
    for index in range(settings.max_secondary):
        if samples.weight[~covered].sum() < settings.coverage * total:
            break
        camera, newly = _secondary(tracer, samples, np.flatnonzero(~covered), total, up, (lo, hi), settings, rng, index)
        if camera is None:
            break
        cameras.append(camera)
        covered[newly] = True
    return Placement(
        cameras=cameras,
        num_samples=samples.num_samples,
        num_unreachable=int(unreachable.sum()),
        primary_fraction=primary_fraction,
        uncovered_fraction=float(samples.weight[~covered].sum()) / total,
        num_spheres=len(spheres),
        box=(lo, hi),
    )
