"""How the relighter asks whether light samples reach shading points.

`Visibility` is the interface; implementations: Embree shadow rays over the cache's occluder
triangles (`relight_torch.visibility.embree`, exact, CPU) and shadow maps rendered in torch from the
cache's occluder triangles (`relight_torch.visibility.shadow_maps`, any device).
"""

from __future__ import annotations

from typing import Protocol

import torch

from relight_torch.lights.light import Light


class Visibility(Protocol):
    """Answers shadow queries for one light's samples at N shading points.

    Attributes:
        thread_safe: whether `occluder_distance` may run on several threads at once (tiles of
            points on the CPU, `relight_torch.parallel`); an implementation without it is
            called from one thread.
    """

    thread_safe: bool

    def occluder_distance(
        self,
        light: Light,
        points: torch.Tensor,
        normals: torch.Tensor,
        directions: torch.Tensor,
        distances: torch.Tensor,
    ) -> torch.Tensor:
        """Distance from each point to the first occluder towards each light sample.

        Args:
            light: the light the samples belong to (shadow maps are built per light).
            points: (N, 3) world shading points.
            normals: (N, 3) unit geometric normals on the side the light is tested from.
            directions: (N, S, 3) unit directions towards the light samples.
            distances: (N, S) distances to the samples (inf for distant and dome lights).

        Returns:
            (N, S) distance to the occluder, inf where the sample is visible. When the light's
            ShadowAPI sets no distance limit only occlusion matters, and an implementation may
            report 0 for every occluded sample.
        """
        ...
