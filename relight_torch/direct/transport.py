"""A light's cached transport at the shading points it reaches (`relighter.Relighter`'s first stage)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch

from relight_torch.direct.sharing import take_rows
from relight_torch.lights.geometry import LightFrame
from relight_torch.lights.light import Light


@dataclass
class Transport:
    """A light's cached transport: P shading points it reaches, S samples each.

    Attributes:
        points: (P,) int64 indices of the shading points, ascending, or None for all N (the
            light reaches most of them: a scatter per shading pass would cost more than the
            unlit points' zeros).
        directions: (S, P, 3) unit world directions from the points towards the light's
            samples, or None when shaping does not apply (distant and dome lights, whose
            samples are then summed: S = 1).
        lobes: (2, S, P, 3) each sample's diffuse [0] and specular [1] f cos(theta_i) L_i V /
            (pdf S) for the unshaped unit light (V: the ShadowAPI factor); None when `factors`
            holds the transport.
        diffuse_ratio: (P,) the ratio estimator's factor on the diffuse sum (closed-form
            unshadowed irradiance over the samples' estimate of it, `lights.ratio`), or None
            for lights without a closed form.
        factors: (F, S, P) the same as per-sample scalars, for lights whose L_i V is one colour
            times a scalar w (untextured, grey shadow colour): w cos(theta_i) / (pdf S) times the
            BRDF's `preview_surface.split_factors` (F = 4, or 6 with a clearcoat); the
            materials' colours enter per point when the images are made (`combine_factors`).
            None when `lobes` holds the transport.
        colour: (3,) that colour (the unit light's radiance scale) when `factors` is set.
        shadow_sums: (P, 2) per point sum_s w V and sum_s w (w: the samples' cos / (pdf S)
            weights) while the transport is being made, when its visibility is filtered: the
            diffuse factors then carry no V, and `diffuse_ratio` takes the filtered V instead.
        emission_local: (S, P, 3) unit emission directions in the light's frame, from the
            samples towards the points: made from `directions` (then dropped) when a shaping or
            Barzel control first needs them, so a light without them never pays for the change
            of frame.

    Samples lead and colours trail so that the shaping factor broadcasts over whole (P, 3)
    slabs and sums over samples add slabs: torch's CPU kernels vectorise those, while a
    broadcast or a reduction over a middle axis of (P, S, 2, 3) ran 10-20x slower.
    """

    points: torch.Tensor | None
    directions: torch.Tensor | None
    lobes: torch.Tensor | None
    diffuse_ratio: torch.Tensor | None = None
    factors: torch.Tensor | None = None
    colour: torch.Tensor | None = None
    shadow_sums: torch.Tensor | None = None
    emission_local: torch.Tensor | None = None

    @property
    def num_bytes(self) -> int:
        tensors = (self.points, self.directions, self.lobes, self.diffuse_ratio, self.factors, self.emission_local)
        return sum(t.numel() * t.element_size() for t in tensors if t is not None)

    @property
    def shapeable(self) -> bool:
        """Whether the samples keep their directions (shaping and Barzel controls apply)."""
        return self.directions is not None or self.emission_local is not None

    def subset(self, todo: torch.Tensor) -> Transport:
        """The transport at those of the shading points `todo` ((K,) ascending indices) it holds,
        `points` naming them (for progressive refinement, `Relighter.refine`)."""
        if self.points is None:
            return dataclasses.replace(self.gathered(todo, todo), shadow_sums=None)
        where, held = self.locate(todo)
        return dataclasses.replace(self.gathered(where[held], todo[held]), shadow_sums=None)

    def locate(self, wanted: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(where, held): for each of the shading points `wanted` (K,), its row in this transport's
        `points` and whether it holds that point at all (rows where not are arbitrary)."""
        assert self.points is not None, "a transport of all points holds every point at its own row"
        where = torch.searchsorted(self.points, wanted).clamp_(max=max(self.points.shape[0] - 1, 0))
        held = self.points[where] == wanted if self.points.numel() else torch.zeros_like(wanted, dtype=torch.bool)
        return where, held

    def gathered(self, where: torch.Tensor, points: torch.Tensor | None) -> Transport:
        """The transport with each point's values taken from its row `where` (K,) of this one,
        at the shading points `points` (K,) (None: all of them)."""

        def take(values: torch.Tensor | None, dim: int) -> torch.Tensor | None:
            return None if values is None else take_rows(values, dim, where)

        return Transport(
            points,
            take(self.directions, 1),
            take(self.lobes, 2),
            take(self.diffuse_ratio, 0),
            take(self.factors, 2),
            self.colour,
            take(self.shadow_sums, 0),
            take(self.emission_local, 1),
        )

    def emission_in(self, light: Light) -> torch.Tensor:
        """`emission_local` for the light the transport was traced for (its transform)."""
        if self.emission_local is None:
            directions = self.directions
            assert directions is not None, "a transport without emission_local keeps its directions (shapeable)"
            self.emission_local = torch.nn.functional.normalize(
                LightFrame.of(light, directions).vector_to_local(-directions), dim=-1
            )
            self.directions = None
        return self.emission_local
