"""Relighting with Cheslack-Postava et al. 2008's nonlinear cut approximation: precomputed visibility cuts merged per
pixel with a per-frame illumination cut, the BRDF evaluated per merged cluster so materials stay
editable.

Per frame, every leaf light gets its light (`CutsRelighter.leaf_light`: environment mode, the dome
lights integrated over each leaf's cell; indirect mode, the direct light reflected by each
surface point) and the illumination cut refines the tree by intensity up to `max_cut` nodes. Per
covered sub-sample, the cuts of its three lattice vertices are merged (`merge.merge`; once, then
kept across frames: `CutsRelighter.visibility_batches`) and the illumination cut is merged into
that (as `merge.refine_nodes`, batched in `CutsRelighter._factor_columns`), then

    B = sum_k |C_k| <l_k> f_r(wo, <x_k>) cos(<x_k>) (w1 <v1_k> + w2 <v2_k> + w3 <v3_k>)

with <x_k> the direction to the merged cluster (its mean direction, or its mean position in indirect
mode, where <v_k> is visibility times the leaves' solid angle), f_r UsdPreviewSurface from the
sub-sample's current parameters (a dome's diffuse and specular multipliers apply per lobe), computed
as the scalars f_r is linear in (`preview_surface.split_factors`, evaluated in place from dot
products by `preview_surface.split_factors_cosines`) summed per illumination-cut node, times the
nodes' light, combined with the current colours (`preview_surface.combine_factors`). What each edit
recomputes (`FactorColumns`): a light edit that keeps the illumination cut's nodes, the products
with the light (none if the nodes' light is unchanged); one that changes them, the entries of the
new nodes too; a colour edit of a material, only the combination; a roughness edit, the lobes'
factors of that material's sub-samples (the next edit of the same rows without their grid's
bookkeeping, `FactorColumns.grids`); none of them the visibility merge. Everything else is the
direct relighter's.
"""

from __future__ import annotations

import collections
import dataclasses
from dataclasses import dataclass

import torch

from relight_torch.brdf import preview_surface
from relight_torch.brdf.preview_surface import PreviewSurfaceParams
from relight_torch.cuts.blocks import BlockEvaluator, add_factors, slabs
from relight_torch.cuts.cuts import Cuts, intensity_cut
from relight_torch.cuts.env import cell_pattern, dome_leaf_light
from relight_torch.cuts.merge import MergedCuts, leaf_cut_index, merge
from relight_torch.cuts.tree import LightTree
from relight_torch.direct.relighter import Relighter
from relight_torch.direct.rig import light_group
from relight_torch.indirect_samples import GatherSamples, gather_radiance
from relight_torch.lights.dome import REC709_LUMINANCE
from relight_torch.lights.emission import validate_light
from relight_torch.lights.light import Light, LightKind
from relight_torch.lights.linking import linked_points
from relight_torch.math.frame import to_local
from relight_torch.parallel import parallel_map, tile_threads
from relight_torch.protocol import Refinement, refuse_progressive, tensor_bytes

MERGE_ROWS = 2048
"""Sub-samples whose visibility cuts are merged together (`CutsRelighter.visibility_batches`), and
whose every merged entry is evaluated together (a new illumination cut, a roughness edit's rows),
each chunk cut to its own longest row: bounds the temporaries (the column sums' scatter stays in
cache), whatever `CutsRelightSettings.rows_per_batch`."""

KEPT_GRID_SHARE = 0.5
"""A roughness edit keeps its rows' grid weights (`FactorColumns.grids`) for the next edit of the
same rows (a slider dragged) if they are at most this share of the sub-samples: (N / 2, K)
float32 at most, a quarter of the factor columns' bytes."""

GRID_LIVE_SHARE = 0.75
"""A grid whose live columns (spanned by some row's cluster) are at most this share of its
columns is shaded on those alone, its factors then added into their columns (`_grid`): ~2.3 ns
per live cell for four factors (one core) against ~5.4 per cell shaded, dead or not."""

PRODUCT_ROWS = 1024
"""Sub-samples whose factor columns are updated and multiplied with the light together: 4 MiB of
bfloat16 columns at a cut of 256, which stay in cache between the two."""


@dataclass(frozen=True)
class CutsRelightSettings:
    """Per-frame settings.

    Attributes:
        max_cut: illumination cut size (Cheslack-Postava et al. 2008: 128, 256 or 512).
        rows_per_batch: sub-samples shaded together, their merged visibility cuts kept padded to
            the batch's longest row (bounds the temporaries' memory; larger batches make fewer,
            larger torch calls per frame: a 640 x 480 dome turn ~20 % faster at 16,384 than at
            2,048, for ~55 % padding of the kept rows instead of ~25 %, +120 MiB).
        factor_dtype: dtype of the kept BRDF factor sums per (sub-sample, illumination-cut node)
            and of their product with the light: bfloat16 (default; half the memory, ~3x faster
            products on CPU, ~0.3 % relative error) or float32.
        compiled: evaluate the BRDF factors of each block of merged entries with code compiled by
            `torch.compile` (inductor: C++ on the CPU, needs a C++ compiler; compiled on first
            use, a few variants per process) instead of eager torch passes; the same functions
            (`relight_torch.cuts.blocks`), equal to float rounding. A failure to compile raises
            `RelightError`.
    """

    max_cut: int = 256
    rows_per_batch: int = 16384
    factor_dtype: torch.dtype = torch.bfloat16
    compiled: bool = False


@dataclass(frozen=True)
class CutsCache:
    """What a cuts cache holds, as tensors on one device.

    Attributes:
        tree: the light tree over L leaves.
        visibility: the lattice vertices' visibility cuts, values (nnz,) mean visibility (indirect
            mode: mean visibility x solid angle of the leaf's patch, sr).
        sample_vertices: (N, 3) int64 lattice vertices of each covered sub-sample.
        sample_weights: (N, 3) their barycentric weights.
        leaf_directions, leaf_weights: environment mode: (L, 3) unit world directions of the
            leaves (tree order) and (L,) their solid angles; None in indirect mode.
        leaf_points: indirect mode: the leaves as surface points (tree order); None in env mode.
    """

    tree: LightTree
    visibility: Cuts
    sample_vertices: torch.Tensor
    sample_weights: torch.Tensor
    leaf_directions: torch.Tensor | None = None
    leaf_weights: torch.Tensor | None = None
    leaf_points: GatherSamples | None = None

    @property
    def mode(self) -> str:
        """'env' (dome lights) or 'indirect' (one diffuse bounce of every light)."""
        return "env" if self.leaf_points is None else "indirect"


@dataclass(frozen=True)
class VisibilityBatch:
    """The lit clusters of the merged visibility cuts of a batch of sub-samples (no lights, no
    materials), one row per sub-sample, padded to the batch's largest row M.

    Attributes:
        rows: (P,) int64 the batch's sub-samples.
        geometry: (P, 3, 4) their shading frames (tangent, bitangent, normal) and the direction
            to the viewer in that frame taken back to world (frame @ wo_local), as columns: a
            world direction's row times it gives its local coordinates and E.L (`_geometry`).
        node: (P, M) int32 each row's merged clusters' nodes, ascending, then padding (2L - 1:
            one past the last node).
        visibility: (P, M) barycentric blend of the three vertices' means (> 0; padding 0).
        length: (P,) int32 each row's clusters (the rest is padding): a roughness edit's rows are
            cut to their longest without a pass over their entries.
        inputs: entries of the batch's vertices' visibility cuts (the merge's input).
        dark: merged clusters dark at all three vertices (dropped).
    """

    rows: torch.Tensor
    geometry: torch.Tensor
    node: torch.Tensor
    visibility: torch.Tensor
    length: torch.Tensor
    inputs: int
    dark: int


@dataclass
class FactorColumns:
    """What the beauty render keeps between frames (`CutsRelighter.cuts_image`).

    Per batch of `visibility_batches`, the BRDF factors (`preview_surface.split_factors`) of the
    merged cut summed per illumination-cut node, in K = max_cut column slots: a light edit that
    keeps a node keeps its column, a node new to the cut gets a free slot and only its column is
    computed; a material edit recomputes the lobes' factors (the third on) of the rows whose
    lobe changed (roughnesses).

    Attributes:
        key: (max_cut, factors F, dtype, rows per batch): a change starts afresh.
        slot_node: (K,) int64 the illumination-cut node in each slot, -1 if free.
        columns: per batch (P, F, K) factor sums (factor_dtype).
        counts: per batch (K,) int64 merged entries per slot.
        sums: (N, F, 3) float the factor sums times the light (diffuse light for the first two
            factors, specular for the others), summed over the cut.
        light_key: the illumination cut `sums` were made with.
        table: (K, 6) the slots' diffuse and specular light `sums` were made with (factor_dtype):
            a light edit that leaves it as it was (a dome moved: its directions are at infinity)
            makes no products.
        dirty: (N,) bool sub-samples whose columns are to be recomputed (material edits).
        grids: per batch, the last roughness edit's rows (D,) int64 and their chunks' `_Grid`s
            (of the illumination cut `light_key`; at most `KEPT_GRID_SHARE` of the sub-samples),
            or None: an edit of the same rows shades them again without their bookkeeping.
    """

    key: tuple
    slot_node: torch.Tensor
    columns: list[torch.Tensor]
    counts: list[torch.Tensor]
    sums: torch.Tensor
    light_key: tuple | None
    table: torch.Tensor | None
    dirty: torch.Tensor
    grids: list[tuple[torch.Tensor, list[_Grid]] | None]


class CutsRelighter:
    """Light by cuts plus the direct relighter, on one deep framebuffer.

    Environment mode: dome lights by cuts, every other light by the direct relighter. Indirect
    mode: every light direct, plus its one-bounce indirect light by cuts (Cheslack-Postava et al. 2008's second mode):
    the leaves are surface points lit with `relight_torch.indirect_samples.gather_radiance` (the
    direct relighter's light kernels and visibility), re-emitting diffusely; their solid angle is
    folded into the visibility cuts (`pipeline.bake.cuts.visibility`) and a merged cluster is
    seen in the direction of its leaves' mean position.

    Args:
        direct: the direct relighter of the cache (its G-buffer, exposure and supersampling).
        cuts: the cache's tree, leaves, visibility cuts and sub-sample interpolation.
        settings: illumination cut size, batch size.

    Attributes:
        params: the current material parameters of every sub-sample (edit with `set_params` or
            `edit_material`; no re-bake). Only the cuts' light follows them.
        stats: of the last cuts render, summed over the sub-samples: 'inputs' (entries of the
            three vertices' visibility cuts, the merge's input), 'merged' (entries of the
            merged cuts built with the illumination cut), 'dark' (visibility clusters dark at all
            three vertices, dropped before the illumination cut is merged in), 'evaluated'
            (merged entries whose BRDF factors this render computed; the rest were kept,
            `FactorColumns`) and 'illumination_cut' (its size).
    """

    material_edits = True  # the cuts' light follows `params` (`CacheRelighter`)
    progressive = False  # no coarse frames (`CacheRelighter.refine`): the cut merge has no point subset yet

    def __init__(self, direct: Relighter, cuts: CutsCache, settings: CutsRelightSettings = CutsRelightSettings()):
        if cuts.sample_vertices.shape[0] != direct.gbuffer.num_samples:
            raise ValueError(
                f"the cuts interpolate {cuts.sample_vertices.shape[0]} sub-samples, the deep "
                f"framebuffer has {direct.gbuffer.num_samples}"
            )
        self.direct = direct
        self.cuts = cuts
        self.settings = settings
        self.params = direct.gbuffer.params
        self.stats: collections.Counter[str] = collections.Counter()
        g, tree = direct.gbuffer, cuts.tree
        # The BRDF is evaluated in the stored frames, as `preview_surface.split` is given
        # `to_local` directions: stored in low precision they are not quite orthonormal, and
        # sharp lobes see it, so dot products are taken with the frame's vectors, not world ones.
        frames = torch.stack((g.tangent, g.bitangent, g.normal), dim=-1)
        wo_local = to_local(g.wo_world(), g.tangent, g.bitangent, g.normal)
        self._cos_e, self._view_sq = wo_local[:, 2], (wo_local * wo_local).sum(-1)
        self._geometry = torch.cat((frames, (frames @ wo_local.unsqueeze(-1))), dim=-1)
        self._node_size = tree.size.to(g.position.dtype)
        # (3, 2L) per node its mean direction (env) or mean position (indirect) by component,
        # and a last column for the padding node of `VisibilityBatch` (weight 0).
        if cuts.mode == "env":
            assert cuts.leaf_directions is not None  # env mode has leaf directions
            points = torch.nn.functional.normalize(tree.aggregate(cuts.leaf_directions), dim=-1)
        else:
            assert cuts.leaf_points is not None  # indirect mode has leaf points
            points = tree.aggregate(cuts.leaf_points.position) / tree.size.to(g.position.dtype).unsqueeze(-1)
        self._node_points = torch.cat((points, points.new_zeros((1, 3)))).t().contiguous()
        self._domes: dict[str, Light] = {}
        self._leaf_radiance: dict[str, tuple[Light, torch.Tensor]] = {}
        self._leaf_pattern: torch.Tensor | None = None  # env: the leaves' cells' directions (`env.cell_pattern`)
        self._samples: torch.Tensor | None = None
        self._visibility_batches: tuple[int, list[VisibilityBatch]] | None = None
        self._by_node: list[tuple[torch.Tensor, torch.Tensor] | None] | None = None
        # The last illumination cut: (key of its lights, the lights (kept alive, so their ids stay
        # theirs), (nodes, diffuse, specular)).
        self._illumination: tuple[tuple, list[Light], tuple[torch.Tensor, ...]] | None = None
        self._columns: FactorColumns | None = None
        self._edits = 0  # dome and material changes (the direct relighter counts its lights')
        self.set_lights(direct.lights)

    @property
    def mode(self) -> str:
        return self.cuts.mode

    @property
    def edits(self) -> int:
        """`CacheRelighter.edits`: the direct relighter's light changes and this one's dome and material changes."""
        return self.direct.edits + self._edits

    def pending(self, stride: int | None) -> int:
        refuse_progressive(self)

    def refine(self, stride: int | None) -> Refinement:
        refuse_progressive(self)

    # -- lights and materials -------------------------------------------------------------------

    def _by_cuts(self, light: Light) -> bool:
        """Whether the cuts (rather than the direct relighter) give this light's direct light."""
        return self.mode == "env" and light.kind is LightKind.DOME

    @property
    def lights(self) -> list[Light]:
        return self.direct.lights + list(self._domes.values())

    def set_lights(self, lights: list[Light]) -> None:
        """Replace the whole rig (env mode: domes go to the cuts, the rest to the direct relighter)."""
        self.direct.set_lights([light for light in lights if not self._by_cuts(light)])
        self._domes = {light.path: light for light in lights if self._by_cuts(light)}
        self._samples = None
        self._edits += 1

    def set_light(self, light: Light) -> None:
        """Add or edit a light (matched by path).

        Raises:
            ValueError: the light is one the kernels cannot honour (`emission.validate_light`).
        """
        validate_light(light)
        if self._by_cuts(light):
            self._domes[light.path] = light
            self._edits += 1
        else:
            self.direct.set_light(light)
        self._samples = None

    def remove_light(self, path: str) -> None:
        if path in self._domes:
            del self._domes[path]
            self._edits += 1
        else:
            self.direct.remove_light(path)
            self._leaf_radiance.pop(path, None)
        self._samples = None

    def set_settings(self, settings: CutsRelightSettings) -> None:
        """Change the illumination cut size or batch size (the next render recomputes the cuts' light)."""
        self.settings = settings
        self._samples = None

    def set_params(self, params: PreviewSurfaceParams) -> None:
        """Replace the material parameters of every sub-sample (rows as the G-buffer's).

        Only the cuts' light follows: the direct relighter keeps the baked materials.
        """
        if params.diffuse_color.shape != self.params.diffuse_color.shape:
            raise ValueError(f"material parameters must have {self.params.diffuse_color.shape[0]} rows")
        params = params.to(self.params.diffuse_color.device, self.params.diffuse_color.dtype)
        if self._columns is not None:  # only the lobes' widths enter the kept factors
            self._columns.dirty |= (params.roughness != self.params.roughness) | (
                params.clearcoat_roughness != self.params.clearcoat_roughness
            )
        self.params = params
        self._samples = None
        self._edits += 1

    def edit_material(self, material_id: int, **values: object) -> None:
        """Set UsdPreviewSurface inputs (field names of `PreviewSurfaceParams`, constants) on the
        sub-samples of one material, e.g. `edit_material(3, diffuse_color=(0.1, 0.5, 0.1), roughness=0.6)`."""
        rows = self.direct.gbuffer.material_id == material_id
        changes = {}
        for name, value in values.items():
            field = getattr(self.params, name)
            new = torch.as_tensor(value, dtype=field.dtype, device=field.device).expand_as(field)
            mask = rows.reshape(-1, *([1] * (field.dim() - 1)))
            changes[name] = torch.where(mask, new, field)
        self.set_params(dataclasses.replace(self.params, **changes))

    # -- rendering ------------------------------------------------------------------------------

    def render(self) -> torch.Tensor:
        """(H, W, 3) linear image: the direct relighter's lights plus the cuts' light."""
        return self.direct.render() + self.cuts_image()

    def cuts_image(self) -> torch.Tensor:
        """(H, W, 3) the light computed by cuts alone (env: the domes; indirect: the bounce),
        box-filtered, camera exposure applied."""
        if self._samples is None:
            self._samples = self.cut_samples(self._cut_lights(), emission=True, keep=True)
        return self.direct.to_image(self._samples)

    def indirect_image(self) -> torch.Tensor:
        """(H, W, 3) indirect light alone (indirect mode; zero in env mode), exposure applied."""
        if self.mode == "indirect":
            return self.cuts_image()
        height, width = self.direct.gbuffer.image_size
        s = self.direct.supersampling
        return self.direct.gbuffer.position.new_zeros((height // s, width // s, 3))

    def light_group_images(self) -> dict[str, torch.Tensor]:
        """Light group -> (H, W, 3) image of its lights (env: domes by cuts, the rest direct;
        indirect: '<group>_direct' and '<group>_indirect'); with `emission_image()` they sum to
        `render()`."""
        direct = self.direct.light_group_images()
        if self.mode == "indirect":
            images = {}
            for group, image in direct.items():
                lights = [light for light in self.direct.lights if light_group(light) == group]
                images[f"{group}_direct"] = image
                images[f"{group}_indirect"] = self.direct.to_image(self.cut_samples(lights))
            return images
        images = dict(direct)
        groups: dict[str, list[Light]] = {}
        for light in self._domes.values():
            groups.setdefault(light_group(light), []).append(light)
        for group, lights in groups.items():
            image = self.direct.to_image(self.cut_samples(lights))
            images[group] = images[group] + image if group in images else image
        return images

    def emission_image(self) -> torch.Tensor:
        """(H, W, 3) the surfaces' own emission (indirect mode: also seen through one bounce)."""
        if self.mode == "env":
            return self.direct.emission_image()
        return self.direct.emission_image() + self.direct.to_image(self.cut_samples([], emission=True))

    def _cut_lights(self) -> list[Light]:
        return list(self._domes.values()) if self.mode == "env" else self.direct.lights

    def leaf_light(self, lights: list[Light], emission: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """(diffuse, specular) light (L, 3) of every leaf for the receivers' two BRDF lobes.

        Env: the domes' radiance integrated over each leaf's cell (`env.dome_leaf_light`), times
        the lights' per-lobe multipliers. Indirect: the radiance leaving each surface point after one
        diffuse reflection of `lights` (plus its emission with `emission`), the same for both lobes.
        """
        cuts = self.cuts
        if self.mode == "env":
            assert cuts.leaf_directions is not None and cuts.leaf_weights is not None  # env mode
            if self._leaf_pattern is None:
                self._leaf_pattern = cell_pattern(cuts.leaf_directions, cuts.leaf_weights)
            return dome_leaf_light(lights, self._leaf_pattern, cuts.leaf_weights)
        points = cuts.leaf_points
        assert points is not None  # indirect mode
        radiance = points.emission.clone() if emission else torch.zeros_like(points.position)
        for light in lights:
            cached = self._leaf_radiance.get(light.path)
            if cached is None or cached[0] is not light:
                leaf = gather_radiance(
                    light,
                    points,
                    self.direct.visibility,
                    self.direct.num_light_samples(light),
                    object_paths=self.direct.object_paths,
                )
                cached = self._leaf_radiance[light.path] = (light, leaf)
            radiance = radiance + cached[1]
        return radiance, radiance

    def illumination_cut(
        self, lights: list[Light], emission: bool = False
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(nodes (K,), diffuse means (K, 3), specular means (K, 3)) of the illumination cut of
        `lights`: refined by the nodes' luminance up to `settings.max_cut` nodes."""
        tree = self.cuts.tree
        diffuse, specular = (tree.aggregate(light) for light in self.leaf_light(lights, emission))
        luminance = torch.as_tensor(REC709_LUMINANCE, device=diffuse.device, dtype=diffuse.dtype)
        nodes = intensity_cut(tree, (diffuse + specular) @ luminance, self.settings.max_cut)
        size = tree.size[nodes].to(diffuse.dtype).unsqueeze(-1)
        return nodes, diffuse[nodes] / size, specular[nodes] / size

    def cut_samples(self, lights: list[Light], emission: bool = False, keep: bool = False) -> torch.Tensor:
        """(N, 3) radiance of every covered sub-sample from `lights` by cuts (env: their domes;
        indirect: their bounce, plus the surfaces' emission bounced with `emission`), camera
        exposure not applied. Env: domes with a light link are merged separately and masked to
        the linked objects (shadow links are not honoured: the visibility cuts hold every occluder).
        With `keep` (the beauty render) the factor columns are kept for the next frame
        (`FactorColumns`; not with light links)."""
        links: dict[tuple[str, ...] | None, list[Light]] = {}
        for light in lights if self.mode == "env" else ():
            links.setdefault(light.light_link, []).append(light)
        if set(links) - {None}:
            total = torch.zeros_like(self.direct.gbuffer.position)
            for link, members in links.items():
                part = self._merged_samples(members, emission)
                total += part if link is None else part * self._link_mask(link)
            return total
        return self._merged_samples(lights, emission, keep)

    def _link_mask(self, link: tuple[str, ...]) -> torch.Tensor:
        """(N, 1) 1 on the sub-samples of the objects a light link includes, else 0."""
        g = self.direct.gbuffer
        if self.direct.object_paths is None:
            raise ValueError("light linking needs the cache's object paths (re-bake the cache)")
        return linked_points(self.direct.object_paths, link, g.object_id).to(g.position.dtype).unsqueeze(-1)

    def _merged_samples(self, lights: list[Light], emission: bool, keep: bool = False) -> torch.Tensor:
        """`cut_samples` of lights sharing one light link (or indirect mode).

        B = sum_k |C_k| <l_k> f_r(<x_k>) cos <v_k> is computed as sums over the illumination
        cut's nodes j of the BRDF factors (`preview_surface.split_factors`) of the merged entries
        inside or under j, times l_j (one matrix product per batch), combined with the current
        materials' colours (`preview_surface.combine_factors`). With `keep` the factor columns
        are kept (`FactorColumns`): a new frame computes only the columns of nodes new to the
        illumination cut and the rows whose lobes changed, then the products.
        """
        g = self.direct.gbuffer
        out = torch.zeros_like(g.position)
        self.stats.clear()
        if self.mode == "env" and not lights:
            return out
        # Env mode has no surface emission in its leaves: with or without it the cut is the same.
        key = (tuple(map(id, lights)), emission and self.mode == "indirect", self.settings.max_cut)
        if self._illumination is None or self._illumination[0] != key:  # a material edit keeps the cut
            self._illumination = (key, lights, self.illumination_cut(lights, emission))
        nodes, diffuse_light, specular_light = self._illumination[2]
        self.stats["illumination_cut"] = int(nodes.shape[0])
        settings = self.settings
        num_factors = 6 if bool(self.params.clearcoat.any()) else 4
        state_key = (settings.max_cut, num_factors, settings.factor_dtype, settings.rows_per_batch)
        # Another image of the kept columns' lights (a light group holding every dome) reuses them.
        keep = keep or (self._columns is not None and self._columns.light_key == key)
        state = self._columns if keep else None
        if state is None or state.key != state_key:
            state = self._new_columns(state_key, keep)
            if keep:
                self._columns = state
        slot, new = _assign_slots(state.slot_node, nodes, self.cuts.tree.num_nodes)
        table = torch.zeros((state.slot_node.shape[0], 6), dtype=out.dtype, device=out.device)
        table[slot] = torch.cat((diffuse_light, specular_light), dim=1)
        table = table.to(settings.factor_dtype)
        relit = state.table is None or not torch.equal(state.table, table)
        if state.light_key != key:  # the kept grids are the last illumination cut's
            state.grids = [None] * len(state.grids)
        state.light_key, state.table = key, table
        # Tables of the nodes to evaluate: every node into its slot (a new cut, dirty rows), or
        # the nodes new to the cut in cut order.
        num_slots = state.slot_node.shape[0]
        every_table = (
            _NodeTable.of(self.cuts.tree, nodes, torch.ones_like(new), self._node_size, slot, num_slots)
            if (bool(new.all()) or bool(state.dirty.any()))
            else None
        )
        new_table = (
            every_table
            if bool(new.all())
            else (_NodeTable.of(self.cuts.tree, nodes, new, self._node_size) if bool(new.any()) else None)
        )
        batches = self.visibility_batches()
        keep_grids = keep and int(state.dirty.sum()) <= KEPT_GRID_SHARE * g.num_samples

        def frame_batch(index: int) -> collections.Counter[str]:
            """Batch `index`'s columns brought to this frame and its rows' sums; its `stats`."""
            batch = batches[index]
            stats: collections.Counter[str] = collections.Counter()
            stats["inputs"] += batch.inputs
            stats["dark"] += batch.dark
            shape = (batch.rows.shape[0], num_factors, state.slot_node.shape[0])
            columns = (
                state.columns[index] if keep else torch.zeros(shape, dtype=settings.factor_dtype, device=out.device)
            )
            counts = state.counts[index] if keep else torch.zeros(shape[2], dtype=torch.int64, device=out.device)
            fresh = None  # (P, F, new nodes) float the columns of the nodes new to the cut, for their slots
            if new_table is not None and new_table.everything:
                counts.zero_()
                # Chunks of rows, each without the padding all its rows have (the column sums'
                # scatter stays in cache).
                for part in torch.arange(shape[0], device=out.device).split(MERGE_ROWS):
                    values, grid = self._factor_columns(batch, new_table, num_factors, part)
                    columns[int(part[0]) : int(part[-1]) + 1].copy_(values[:, :, :num_slots].transpose(0, 1))
                    counts += grid.counts
                stats["evaluated"] += int(counts.sum())
            elif new_table is not None:
                values, grid = self._factor_columns(batch, new_table, num_factors, by_node=self._entries_by_node(index))
                fresh = values[:, :, : grid.counts.shape[0]].transpose(0, 1)
                counts[slot[new]] = grid.counts
                stats["evaluated"] += int(grid.counts.sum())
            dirty = state.dirty.index_select(0, batch.rows)
            dirty_rows = torch.nonzero(dirty).squeeze(1)
            if dirty_rows.shape[0] and not bool(new.all()):  # the lobes' factors (2 on) of their rows
                # The grids of the last edit if it was of the same rows (a roughness slider dragged).
                last = state.grids[index] if keep else None
                kept = last[1] if last is not None and torch.equal(last[0], dirty_rows) else None
                assert every_table is not None  # made whenever rows are dirty
                grids = []
                for number, part in enumerate(dirty_rows.split(MERGE_ROWS)):  # the column sums' scatter stays in cache
                    values, grid = self._factor_columns(
                        batch,
                        every_table,
                        num_factors,
                        part,
                        first_factor=2,
                        grid=None if kept is None else kept[number],
                    )
                    grids.append(grid)
                    stats["evaluated"] += int(grid.counts.sum())
                    # The lobes' factors as one span of each row: ~25 % faster than a 3-D index_copy_.
                    lobes = values[2:, :, :num_slots].transpose(0, 1).to(columns.dtype).contiguous()
                    columns.view(shape[0], -1)[:, 2 * num_slots :].index_copy_(0, part, lobes.view(part.shape[0], -1))
                if keep:
                    state.grids[index] = (dirty_rows, grids) if keep_grids else None
            stats["merged"] += int(counts[slot].sum())
            if relit or bool(new.any()):
                # Chunks of rows: the new slots written (scattered along the last axis: every
                # cache line of the columns is read and written) just before the products read them.
                for part in range(0, shape[0], PRODUCT_ROWS):
                    chunk = columns[part : part + PRODUCT_ROWS]
                    if fresh is not None:
                        chunk.index_copy_(2, slot[new], fresh[part : part + PRODUCT_ROWS].to(chunk.dtype))
                    state.sums.index_copy_(
                        0, batch.rows[part : part + PRODUCT_ROWS], _light_sums(chunk, table, out.dtype)
                    )
            elif dirty_rows.shape[0]:
                state.sums.index_copy_(
                    0,
                    batch.rows.index_select(0, dirty_rows),
                    _light_sums(_rows_of(columns, dirty_rows), table, out.dtype),
                )
            return stats

        # Batches on the kept worker threads (`relight_torch.parallel`): much of a batch's
        # bookkeeping (nonzero, bincount, cumsum, scatters) runs on one thread under OpenMP.
        threads = 1 if settings.compiled else tile_threads(out.device)
        for stats in parallel_map(frame_batch, range(len(batches)), threads):
            self.stats.update(stats)
        state.dirty.zero_()
        colours = preview_surface.factor_colours(self.params, state.sums.shape[1] > 4)
        diffuse, specular = preview_surface.combine_factors(colours, state.sums.movedim(1, 0))
        return diffuse + specular

    def _new_columns(self, key: tuple, keep: bool) -> FactorColumns:
        """Empty `FactorColumns` (every row dirty-free, no slot used); batches' arrays only if kept."""
        max_cut, num_factors, dtype, _ = key
        device = self.direct.gbuffer.position.device
        columns, counts = [], []
        if keep:
            for batch in self.visibility_batches():
                columns.append(torch.zeros((batch.rows.shape[0], num_factors, max_cut), dtype=dtype, device=device))
                counts.append(torch.zeros(max_cut, dtype=torch.int64, device=device))
        num_samples = self.direct.gbuffer.num_samples
        return FactorColumns(
            key,
            torch.full((max_cut,), -1, dtype=torch.int64, device=device),
            columns,
            counts,
            torch.zeros((num_samples, num_factors, 3), dtype=self.direct.gbuffer.position.dtype, device=device),
            None,
            None,
            torch.zeros(num_samples, dtype=torch.bool, device=device),
            [None] * len(columns),
        )

    def _factor_columns(
        self,
        batch: VisibilityBatch,
        table: _NodeTable,
        num_factors: int,
        rows: torch.Tensor | None = None,
        by_node: tuple[torch.Tensor, torch.Tensor] | None = None,
        first_factor: int = 0,
        grid: _Grid | None = None,
    ) -> tuple[torch.Tensor, _Grid]:
        """BRDF factors of a batch's merged cut (its visibility clusters merged with the
        illumination cut), summed per wanted illumination-cut node (`table`).

        A visibility cluster spanning several illumination-cut nodes is refined into them: each
        node j inside it is one entry, in j's direction, weighted |C_j| <v>. A row's clusters
        partition the leaves, so a row meets each node so at most once: these entries are shaded
        on a (P, W) grid, one column per wanted node, whose factors are the column sums; each
        cell's cluster is a running sum over the row of the clusters' ranges of wanted nodes
        (`_grid`; only the columns some row's cluster spans if few are, `GRID_LIVE_SHARE`). A
        cluster inside one illumination-cut node is one entry in its own direction, summed into
        its column: shaded on the batch's (P, M) rows when every node is wanted (padding and
        spanning clusters weigh 0, a row's frame and material broadcast over its entries), else
        only the entries under or above wanted nodes are found (`by_node`) and shaded one by
        one. The BRDF runs on cache-sized blocks (`blocks.BlockEvaluator`: `preview_surface.split_factors_cosines`,
        eager or compiled, `CutsRelightSettings.compiled`).

        Args:
            table: the wanted nodes of the illumination cut and what each tree node is to them.
            rows: (P,) int64 rows of the batch to compute (default: all; every node wanted).
            by_node: the batch's `_entries_by_node` (needed unless every node is wanted).
            first_factor: factors before it are not summed, their sums unset (a lobe's width changes
                only the later ones).
            grid: the `_Grid` of these rows and `table` if an earlier call made it.

        Returns:
            ((F, P, C + 2) float factor sums per column (`table`), then two zero columns; the
            rows' `_Grid`, with the merged entries per column).
        """
        node, visibility = batch.node, batch.visibility
        samples, geometry = batch.rows, batch.geometry
        if rows is not None:  # their entries, less the padding all of them have
            width = max(int(batch.length.index_select(0, rows).max()), 1)
            node, visibility = node[:, :width].index_select(0, rows), visibility[:, :width].index_select(0, rows)
            samples, geometry = samples.index_select(0, rows), geometry.index_select(0, rows)
        (num_rows, width), num_columns = node.shape, table.nodes.shape[0]
        flat_node, flat_visibility = node.view(-1), visibility.view(-1)
        roughnesses = (self.params.roughness, self.params.clearcoat_roughness)[: num_factors // 2 - 1]
        roughnesses = tuple(r.index_select(0, samples).unsqueeze(1) for r in roughnesses)
        cos_e = self._cos_e.index_select(0, samples).unsqueeze(1)
        view_sq = self._view_sq.index_select(0, samples).unsqueeze(1)
        # Column of each entry: < C its wanted node's, C + 1 spanning several cut nodes (some
        # wanted), C none (or padding); the sums have two dump columns C, C + 1 of weight 0.
        if table.everything:
            entry = None  # every entry of the (P, M) rows
            column = table.column.index_select(0, flat_node)
        else:  # only the entries of the wanted nodes' subtrees and of the nodes above them
            assert by_node is not None  # callers pass it for a partial table
            order, offsets = by_node
            entry = order.index_select(
                0,
                _concatenated_ranges(
                    offsets.index_select(0, table.ranges[0]).long(), offsets.index_select(0, table.ranges[1]).long()
                ),
            ).long()
            column = table.column.index_select(0, flat_node.index_select(0, entry))
        if grid is None:
            grid = _grid(table, column, entry, flat_node, flat_visibility, num_rows, width)
        sums = visibility.new_empty((num_factors, num_rows, num_columns + 2))
        blocks = BlockEvaluator(num_factors, visibility.dtype, visibility.device, self.settings.compiled)
        self._grid_sums(blocks, table, grid, (geometry, samples, roughnesses, cos_e, view_sq), sums, first_factor)
        # Clusters inside one wanted illumination-cut node, summed into their columns: the
        # (P, M) rows as they are (padding and spanning clusters weigh 0), or one per line.
        if entry is None:
            lines = torch.arange(num_rows, device=node.device)
            column = column.view(num_rows, width)
        else:
            inside = torch.nonzero(column < num_columns).squeeze(1)
            entry = entry.index_select(0, inside)
            lines = torch.div(entry, width, rounding_mode="floor")
            node = flat_node.index_select(0, entry).view(-1, 1)
            visibility = flat_visibility.index_select(0, entry).view(-1, 1)
            column = column.index_select(0, inside).view(-1, 1)
        weight = table.inside_size.index_select(0, node.reshape(-1)).view(node.shape).mul_(visibility)
        cell = column.add_((lines * (num_columns + 2)).unsqueeze(1))
        flat = sums.view(-1)
        picked = None if entry is None else lines  # one entry per line: its row's values gathered per block
        for part in slabs(*node.shape):
            blocks.dense(
                self._node_points,
                node[part],
                _lines_of(geometry, part, picked),
                self._positions(_lines_of(samples, part, picked)),
                tuple(_lines_of(r, part, picked) for r in roughnesses),
                _lines_of(cos_e, part, picked),
                _lines_of(view_sq, part, picked),
                weight[part],
                cell[part].reshape(-1),
                flat,
                first_factor,
            )
        return sums, grid

    def _grid_sums(
        self, blocks: BlockEvaluator, table: _NodeTable, grid: _Grid, rows: tuple, sums: torch.Tensor, first_factor: int
    ) -> None:
        """The factors of a `_Grid` of P rows written into the column sums `sums` (F, P, C + 2)
        (`_factor_columns`): every factor if the grid has every column, else the live columns'
        from `first_factor` on (the earlier factors unset); the rest 0. `rows`: (geometry,
        samples, roughnesses, cos_e, view_sq) of the P rows."""
        geometry, samples, roughnesses, cos_e, view_sq = rows
        num_factors, num_rows, _ = sums.shape
        num_columns, num_grid = table.nodes.shape[0], grid.columns.shape[0]
        in_place = num_grid == num_columns
        (sums[:, :, num_columns:] if in_place else sums[first_factor:]).zero_()
        nodes = table.nodes if in_place else table.nodes.index_select(0, grid.columns)
        parts = slabs(num_rows, num_grid)
        block = sums.new_empty(0 if in_place or not parts else num_factors * parts[0].stop * num_grid)
        for part in parts:
            size = part.stop - part.start
            out = (
                sums[:, part, :num_columns]
                if in_place
                else block[: num_factors * size * num_grid].view(num_factors, size, num_grid)
            )
            blocks.grid(
                self._node_points,
                nodes,
                geometry[part],
                self._positions(samples[part]),
                tuple(r[part] for r in roughnesses),
                cos_e[part],
                view_sq[part],
                grid.weight[part],
                out,
            )
            if not in_place:
                lines = torch.arange(part.start, part.stop, device=sums.device) * (num_columns + 2)
                add_factors(sums.view(-1), (grid.columns + lines.unsqueeze(1)).view(-1), out, first_factor)

    def held_bytes(self) -> int:
        """`CacheRelighter.held_bytes`: the direct relighter's, the leaves' light per light and `kept_bytes`."""
        return (
            self.direct.held_bytes()
            + tensor_bytes(*(radiance for _, radiance in self._leaf_radiance.values()))
            + self.kept_bytes()
        )

    def kept_bytes(self) -> int:
        """Bytes kept between frames: the merged visibility batches (and their entries by node),
        the factor columns and the last roughness edit's grids."""
        tensors = [
            t
            for batch in (self._visibility_batches or (0, []))[1]
            for t in (batch.rows, batch.geometry, batch.node, batch.visibility, batch.length)
        ]
        tensors += [t for index in (self._by_node or []) if index is not None for t in index]
        if self._columns is not None:
            tensors += [*self._columns.columns, *self._columns.counts, self._columns.sums, self._columns.dirty]
            for rows, grids in filter(None, self._columns.grids):
                tensors += [rows, *(t for grid in grids for t in (grid.columns, grid.weight, grid.counts))]
        return sum(t.numel() * t.element_size() for t in tensors)

    def _positions(self, rows: torch.Tensor) -> torch.Tensor | None:
        """(P, 3) positions of sub-samples `rows` (P,) in indirect mode (directions towards the
        clusters' mean positions); None in env mode (the clusters' mean directions)."""
        return None if self.mode == "env" else self.direct.gbuffer.position.index_select(0, rows)

    def _entries_by_node(self, index: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Batch `index`'s entries by node: ((Q,) int32 the flat (P M) positions of its rows'
        clusters, padding left out, sorted by node, (2L + 2,) int32 offsets: node n's entries are
        [offsets[n], offsets[n + 1]), n < 2L - 1). Made on first use (a light edit that changes
        part of the illumination cut) and kept; a frame's batches, on several threads, each fill
        their own entry of the list `visibility_batches` makes."""
        batch = self.visibility_batches()[index]
        assert self._by_node is not None  # made with the batches
        entry = self._by_node[index]
        if entry is None:
            node = batch.node.view(-1)
            counts = torch.bincount(node, minlength=self.cuts.tree.num_nodes + 1)
            offsets = torch.cat((counts.new_zeros(1), torch.cumsum(counts, 0)))
            # The padding (node 2L - 1, sorted last) is never looked up: not kept.
            order = torch.argsort(node, stable=True)[: int(offsets[self.cuts.tree.num_nodes])].int()
            entry = self._by_node[index] = (order, offsets.int())
        return entry

    def visibility_batches(self) -> list[VisibilityBatch]:
        """The merged visibility cuts of every covered sub-sample, in batches of
        `settings.rows_per_batch`: computed on first use, then kept (they depend on neither the
        lights nor the materials). Sub-samples are batched in the order of their vertices' cut
        sizes, so that a batch's merged cuts have similar sizes."""
        batch_rows = self.settings.rows_per_batch
        if self._visibility_batches is None or self._visibility_batches[0] != batch_rows:
            cuts, g = self.cuts, self.direct.gbuffer
            inputs = cuts.visibility.sizes()[cuts.sample_vertices].sum(dim=1)
            order = torch.argsort(inputs, stable=True)
            batches = []
            for start in range(0, g.num_samples, batch_rows):
                rows = order[start : start + batch_rows]
                row, node, visibility, dark = [], [], [], 0
                for first in range(0, rows.shape[0], MERGE_ROWS):  # the merge's temporaries stay small
                    part = rows[first : first + MERGE_ROWS]
                    merged = self.merged_visibility(part)
                    blend = self._visibility(merged, cuts.sample_weights[part])
                    # Clusters all three vertices see as dark stay dark however the illumination
                    # cut would split them: they are dropped before the illumination cut is merged in.
                    lit = blend > 0
                    row.append(merged.row[lit] + first)
                    node.append(merged.node[lit])
                    visibility.append(blend[lit])
                    dark += int((~lit).sum())
                length, padded_node, padded_visibility = _padded_rows(
                    torch.cat(row),
                    (torch.cat(node), torch.cat(visibility)),
                    rows.shape[0],
                    (self.cuts.tree.num_nodes, 0.0),
                )
                batches.append(
                    VisibilityBatch(
                        rows,
                        self._geometry[rows],
                        padded_node.int(),
                        padded_visibility,
                        length.int(),
                        int(inputs[rows].sum()),
                        dark,
                    )
                )
            self._visibility_batches = (batch_rows, batches)
            self._by_node = [None] * len(batches)
        return self._visibility_batches[1]

    def _visibility(self, merged: MergedCuts, weights: torch.Tensor) -> torch.Tensor:
        """(Q,) barycentric blend of the three vertices' cluster means; `weights` (P, 3) per row."""
        values = self.cuts.visibility.values
        row, cover = merged.row, merged.cover
        return (
            weights[row, 0] * values[cover[0]] + weights[row, 1] * values[cover[1]] + weights[row, 2] * values[cover[2]]
        )

    def merged_visibility(self, rows: torch.Tensor) -> MergedCuts:
        """The merged visibility cuts of the three lattice vertices of sub-samples `rows` (P,)."""
        vertices = self.cuts.sample_vertices[rows]
        return merge(self.cuts.tree, [(self.cuts.visibility, vertices[:, j]) for j in range(3)])


def _assign_slots(slot_node: torch.Tensor, nodes: torch.Tensor, num_nodes: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Give every node of an illumination cut (K,) a column slot: its own if `slot_node` (S,)
    already holds it, else a slot no node of the cut holds. Updates `slot_node` in place.

    Returns:
        ((K,) int64 slot of each node, (K,) bool whether the node is new to the slots).
    """
    held = torch.nonzero(slot_node >= 0).squeeze(1)
    slot_of = torch.full((num_nodes,), -1, dtype=torch.int64, device=nodes.device)
    slot_of[slot_node.index_select(0, held)] = held
    slot = slot_of.index_select(0, nodes)
    new = slot < 0
    used = torch.zeros_like(slot_node, dtype=torch.bool)
    used[slot[~new]] = True
    slot[new] = torch.nonzero(~used).squeeze(1)[: int(new.sum())]
    slot_node.fill_(-1)
    slot_node[slot] = nodes
    return slot, new


@dataclass(frozen=True)
class _NodeTable:
    """What each tree node is to the wanted nodes of an illumination cut (per frame), and the
    C output columns they are summed into.

    Attributes:
        nodes: (C,) int64 each column's illumination-cut node (2L - 1, the padding node, if none).
        size: (C,) float their leaf counts |C| (0 if none).
        column: (2L,) int64 per tree node (and the padding node 2L - 1 of `VisibilityBatch`):
            the column of the wanted node it lies in (< C), C if it lies in no wanted node (or is
            the padding), C + 1 if it spans several cut nodes, some of them wanted.
        start, end: (2L,) int64 the wanted nodes [start, end) a node overlaps, numbered in cut order.
        grid_source: (C,) int64 each column's wanted node in cut order (W: none); None if the
            columns are the wanted nodes in cut order.
        ranges: (2, R) int64 node ranges [first, end) holding every node of column != C: the
            wanted nodes' subtrees [leftleaf, node + 1) and the spanning nodes.
        inside_size: (2L,) float |C| of the nodes with column < C, else 0.
        num_wanted: W, the wanted nodes.
        everything: whether every node of the cut is wanted.
    """

    nodes: torch.Tensor
    size: torch.Tensor
    column: torch.Tensor
    start: torch.Tensor
    end: torch.Tensor
    grid_source: torch.Tensor | None
    ranges: torch.Tensor
    inside_size: torch.Tensor
    num_wanted: int
    everything: bool

    @staticmethod
    def of(
        tree: LightTree,
        nodes: torch.Tensor,
        wanted: torch.Tensor,
        node_size: torch.Tensor,
        columns: torch.Tensor | None = None,
        num_columns: int = 0,
    ) -> _NodeTable:
        """The table of the cut `nodes` (K,) (sorted) whose `wanted` (K,) bool nodes are to be
        computed, into `num_columns` columns, `columns` (K,) int64 giving a wanted node's (e.g.
        its slot), or by default in cut order (C = W); `node_size` (2L - 1,) float |C| of
        every node. A node overlaps the cut nodes from the one holding its leftmost leaf to the
        one holding its rightmost (`leaf_cut_index`)."""
        cut_of = leaf_cut_index(tree, nodes)
        first = cut_of.index_select(0, tree.leftleaf)
        last = cut_of.index_select(0, torch.arange(tree.num_nodes, device=nodes.device) - tree.height)
        rank = torch.cumsum(wanted, 0)
        start = rank.index_select(0, first) - wanted.index_select(0, first).long()
        end = rank.index_select(0, last)
        wanted_index = torch.nonzero(wanted).squeeze(1)
        num_wanted = wanted_index.shape[0]
        grid_source = None
        if columns is None:
            columns, num_columns = rank - 1, num_wanted
        else:
            grid_source = torch.full((num_columns,), num_wanted, dtype=torch.int64, device=nodes.device).index_copy_(
                0, columns.index_select(0, wanted_index), torch.arange(num_wanted, device=nodes.device)
            )
        column_nodes = torch.full((num_columns,), tree.num_nodes, dtype=torch.int64, device=nodes.device).index_copy_(
            0, columns.index_select(0, wanted_index), nodes.index_select(0, wanted_index)
        )
        column = torch.where(
            first == last,
            torch.where(wanted.index_select(0, first), columns.index_select(0, first), num_columns),
            torch.where(end > start, num_columns + 1, num_columns),
        )
        pad = column.new_zeros(1)
        padded_size = torch.cat((node_size, node_size.new_zeros(1)))
        inside_size = torch.where(column < num_columns, node_size, 0.0)
        wanted_nodes = nodes.index_select(0, wanted_index)
        spanning = torch.nonzero(column == num_columns + 1).squeeze(1)
        ranges = torch.stack(
            (
                torch.cat((tree.leftleaf.index_select(0, wanted_nodes), spanning)),
                torch.cat((wanted_nodes, spanning)) + 1,
            )
        )
        return _NodeTable(
            column_nodes,
            padded_size.index_select(0, column_nodes),
            torch.cat((column, pad + num_columns)),
            torch.cat((start, pad)),
            torch.cat((end, pad)),
            grid_source,
            ranges,
            torch.cat((inside_size, inside_size.new_zeros(1))),
            num_wanted,
            num_wanted == nodes.shape[0],
        )


@dataclass(frozen=True)
class _Grid:
    """What a chunk of rows' factor sums (`CutsRelighter._factor_columns`) depend on besides the
    materials, past the entries' columns: a roughness edit keeps it for the next edit of the
    same rows (`FactorColumns.grids`).

    Attributes:
        columns: (G,) int64 the grid's columns, ascending: every column, or the live ones (some
            row's cluster spans their node; the others weigh 0 in every row) if at most
            `GRID_LIVE_SHARE` of them.
        weight: (P, G) float |C_j| <v> of the cluster spanning column j's node in each row (0: none).
        counts: (C,) int64 merged entries per column (grid cells and clusters inside the node).
    """

    columns: torch.Tensor
    weight: torch.Tensor
    counts: torch.Tensor


def _grid(
    table: _NodeTable,
    column: torch.Tensor,
    entry: torch.Tensor | None,
    flat_node: torch.Tensor,
    flat_visibility: torch.Tensor,
    num_rows: int,
    width: int,
) -> _Grid:
    """The `_Grid` of the (P, M) rows `flat_node`, `flat_visibility` (P M,) of a batch (M =
    `width`) whose entries `entry` (E,) int64 (None: all) have columns `column` (E,) int64
    (`_NodeTable.column`)."""
    num_columns = table.nodes.shape[0]
    counts = torch.bincount(column, minlength=num_columns + 2)
    # Clusters spanning several illumination-cut nodes: a grid of the wanted nodes in cut order.
    spanning = torch.nonzero(column == num_columns + 1).squeeze(1)
    if entry is not None:
        spanning = entry.index_select(0, spanning)
    spanning_node = flat_node.index_select(0, spanning)
    num_wanted = table.num_wanted
    # int32 labels: the grid's zeros, running sums and gather move half the bytes of int64.
    label = torch.arange(1, spanning.shape[0] + 1, dtype=torch.int32, device=flat_node.device)
    base = torch.div(spanning, width, rounding_mode="floor") * (num_wanted + 1)
    start, end = table.start.index_select(0, spanning_node), table.end.index_select(0, spanning_node)
    steps = torch.zeros(num_rows * (num_wanted + 1), dtype=torch.int32, device=flat_node.device)
    steps.index_add_(0, base + start, label)
    steps.index_add_(0, base + end, -label)
    cluster = torch.cumsum(steps.view(num_rows, num_wanted + 1), dim=1, dtype=torch.int32)  # 0: none (last column: 0)
    # Grid cells holding a cluster, per wanted node in cut order (the last: none).
    covered = torch.cumsum(
        torch.bincount(start, minlength=num_wanted + 1) - torch.bincount(end, minlength=num_wanted + 1), 0
    )
    weight = (
        torch.cat((flat_visibility.new_zeros(1), flat_visibility.index_select(0, spanning)))
        .index_select(0, cluster.view(-1))
        .view(num_rows, num_wanted + 1)
    )
    source = table.grid_source
    covered = covered[:num_wanted] if source is None else covered.index_select(0, source)
    # The `dome` backdrop's chunks of 2,048 rows span ~147 of the cut's 256 nodes.
    live = torch.nonzero(covered).squeeze(1)
    if live.shape[0] > GRID_LIVE_SHARE * num_columns:  # every column
        live, size = torch.arange(num_columns, device=flat_node.device), table.size
        weight = weight[:, :num_wanted] if source is None else weight.index_select(1, source)
    else:
        size = table.size.index_select(0, live)
        weight = weight.index_select(1, live if source is None else source.index_select(0, live))
    return _Grid(live, weight.mul_(size), covered + counts[:num_columns])


def _lines_of(values: torch.Tensor, part: slice, lines: torch.Tensor | None) -> torch.Tensor:
    """Per-row `values` (P, ...) for the lines `part` of a block: the rows themselves (`lines`
    None), or those of the lines' rows `lines` (E,) int64, gathered for this block only."""
    return values[part] if lines is None else values.index_select(0, lines[part])


def _concatenated_ranges(low: torch.Tensor, high: torch.Tensor) -> torch.Tensor:
    """(sum(high - low),) int64 the integers of the ranges [low, high) (R,), one after another."""
    counts = high - low
    owner = torch.repeat_interleave(torch.arange(low.shape[0], device=low.device), counts)
    return (low - (torch.cumsum(counts, 0) - counts)).index_select(0, owner) + torch.arange(
        owner.shape[0], device=low.device
    )


def _padded_rows(
    row: torch.Tensor, values: tuple[torch.Tensor, ...], num_rows: int, fills: tuple[float, ...]
) -> tuple[torch.Tensor, ...]:
    """((P,) int64 entries per row, then (P, M) arrays of per-row entries: `values` (Q,) each, in
    rows `row` (Q,) int64 ascending, each row's entries in order then its `fill`); M the longest
    row (at least 1)."""
    counts = torch.bincount(row, minlength=num_rows)
    width = max(int(counts.max()) if num_rows else 0, 1)
    slot = (
        row * width
        + torch.arange(row.shape[0], device=row.device)
        - (torch.cumsum(counts, 0) - counts).index_select(0, row)
    )
    return counts, *(
        torch.full((num_rows * width,), fill, dtype=value.dtype, device=value.device)
        .index_copy_(0, slot, value)
        .view(num_rows, width)
        for value, fill in zip(values, fills, strict=True)
    )


def _rows_of(columns: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """(R, F, K) the factor columns (P, F, K) of `rows` (R,) int64: one `index_select` of the
    flattened (P, F K) rows (on the CPU a bfloat16 `index_select` of the 3-D tensor ran ~20x
    slower: 28 against 1.5 ms for 10,000 of 16,384 rows at F K = 1,024)."""
    return columns.view(columns.shape[0], -1).index_select(0, rows).view(rows.shape[0], *columns.shape[1:])


def _light_sums(columns: torch.Tensor, table: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """(P, F, 3) factor sums (P, F, K) times the slots' light (K, 6), as `dtype`: diffuse light
    (first three columns) for the first two factors, specular light for the others."""
    products = (columns.reshape(-1, columns.shape[2]) @ table).view(columns.shape[0], columns.shape[1], 6).to(dtype)
    return torch.cat((products[:, :2, :3], products[:, 2:, 3:]), dim=1)
