"""Progressive relighting: after any edit a coarse frame within a time budget, then refinements
that end in exactly the frame `render()` gives.

A relighter whose `progressive` capability is set (`CacheRelighter`) shades the lights changed
since its last exact frame at one point per p x p pixels (`refine(p)`, `relight_torch.levels`),
brings them to every pixel by edge-aware upsampling guided by its deep framebuffer, and adds the
exact image of the lights that did not change. The work of each coarse frame is kept per light and
per point, so the next finer frame shades only the points it adds and the exact frame
(`refine(None)`) the rest; an edit made between two frames drops only the edited light's work
(what the edit leaves valid, as for `render()`), and the next frame starts again from the coarse
end. Interactive lighting tools work this way (Pellacini et al. 2005, Lpics; Ragan-Kelley et al.
2007, Lightspeed): an answer within a frame of every edit, final quality while the artist looks.

    frames = progressive_frames(relighter, budget_ms=33.0)
    first = next(frames)          # within the budget (the cost model permitting, see below)
    relighter.set_light(edited)   # an edit mid-refinement: the next frame is coarse again
    for frame in frames:          # refinements, the last one `done` and equal to render()
        show(frame.image)

The first frame after an edit is the finest level whose predicted cost fits `budget_ms`: a
per-point cost and a per-level overhead, measured on the frames made so far (a fresh relighter
starts at the coarsest level, and a level's first frame also builds its upsampling weights).
"""

from __future__ import annotations

import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import torch

from relight_torch.protocol import CacheRelighter, refuse_progressive

STRIDES: tuple[int, ...] = (16, 8, 4, 2, 1)
"""Pixels per block side of the coarse levels, coarse to fine; the exact frame follows them."""

DEFAULT_BUDGET_MS = 33.0
"""Time budget of the first frame after an edit (30 frames a second)."""


def level_label(stride: int | None) -> str:
    """A level as tables name it: '1/p' (one shaded point per p x p pixels), or 'exact'."""
    return "exact" if stride is None else f"1/{stride}"


@dataclass(frozen=True)
class Frame:
    """One progressive frame.

    Attributes:
        image: (H, W, 3) linear radiance, camera exposure applied.
        stride: the level's pixels per block side; None for the exact frame.
        elapsed_ms: wall milliseconds from the edit's first frame request to this frame's end.
        frame_ms: wall milliseconds this frame took.
        evaluated: light evaluations (a light at a shading point) this frame made.
        done: the exact frame (equal to the relighter's `render()`): the refinement of the
            current rig is over.
    """

    image: torch.Tensor
    stride: int | None
    elapsed_ms: float
    frame_ms: float
    evaluated: int
    done: bool


@dataclass
class CostModel:
    """Predicted wall ms of a frame: a level's overhead (its last frame less its work) plus the
    work it will do (`CacheRelighter.pending`: light samples) times the median ms per sample of
    the last frames that did some.

    Attributes:
        per_sample_ms: ms per light sample of the last frames that evaluated at least 1,000.
        overhead_ms: level (stride or None) -> its last frame's ms less its samples' share.
    """

    per_sample_ms: list[float] = field(default_factory=list)
    overhead_ms: dict[int | None, float] = field(default_factory=dict)

    def record(self, stride: int | None, frame_ms: float, work: float) -> None:
        if work >= 1000:
            self.per_sample_ms = (self.per_sample_ms + [frame_ms / work])[-9:]
        self.overhead_ms[stride] = max(0.0, frame_ms - work * self._per_sample())

    def predict(self, stride: int | None, work: float) -> float | None:
        """Predicted ms, or None for a level not seen yet (or no cost per sample measured)."""
        if stride not in self.overhead_ms or (work and not self.per_sample_ms):
            return None
        return self.overhead_ms[stride] + work * self._per_sample()

    def _per_sample(self) -> float:
        if not self.per_sample_ms:
            return 0.0
        return sorted(self.per_sample_ms)[len(self.per_sample_ms) // 2]


def check_progressive(relighter: CacheRelighter) -> None:
    """Raise RelightError unless the relighter can refine progressively (its `progressive` flag)."""
    if not relighter.progressive:
        refuse_progressive(relighter)


def progressive_frames(
    relighter: CacheRelighter,
    budget_ms: float = DEFAULT_BUDGET_MS,
    strides: Sequence[int] = STRIDES,
    costs: CostModel | None = None,
) -> Iterator[Frame]:
    """Frames of the relighter's current rig, coarse to exact (see the module doc).

    Args:
        relighter: a relighter whose `progressive` is True.
        budget_ms: the first frame after an edit is the finest level predicted to fit it
            (0: always the coarsest).
        strides: the coarse levels' pixels per block side, decreasing; the exact frame follows.
        costs: the cost model to predict with and update (keep one per relighter across edits:
            a fresh one knows nothing and starts at the coarsest level).

    Yields:
        `Frame`s, the last one exact (`done`). An edit of the relighter between two frames
        starts the sequence again from the level the budget allows.

    Raises:
        RelightError: the relighter's method has no progressive refinement.
    """
    check_progressive(relighter)
    if list(strides) != sorted(set(strides), reverse=True) or (strides and min(strides) < 1):
        raise ValueError(f"strides must be distinct, decreasing and >= 1, got {list(strides)}")
    levels: list[int | None] = [*strides, None]
    costs = CostModel() if costs is None else costs
    seen: int | None = None
    index = 0
    start = time.perf_counter()
    while True:
        if relighter.edits != seen:
            seen, start = relighter.edits, time.perf_counter()
            index = _first_level(relighter, levels, budget_ms, costs)
        stride = levels[index]
        began = time.perf_counter()
        result = relighter.refine(stride)
        end = time.perf_counter()
        frame_ms = 1e3 * (end - began)
        costs.record(stride, frame_ms, result.work)
        shown = None if result.exact else stride
        yield Frame(result.image, shown, 1e3 * (end - start), frame_ms, result.evaluated, result.exact)
        if result.exact and relighter.edits == seen:
            return
        index = min(index + 1, len(levels) - 1)


def _first_level(relighter: CacheRelighter, levels: list[int | None], budget_ms: float, costs: CostModel) -> int:
    """The finest level predicted to fit the budget, else the coarsest."""
    for index in range(len(levels) - 1, 0, -1):
        if levels[index] not in costs.overhead_ms:  # never made: unknown cost (and perhaps unbuilt)
            continue
        predicted = costs.predict(levels[index], relighter.pending(levels[index]))
        if predicted is not None and predicted <= budget_ms:
            return index
    return 0
