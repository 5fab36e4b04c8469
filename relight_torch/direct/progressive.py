"""Progressive refinement of the direct relighter (`Relighter.refine`, `relight_torch.progressive`):
a light's unit images made point by point (`Progress`), a light's image at some points, and the
coarse light of a level upsampled with the ratio estimator."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from relight_torch.direct.images import lobe_scales
from relight_torch.direct.points import take
from relight_torch.direct.rig import LightState
from relight_torch.direct.stages import LightStages, SampleGroup
from relight_torch.direct.transport import Transport
from relight_torch.gbuffer import GBuffer
from relight_torch.lights.light import Light


@dataclass
class Progress:
    """A light's unit images made point by point (progressive refinement, `Relighter.refine`).

    Attributes:
        images: (2, N, 3) diffuse and specular unit images at the points done, undefined elsewhere
            (allocated, not zeroed: a coarse frame's first work should not be a pass over N).
        done: (N,) bool, the points done.
        num_done: their count.
        samples_per_point: the light's samples per point, averaged over the points (its sample
            groups, `LightStages.sample_groups`): the work a point costs, for `pending`.
        parts: per sample group, the transports traced so far and the points they were traced
            for, kept (where the memory budget allows it) to become the light's transport once
            every point is done, so that a later shaping edit traces nothing; None: not kept.
        traced: whether they come from shadow rays traced for them (the light kept no transport)
            or from its kept transport.
        shadow_sums: (N, 2) sum_s w V and sum_s w at the points done, for a traced light whose
            visibility is filtered (`Transport.shadow_sums`): its filtered visibility needs every
            point's sums and multiplies `images[0]` once the last point is done. None otherwise.
    """

    images: torch.Tensor
    done: torch.Tensor
    traced: bool
    samples_per_point: float
    num_done: int = 0
    shadow_sums: torch.Tensor | None = None
    parts: list[list[tuple[torch.Tensor, Transport]]] | None = None

    @classmethod
    def start(
        cls,
        gbuffer: GBuffer,
        groups: list[SampleGroup],
        traced: bool,
        keep_parts: bool,
        images: torch.Tensor | None = None,
    ) -> Progress:
        """No point done yet of a light made in sample `groups`, its parts kept with `keep_parts`,
        into `images` ((2, N, 3) in the G-buffer's dtype, taken over; None: allocated)."""
        g = gbuffer
        done = torch.zeros(g.num_samples, dtype=torch.bool, device=g.device)
        samples = sum((g.num_samples if p is None else p.shape[0]) * num for p, num, _ in groups)
        per_point = samples / max(g.num_samples, 1)
        images = g.position.new_empty(2, g.num_samples, 3) if images is None else images
        progress = cls(images, done, traced, per_point)
        if keep_parts:
            progress.parts = [[] for _ in groups]
        return progress

    @property
    def num_bytes(self) -> int:
        tensors = (self.images, self.done, self.shadow_sums)
        kept = sum(part.num_bytes for group in self.parts or () for _, part in group)
        return kept + sum(t.numel() * t.element_size() for t in tensors if t is not None)

    def pending(self, points: torch.Tensor | None) -> float:
        """Light samples still to evaluate at `points` ((M,) ascending; None: all)."""
        if points is None:
            todo = self.done.shape[0] - self.num_done
        elif self.num_done == 0:  # just edited: no pass over the level's points
            todo = points.shape[0]
        else:
            todo = int((~take(self.done, points)).sum())
        return todo * self.samples_per_point


def refine_points(
    stages: LightStages, state: LightState, progress: Progress, points: torch.Tensor | None
) -> tuple[int, float, torch.Tensor | None]:
    """Shade the light of `state` at those of `points` ((M,) ascending; None: all) its `progress`
    lacks; once every point is done, its unit images are complete (and, with kept parts, its
    transport `state.transports`). Returns (points shaded, their samples, the complete unit images
    (2, N, 3) or None)."""
    todo = torch.nonzero(~progress.done).squeeze(-1) if points is None else points[~take(progress.done, points)]
    if todo.numel():
        progress.images.index_fill_(1, todo, 0.0)  # unlit points get no values, only these zeros
        if progress.traced:
            progress.shadow_sums = stages.traced_images(
                state.light, todo, progress.images, progress.shadow_sums, progress.parts
            )
        else:
            assert state.transports is not None  # not traced: shaded from the kept transport
            stages.retrace_stale(state, todo)
            for transport in state.transports:
                part = transport.subset(todo)
                assert part.points is not None  # a subset names its points
                progress.images.index_add_(1, part.points, stages.per_point(state.light, part))
        progress.done[todo] = True
        progress.num_done += int(todo.numel())
    complete = None
    if points is None or progress.num_done == progress.done.shape[0]:
        images = progress.images
        visibility = None
        if progress.shadow_sums is not None:  # as in LightStages.streamed_images
            visibility = stages.filter.visibility(progress.shadow_sums)
            images[0].mul_(visibility.unsqueeze(-1))
        if progress.parts is not None:  # the transport `LightStages.transports` would have made
            state.transports = [stages.kept_transport(group) for group in progress.parts if group]
            state.stale = None
            if visibility is not None:
                stages.filter.fold(state.transports, visibility)
        stages.counters["visibility"] += int(progress.traced)
        stages.counters["shading"] += 1
        complete = images
    return int(todo.numel()), int(todo.numel()) * progress.samples_per_point, complete


def reshade_at(stages: LightStages, state: LightState, rows: torch.Tensor) -> None:
    """After an edit of the materials at `rows` (N,) bool (`material_edits`) that the light's kept
    transport already serves (its colours enter when its images are made; `LightStages.retrace_at`
    wrote the rest): its unit images become a `Progress` whose points elsewhere are done, so that
    refinement (or the next render) shades those points again from that transport, tracing nothing."""
    progress = state.progress
    if state.images is not None:
        groups = stages.sample_groups(stages.transport_light(state.light))
        images = state.images.to(stages.gbuffer.position.dtype)  # taken over, or widened from half
        progress = Progress.start(stages.gbuffer, groups, traced=False, keep_parts=False, images=images)
        progress.done.copy_(~rows)
        state.images, state.progress = None, progress
    elif progress is None or progress.traced:
        return  # nothing shaded yet from the transport: the next shading uses the new colours
    else:
        progress.done.logical_and_(~rows)
    progress.num_done = int(progress.done.sum())


def add_light_at(
    values: torch.Tensor,
    state: LightState,
    points: torch.Tensor,
    light_mask: Callable[[Light], torch.Tensor | None],
) -> torch.Tensor | None:
    """values (M, 3) plus the light's image at shading points `points` (M,), from its unit
    images or, while they are made, from the points done (`light_mask`: its (N, 1) light-link
    mask, `Relighter.light_mask`). A light whose visibility will be filtered adds its specular
    light only and returns (M, 5): its unshadowed diffuse light and its sums of w V and w at the
    points (see `Relighter.coarse_values`); None otherwise."""
    light = state.light
    scales = lobe_scales(light, values)
    if scales is None:
        return None
    sums = None
    if state.images is not None:
        unit = state.images.index_select(1, points).to(values.dtype)
    else:
        assert state.progress is not None, "a light without images is refined before it is shown"
        unit = state.progress.images.index_select(1, points)
        if state.progress.shadow_sums is not None:
            sums = take(state.progress.shadow_sums, points)
    diffuse_scale, specular_scale = scales
    mask = light_mask(light)
    if mask is not None:
        diffuse_scale, specular_scale = diffuse_scale * take(mask, points), specular_scale * take(mask, points)
    values.addcmul_(unit[1], specular_scale)
    if sums is not None:
        return torch.cat((unit[0] * diffuse_scale, sums), dim=1)
    values.addcmul_(unit[0], diffuse_scale)
    return None


def coarse_light(upsampled: torch.Tensor) -> torch.Tensor:
    """(M, 3) light from `Relighter.coarse_values` upsampled (M, C): its light, plus per light
    whose visibility will be filtered its unshadowed diffuse light times the ratio of its
    upsampled sums of w V and w: the ratio estimator (Heitz et al. 2018) with the upsampling as
    the filter, where each point's own ratio (one light sample at matte points) would show as
    blotches."""
    coarse = upsampled[:, :3]
    for first in range(3, upsampled.shape[1], 5):
        unshadowed, sums = upsampled[:, first : first + 3], upsampled[:, first + 3 : first + 5]
        visible = torch.where(sums[:, 1] > 0, sums[:, 0] / sums[:, 1].clamp(min=1e-30), 0.0)
        coarse = coarse + unshadowed * visible.unsqueeze(-1)
    return coarse
