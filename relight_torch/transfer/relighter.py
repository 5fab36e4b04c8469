"""The transfer relighter: direct light from the direct `Relighter`, plus indirect light.

Per light, linear as the direct part: the unit light's gather radiance g_d (one reflection off
the gathers, `gather_radiance`) and its indirect image F (I + M + ... + M^(B-1)) g_d are cached,
and scaled by the light's colour factor at render time. A colour edit therefore re-renders
nothing; a move or a reshape recomputes that light's gather light and one pass of sparse
products; a light-link edit re-masks the cached gather light (UsdLux linking on the gathers, as
`diffuse_light` applies it) and redoes the products only; other lights keep theirs. Emissive
gathers add a light-independent term, computed once.
"""

from __future__ import annotations

import collections
import dataclasses

import torch

from relight_torch.diffuse_light import link_mask
from relight_torch.direct import gradients
from relight_torch.direct.images import unit_light
from relight_torch.direct.relighter import Relighter
from relight_torch.indirect import IndirectRelighter, gather_light_key
from relight_torch.indirect_samples import GatherSamples, gather_radiance
from relight_torch.light_samples import fixed_light_samples
from relight_torch.lights.light import Light, light_snapshot
from relight_torch.protocol import tensor_bytes
from relight_torch.transfer.haar import haar2d
from relight_torch.transfer.sparse import SparseRows, column_norms, cull_light
from relight_torch.upsample import EdgeAwareUpsampler

GATHER_SAMPLES = 4
"""Light samples per gather for area lights by default (see `TransferRelighter`)."""

PREVIEW_BOUNCES = 2
"""Terms of the bounce series (g, M g) of the stand-in light vector of a first coarse frame
(`TransferRelighter._preview_vector`); each further one costs a product with M."""


def wavelet_light(radiance: torch.Tensor, bounce: SparseRows | None, num_bounces: int, side: int) -> torch.Tensor:
    """(G, 3) gather radiance g_d, texture order -> (G, 3) the Haar coefficients (flattened row-major)
    of the light that F multiplies: (I + M + ... + M^(B-1)) g_d, M applied to wavelet light.

    Args:
        radiance: (G, 3) light leaving the gathers after one reflection.
        bounce: M, G wavelet rows over G (None when `num_bounces` is 1).
        num_bounces: B >= 1.
        side: the gathers' texture side (G = side^2).
    """

    def wavelet(values: torch.Tensor) -> torch.Tensor:
        return haar2d(values.reshape(side, side, 3)).reshape(-1, 3)

    total, bounced = radiance, radiance
    for _ in range(num_bounces - 1):
        if bounce is None:
            raise ValueError(f"{num_bounces} bounces need the bounce matrix M")
        bounced = bounce.matmul(wavelet(bounced))
        total = total + bounced
    return wavelet(total)


@dataclasses.dataclass(frozen=True)
class FrozenTransfer:
    """A light's visibility at one pose for `TransferRelighter.differentiable_light_image`.

    Attributes:
        direct: the view samples' (`Relighter.freeze_light`).
        gathers: the gathers' (`gradients.frozen_visibility`).
        u: (G, S, 2) the gathers' fixed light-sample numbers.
    """

    direct: gradients.FrozenVisibility
    gathers: gradients.FrozenVisibility
    u: torch.Tensor


@dataclasses.dataclass
class _Rows:
    """F rows of one light vector made a few at a time (progressive refinement).

    Attributes:
        light_link: the link the vector was masked with.
        vector: (G, 3) the wavelet light F multiplies (`TransferRelighter.light_vector`).
        values: (R, 3) the rows done (undefined elsewhere); done: (R,) bool; num_done: their count.
    """

    light_link: tuple[str, ...] | None
    vector: torch.Tensor
    values: torch.Tensor
    done: torch.Tensor
    num_done: int = 0


@dataclasses.dataclass
class _IndirectState:
    gather_key: object  # `gather_light_key` of the unit light less its link
    radiance: torch.Tensor  # (G, 3) its gather light g_d, no light link applied
    light_link: tuple[str, ...] | None = None  # the link `unit_indirect` was masked with
    unit_indirect: torch.Tensor | None = None  # (R, 3) its indirect radiance at the F rows
    rows: _Rows | None = None  # `unit_indirect` in the making, while it is None or stale
    vector: torch.Tensor | None = None  # (G, 3) the light vector `unit_indirect` was made of
    shaping: object = None  # light_snapshot of the light's (shaping, barzel) (`_preview_vector`)


class TransferRelighter(IndirectRelighter[_IndirectState]):
    """Direct + indirect relighting of one transfer cache.

    Progressive (`CacheRelighter.refine`): a coarse frame multiplies only the F rows of its
    level's pixels, and keeps them (`_Rows`) for the finer frames and the exact one. The first
    coarse frame after a light's edit takes a stand-in light vector (`_preview_vector`: the
    light's vector before the edit, else its gather light at one sample with PREVIEW_BOUNCES
    terms), so that it never waits for the gather light and the bounces; the next frame makes the
    light's own.

    Args:
        direct: the direct relighter of the cache's deep framebuffer (lights live there; its
            visibility also answers the gathers' shadow queries).
        gathers: the G gather samples, texture order, on the direct relighter's device.
        view_pixels: (R,) int64 pixel (row * W + col) of each F row (in the reduced image when
            `upsampler` is given).
        final_gather: F, R wavelet rows over G.
        bounce: M, G wavelet rows over G, or None for one bounce.
        num_bounces: B >= 1; M is applied B - 1 times.
        gather_samples: light samples per gather for area lights (dome lights always take the
            direct settings' `dome_samples`). The gather light costs about as many shadow rays as
            samples, and F averages its noise over many gathers: against 256 samples, the indirect
            image is 2.3 / 0.5 / 0.1 % RMS off at 1 / 4 / 16 samples on the glossy scene's sphere
            lights and 2.3 / 1.2 / 0.7 % on the Cornell box's rect (96 x 96, 4,096 gathers), far
            below the method's own ~6 % (docs/TRANSFER.md). A lamp 10 mm from a wall, which lost
            a third of its indirect light at 4 samples before the rect's closed form (the ratio
            estimator) reached the gathers, now gives the same image at 1 to 64 samples.
        upsampler: for F rows baked at a reduced resolution (`--indirect-scale`), the edge-aware
            map from them to the full image's pixels (`upsample.edge_aware_upsampler`); None when
            `view_pixels` are pixels of the full image.
        indirect_scale: full pixels per side of an F row's pixel (1 without `upsampler`).
        cull_tolerance: on-the-fly culling of weak wavelet lights in the F product (the chapter's
            section 9.8.3, `sparse.cull_light`): the Haar coefficients of the gather light whose
            weight |l_c| ||F_c|| sums to at most this fraction of the total are zeroed, bounding
            the dropped indirect light's L2 norm by that fraction of the summed weights. It
            changes accuracy, not speed, on the CPU: the row product's embedding_bag touches every
            stored entry, and a product over the kept columns alone (gather, multiply,
            index_add_) cost 30-80x more per entry there, more than any culling saved (docs/TRANSFER.md).
    """

    progressive = True  # `pending` and `refine` (`CacheRelighter`)
    # `relight solve` differentiates the direct light and the gathers' direct light, which the
    # transport carries linearly (`protocol.GradientRelighter`).
    gradient_kinds = frozenset(gradients.GEOMETRY_KINDS)

    def __init__(
        self,
        direct: Relighter,
        gathers: GatherSamples,
        view_pixels: torch.Tensor,
        final_gather: SparseRows,
        bounce: SparseRows | None = None,
        num_bounces: int = 1,
        gather_samples: int = GATHER_SAMPLES,
        upsampler: EdgeAwareUpsampler | None = None,
        cull_tolerance: float = 0.0,
        indirect_scale: int = 1,
    ):
        if final_gather.num_columns != gathers.num_gathers or final_gather.num_rows != view_pixels.shape[0]:
            raise ValueError(
                f"F is {final_gather.num_rows}x{final_gather.num_columns}; expected "
                f"{view_pixels.shape[0]} view rows x {gathers.num_gathers} gathers"
            )
        if num_bounces < 1 or (num_bounces > 1 and (bounce is None or bounce.num_rows != gathers.num_gathers)):
            raise ValueError(
                f"{num_bounces} bounces need M as {gathers.num_gathers} rows (got "
                f"{None if bounce is None else bounce.num_rows})"
            )
        if gather_samples < 1:
            raise ValueError(f"gather_samples must be >= 1, got {gather_samples}")
        if not 0.0 <= cull_tolerance < 1.0:
            raise ValueError(f"cull_tolerance must lie in [0, 1), got {cull_tolerance}")
        super().__init__(direct)
        self.gathers = gathers
        self.view_pixels = view_pixels
        self.final_gather = final_gather
        self.bounce = bounce
        self.num_bounces = num_bounces
        self.gather_samples = gather_samples
        self.upsampler = upsampler
        self.indirect_scale = indirect_scale
        self.cull_tolerance = cull_tolerance
        self._column_norms = column_norms(final_gather) if cull_tolerance > 0 else None
        self.counters: collections.Counter[str] = collections.Counter()
        self._emission_indirect: torch.Tensor | None = None
        self._previewed: dict[str, object] = {}  # light path -> gather key of its last stand-in frame

    def scene_diagonal(self) -> float:
        """`protocol.GradientRelighter.scene_diagonal`: the direct relighter's."""
        return self.direct.scene_diagonal()

    def freeze_light(self, light: Light, pose: gradients.LightPose, num_samples: int) -> FrozenTransfer:
        """`protocol.GradientRelighter.freeze_light`: the view samples' and the gathers' shadow rays."""
        g = self.gathers
        u = fixed_light_samples(
            g.num_gathers, num_samples, self.direct.settings.seed, g.position.device, g.position.dtype
        )
        return FrozenTransfer(
            self.direct.freeze_light(light, pose, num_samples),
            gradients.frozen_visibility(self.direct.visibility, light, pose, g.position, g.normal, u),
            u,
        )

    def differentiable_light_image(
        self, light: Light, pose: gradients.LightPose, frozen: FrozenTransfer
    ) -> torch.Tensor:
        """`protocol.GradientRelighter.differentiable_light_image`: the direct image plus the
        indirect image F (I + M + ...) g_d of the gathers' differentiable direct light."""
        direct = self.direct.differentiable_light_image(light, pose, frozen.direct)
        g = self.gathers
        radiance = gradients.diffuse_light(light, pose, g.position, g.normal, g.albedo, frozen.u, frozen.gathers)
        linked = link_mask(light, g.object_id, self.direct.object_paths)
        if linked is not None:
            radiance = radiance * linked.unsqueeze(-1).to(radiance)
        return direct + self._rows_to_image(self.transfer(radiance.to(g.position.dtype)))

    def transfer(self, radiance: torch.Tensor) -> torch.Tensor:
        """F (I + M + ... + M^(B-1)) radiance: (G, 3) gather radiance -> (R, 3) at the view rows, clamped
        at zero: truncated wavelet rows ring slightly negative (-2e-4 against a peak of 0.13) where a
        light reaches only a few gathers, and reflected radiance never is."""
        return self.final_gather.matmul(self.light_vector(radiance)).clamp_(min=0.0)

    def light_vector(self, radiance: torch.Tensor, num_bounces: int | None = None) -> torch.Tensor:
        """(G, 3) gather radiance -> (G, 3) the wavelet light F multiplies in `transfer`: the
        bounces added (`num_bounces` terms, default all), Haar-transformed, weak wavelet lights culled."""
        self.counters["transfer"] += 1
        bounces = self.num_bounces if num_bounces is None else min(num_bounces, self.num_bounces)
        light = wavelet_light(radiance, self.bounce, bounces, self.gathers.side)
        if self.cull_tolerance > 0.0:
            assert self._column_norms is not None  # computed whenever culling is on
            light = cull_light(light, self._column_norms, self.cull_tolerance)
        return light

    def invalidate_indirect(self) -> None:
        """Drop every cached indirect image (after `num_bounces` changes); the gather light is kept."""
        self._emission_indirect = self._static = None
        for state in self._per_light.values():
            state.unit_indirect = state.rows = state.vector = None

    def _rows_to_image(self, rows: torch.Tensor) -> torch.Tensor:
        """(R, 3) values at the F rows' view samples -> (H, W, 3) image, camera exposure applied."""
        if self.upsampler is None:
            return super()._rows_to_image(rows)
        height, width = (size // self.direct.supersampling for size in self.direct.gbuffer.image_size)
        return self.upsampler(rows).reshape(height, width, 3) * self.direct.exposure_scale

    # -- cached stages --------------------------------------------------------------------------

    def _indirect_bytes(self) -> int:
        rows = [state.rows for state in self._per_light.values() if state.rows is not None]
        return tensor_bytes(
            self._emission_indirect,
            *(t for state in self._per_light.values() for t in (state.radiance, state.unit_indirect, state.vector)),
            *(t for part in rows for t in (part.vector, part.values, part.done)),
        )

    def _emission_rows(self) -> torch.Tensor:
        if self._emission_indirect is None:
            self._emission_indirect = self.transfer(self.gathers.emission)
        return self._emission_indirect

    def _unit_indirect(self, light: Light) -> torch.Tensor:
        """F (I + M + ...) g_d of the unit light: its gather light is traced again only when what
        it depends on changes; a light-link edit re-masks the cached gather light and transfers.
        Rows a coarse frame made (`_unit_indirect_at`) are kept: only the others are multiplied."""
        state = self._gather_state(light)
        if state.unit_indirect is None or state.light_link != light.light_link:
            rows = state.rows
            if rows is None or rows.light_link != light.light_link:
                state.vector = self.light_vector(self._linked_radiance(state, light))
                state.unit_indirect = self.final_gather.matmul(state.vector).clamp_(min=0.0)
            else:
                self._fill_rows(rows, torch.nonzero(~rows.done).squeeze(-1))
                state.unit_indirect, state.vector = rows.values, rows.vector
            state.light_link, state.rows = light.light_link, None
        return state.unit_indirect

    def _unit_indirect_at(self, light: Light, rows: torch.Tensor) -> torch.Tensor:
        """(K, 3) the unit light's indirect radiance at F rows `rows` (K,): from `unit_indirect`
        when current, else those rows multiplied (once) and kept for the rest; in the first frame
        after the light's edit, those rows of a stand-in vector (`_preview_vector`), not kept."""
        preview = self._preview_vector(light)
        if preview is not None:
            needed, inverse = torch.unique(rows, return_inverse=True)
            product = self.final_gather.select_rows(needed).matmul(preview).clamp_(min=0.0)
            return product.index_select(0, inverse)
        state = self._gather_state(light)
        if state.unit_indirect is not None and state.light_link == light.light_link:
            return state.unit_indirect.index_select(0, rows)
        if state.rows is None or state.rows.light_link != light.light_link:
            vector = self.light_vector(self._linked_radiance(state, light))
            num_rows = self.final_gather.num_rows
            done = torch.zeros(num_rows, dtype=torch.bool, device=vector.device)
            state.rows = _Rows(light.light_link, vector, vector.new_empty(num_rows, 3), done)
        needed = torch.unique(rows)
        self._fill_rows(state.rows, needed[~state.rows.done.index_select(0, needed)])
        return state.rows.values.index_select(0, rows)

    def _preview_vector(self, light: Light) -> torch.Tensor | None:
        """A stand-in light vector for the first coarse frame after the light's edit, None when
        the light's own is current or its stand-in frame was made: its vector before the edit (a
        move changes the indirect light little, and it costs nothing), else (a new light, a
        reshaped one, a new light link) its gather light at one sample per gather with PREVIEW_BOUNCES
        terms of the bounce series (the first frame then misses the later bounces)."""
        gather_light = dataclasses.replace(unit_light(light), light_link=None)
        key = gather_light_key(gather_light)
        state = self._per_light.get(light.path)
        if (state is not None and state.gather_key == key) or self._previewed.get(light.path) == key:
            return None
        self._previewed[light.path] = key
        if state is not None and state.shaping == light_snapshot((light.shaping, light.barzel)):
            if state.rows is not None and state.rows.light_link == light.light_link:
                return state.rows.vector
            if state.vector is not None and state.light_link == light.light_link:
                return state.vector
        radiance = gather_radiance(gather_light, self.gathers, self.direct.visibility, 1, self.direct.settings.seed)
        linked = link_mask(light, self.gathers.object_id, self.direct.object_paths)
        if linked is not None:
            radiance = radiance * linked.unsqueeze(-1).to(radiance)
        return self.light_vector(radiance, PREVIEW_BOUNCES)

    def _fill_rows(self, rows: _Rows, todo: torch.Tensor) -> None:
        """Multiply the F rows `todo` (K,) by the kept vector into `rows`."""
        if todo.numel():
            product = self.final_gather.select_rows(todo).matmul(rows.vector).clamp_(min=0.0)
            rows.values.index_copy_(0, todo, product)
            rows.done[todo] = True
            rows.num_done += int(todo.numel())

    def _linked_radiance(self, state: _IndirectState, light: Light) -> torch.Tensor:
        """(G, 3) the cached gather light with the light's link applied."""
        linked = link_mask(light, self.gathers.object_id, self.direct.object_paths)
        return state.radiance if linked is None else state.radiance * linked.unsqueeze(-1).to(state.radiance)

    def _gather_state(self, light: Light) -> _IndirectState:
        """The light's state, its gather light traced again when what it depends on changed."""
        unit = unit_light(light)
        gather_light = dataclasses.replace(unit, light_link=None)
        key = gather_light_key(gather_light)
        state = self._per_light.get(light.path)
        if state is None or state.gather_key != key:
            settings = self.direct.settings
            num_samples = self._gather_samples(unit, self.gather_samples)
            radiance = gather_radiance(gather_light, self.gathers, self.direct.visibility, num_samples, settings.seed)
            self.counters["gather_light"] += 1
            state = _IndirectState(key, radiance, shaping=light_snapshot((light.shaping, light.barzel)))
            self._per_light[light.path] = state
        return state
