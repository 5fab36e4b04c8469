"""Shadow answers remembered per light, so that edits which leave the shadow rays alone trace none.

The gathers' direct light (`relight_torch.diffuse_light.diffuse_radiance`) is recomputed whole
when a light's shaping (cone, focus, IES) changes, but its samples and shadow rays do not depend on
shaping: light sampling is by area and shaping only re-weights the emission
(`lights.emission.sample_light`). Wrapping the visibility in `RememberedVisibility` turns those
edits into a re-weighting: the first queries of each light geometry are answered by the wrapped
visibility and kept; identical later queries are answered from memory.
"""

from __future__ import annotations

import collections

import torch

from relight_torch.direct.rig import geometry_key
from relight_torch.lights.light import Light
from relight_torch.visibility import Visibility

MAX_ANSWERS = 8
"""Queries kept per light (the oldest is dropped): one per chunk of points of a pass."""


class RememberedVisibility:
    """A `Visibility` that answers a repeated query of an unchanged light from memory.

    Args:
        visibility: the visibility asked the first time.

    Attributes:
        counters: 'queries' answered by the wrapped visibility, 'remembered' from memory.
    """

    def __init__(self, visibility: Visibility):
        self.visibility = visibility
        self.thread_safe = False  # its memory is one list per light
        self.counters: collections.Counter[str] = collections.Counter()
        self._answers: dict[str, tuple[tuple, list[tuple[tuple[torch.Tensor, ...], torch.Tensor]]]] = {}

    def occluder_distance(
        self,
        light: Light,
        points: torch.Tensor,
        normals: torch.Tensor,
        directions: torch.Tensor,
        distances: torch.Tensor,
    ) -> torch.Tensor:
        """(N, S) distance to the first occluder, inf where visible (see `Visibility`)."""
        key = geometry_key(light)
        if light.path not in self._answers or self._answers[light.path][0] != key:
            self._answers[light.path] = (key, [])
        queries = (points, normals, directions, distances)
        answers = self._answers[light.path][1]
        for asked, answer in answers:
            if all(a.shape == q.shape and torch.equal(a, q) for a, q in zip(asked, queries, strict=True)):
                self.counters["remembered"] += 1
                return answer
        answer = self.visibility.occluder_distance(light, points, normals, directions, distances)
        answers.append((tuple(q.clone() for q in queries), answer))
        del answers[:-MAX_ANSWERS]
        self.counters["queries"] += 1
        return answer

    def forget(self, path: str) -> None:
        """Drop the answers kept for the light at `path`."""
        self._answers.pop(path, None)
