"""Relighting with seed 004's nonlinear cut approximation: precomputed visibility cuts merged per
pixel with a per-frame illumination cut, the BRDF evaluated per merged cluster so materials stay
editable.

Per frame, every leaf light gets its light (`CutsRelighter.leaf_light`: environment mode, the dome
lights integrated over each leaf's cell; indirect mode, the direct light reflected by each
surface point) and the illumination cut refines the tree by intensity up to `max_cut` nodes. Per
covered sub-sample, the cuts of its three lattice vertices are merged (`merge.merge`; once, then
kept across frames: `CutsRelighter.visibility_batches`) and the illumination cut is merged into
that (as `merge.refine_nodes`, batched in `CutsRelighter._factor_columns`), then

    B = sum_k |C_k| <l_k> f_r(wo, <x_k>) cos(<x_k>) (w1 <v1_k> + w2 <v2_k> + w3 <v3_k>)

with <x_k> the direction to the merged cluster (its mean direction, or its mean position in
indirect mode, where <v_k> is visibility times the leaves' solid angle), f_r UsdPreviewSurface from the
sub-sample's current parameters (a dome's diffuse and specular multipliers apply per lobe),
computed as the scalars f_r is linear in (`preview_surface.split_factors`) summed per
illumination-cut node, times the nodes' light, combined with the current colours
(`preview_surface.combine_factors`). What each edit recomputes (`FactorColumns`): a light edit
that keeps the illumination cut's nodes, the products with the light; one that changes them, the
entries of the new nodes too; a colour edit of a material, only the combination; a roughness
edit, the entries of that material's sub-samples; none of them the visibility merge.
Everything else is the direct relighter's.
"""

from __future__ import annotations

import collections
import dataclasses
from dataclasses import dataclass

import torch

from relight_torch.brdf import preview_surface
from relight_torch.brdf.preview_surface import PreviewSurfaceParams
from relight_torch.cuts.cuts import Cuts, intensity_cut
from relight_torch.cuts.env import dome_leaf_light
from relight_torch.cuts.merge import MergedCuts, leaf_cut_index, merge
from relight_torch.cuts.tree import LightTree
from relight_torch.lights.dome import REC709_LUMINANCE
from relight_torch.lights.light import Light, LightKind
from relight_torch.lights.linking import linked_points
from relight_torch.math.frame import to_local
from relight_torch.relighter import Relighter, light_group
from relight_torch.transfer.gathers import GatherSamples, gather_radiance


@dataclass(frozen=True)
class CutsRelightSettings:
    """Per-frame settings.

    Attributes:
        max_cut: illumination cut size (seed 004: 128, 256 or 512).
        rows_per_batch: sub-samples merged and shaded together (bounds the temporaries' memory).
        factor_dtype: dtype of the kept BRDF factor sums per (sub-sample, illumination-cut node)
            and of their product with the light: bfloat16 (default; half the memory, ~3x faster
            products on CPU, ~0.3 % relative error) or float32.
    """

    max_cut: int = 256
    rows_per_batch: int = 2048
    factor_dtype: torch.dtype = torch.bfloat16


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
    """The lit clusters of the merged visibility cuts of a batch of sub-samples (no lights, no materials).

    Attributes:
        rows: (P,) int64 the batch's sub-samples.
        frame: (P, 3, 3) their shading frames, columns tangent, bitangent, normal (world -> local
            by right-multiplication).
        local: (Q,) int32 row (into `rows`) of each merged cluster, ascending.
        node: (Q,) int32 its node, ascending within a row.
        visibility: (Q,) barycentric blend of the three vertices' means (> 0).
        inputs: entries of the batch's vertices' visibility cuts (the merge's input).
        dark: merged clusters dark at all three vertices (dropped).
    """

    rows: torch.Tensor
    frame: torch.Tensor
    local: torch.Tensor
    node: torch.Tensor
    visibility: torch.Tensor
    inputs: int
    dark: int


@dataclass
class FactorColumns:
    """What the beauty render keeps between frames (`CutsRelighter.cuts_image`).

    Per batch of `visibility_batches`, the BRDF factors (`preview_surface.split_factors`) of the
    merged cut summed per illumination-cut node, in K = max_cut column slots: a light edit that
    keeps a node keeps its column, a node new to the cut gets a free slot and only its column is
    computed; a material edit recomputes the rows whose lobe changed (roughnesses).

    Attributes:
        key: (max_cut, factors F, dtype, rows per batch): a change starts afresh.
        slot_node: (K,) int64 the illumination-cut node in each slot, -1 if free.
        columns: per batch (P, F, K) factor sums (factor_dtype).
        counts: per batch (2, K) int64 merged entries and shaded entries (lit, above the
            horizon) per slot.
        sums: (N, F, 3) float the factor sums times the light (diffuse light for the first two
            factors, specular for the others), summed over the cut.
        light_key: the illumination cut `sums` were made with.
        dirty: (N,) bool sub-samples whose columns are to be recomputed (material edits).
    """

    key: tuple
    slot_node: torch.Tensor
    columns: list[torch.Tensor]
    counts: list[torch.Tensor]
    sums: torch.Tensor
    light_key: tuple | None
    dirty: torch.Tensor


class CutsRelighter:
    """Light by cuts plus the direct relighter, on one deep framebuffer.

    Environment mode: dome lights by cuts, every other light by the direct relighter. Indirect
    mode: every light direct, plus its one-bounce indirect light by cuts (seed 004's second mode):
    the leaves are surface points lit with `relight_torch.transfer.gathers.gather_radiance` (the
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
            three vertices, dropped before the illumination cut is merged in), 'shaded' (merged
            entries lit and above the horizon), 'evaluated' (merged entries whose BRDF factors
            this render computed; the rest were kept, `FactorColumns`) and 'illumination_cut'
            (its size).
    """

    def __init__(self, direct: Relighter, cuts: CutsCache, settings: CutsRelightSettings = CutsRelightSettings()):
        if cuts.sample_vertices.shape[0] != direct.gbuffer.num_samples:
            raise ValueError(f"the cuts interpolate {cuts.sample_vertices.shape[0]} sub-samples, the deep "
                             f"framebuffer has {direct.gbuffer.num_samples}")
        self.direct = direct
        self.cuts = cuts
        self.settings = settings
        self.params = direct.gbuffer.params
        self.stats: collections.Counter[str] = collections.Counter()
        g, tree = direct.gbuffer, cuts.tree
        self._wo_local = to_local(g.wo_world(), g.tangent, g.bitangent, g.normal)
        self._node_size = tree.size.to(g.position.dtype)
        if cuts.mode == "env":
            self._node_directions = torch.nn.functional.normalize(tree.aggregate(cuts.leaf_directions), dim=-1)
        else:
            points = cuts.leaf_points
            self._node_position = tree.aggregate(points.position) / tree.size.to(g.position.dtype).unsqueeze(-1)
        self._domes: dict[str, Light] = {}
        self._leaf_radiance: dict[str, tuple[Light, torch.Tensor]] = {}
        self._samples: torch.Tensor | None = None
        self._visibility_batches: tuple[int, list[VisibilityBatch]] | None = None
        # The last illumination cut: (key of its lights, the lights (kept alive, so their ids stay
        # theirs), (nodes, diffuse, specular)).
        self._illumination: tuple[tuple, list[Light], tuple[torch.Tensor, ...]] | None = None
        self._columns: FactorColumns | None = None
        self.set_lights(direct.lights)

    @property
    def mode(self) -> str:
        return self.cuts.mode

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

    def set_light(self, light: Light) -> None:
        """Add or edit a light (matched by path)."""
        if self._by_cuts(light):
            self._domes[light.path] = light
        else:
            self.direct.set_light(light)
        self._samples = None

    def remove_light(self, path: str) -> None:
        if path in self._domes:
            del self._domes[path]
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
        if self._columns is not None:   # only the lobes' widths enter the kept factors
            self._columns.dirty |= ((params.roughness != self.params.roughness)
                                    | (params.clearcoat_roughness != self.params.clearcoat_roughness))
        self.params = params
        self._samples = None

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
        return self.direct._to_image(self._samples)

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
                images[f"{group}_indirect"] = self.direct._to_image(self.cut_samples(lights))
            return images
        images = dict(direct)
        groups: dict[str, list[Light]] = {}
        for light in self._domes.values():
            groups.setdefault(light_group(light), []).append(light)
        for group, lights in groups.items():
            image = self.direct._to_image(self.cut_samples(lights))
            images[group] = images[group] + image if group in images else image
        return images

    def emission_image(self) -> torch.Tensor:
        """(H, W, 3) the surfaces' own emission (indirect mode: also seen through one bounce)."""
        if self.mode == "env":
            return self.direct.emission_image()
        return self.direct.emission_image() + self.direct._to_image(self.cut_samples([], emission=True))

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
            return dome_leaf_light(lights, cuts.leaf_directions, cuts.leaf_weights)
        points = cuts.leaf_points
        radiance = points.emission.clone() if emission else torch.zeros_like(points.position)
        for light in lights:
            cached = self._leaf_radiance.get(light.path)
            if cached is None or cached[0] is not light:
                leaf = gather_radiance(light, points, self.direct.visibility, self.direct.num_light_samples(light),
                                       object_paths=self.direct.object_paths)
                cached = self._leaf_radiance[light.path] = (light, leaf)
            radiance = radiance + cached[1]
        return radiance, radiance

    def illumination_cut(self, lights: list[Light], emission: bool = False
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
        relit = state.light_key != key
        state.light_key = key
        everything = torch.ones_like(new)
        touched = None if bool(new.all()) else _touched_nodes(self.cuts.tree, nodes, new)
        cut_of = leaf_cut_index(self.cuts.tree, nodes)
        for index, batch in enumerate(self.visibility_batches()):
            self.stats["inputs"] += batch.inputs
            self.stats["dark"] += batch.dark
            shape = (batch.rows.shape[0], num_factors, state.slot_node.shape[0])
            columns = state.columns[index] if keep else torch.zeros(shape, dtype=settings.factor_dtype,
                                                                   device=out.device)
            counts = state.counts[index] if keep else torch.zeros((2, shape[2]), dtype=torch.int64, device=out.device)
            if bool(new.any()):
                values, new_counts = self._factor_columns(batch, cut_of, nodes, new, touched, num_factors)
                columns.index_copy_(2, slot[new], values.to(columns.dtype))
                counts[:, slot[new]] = new_counts
                self.stats["evaluated"] += int(new_counts[0].sum())
            dirty = state.dirty.index_select(0, batch.rows)
            dirty_rows = torch.nonzero(dirty).squeeze(1)
            if dirty_rows.shape[0]:
                values, dirty_counts = self._factor_columns(batch, cut_of, nodes, everything, None, num_factors,
                                                              dirty_rows)
                self.stats["evaluated"] += int(dirty_counts[0].sum())
                part = columns.index_select(0, dirty_rows)
                part.index_copy_(2, slot, values.to(columns.dtype))
                columns.index_copy_(0, dirty_rows, part)
            self.stats["merged"] += int(counts[0, slot].sum())
            self.stats["shaded"] += int(counts[1, slot].sum())
            if relit or bool(new.any()):
                state.sums.index_copy_(0, batch.rows, _light_sums(columns, table, out.dtype))
            elif dirty_rows.shape[0]:
                state.sums.index_copy_(0, batch.rows.index_select(0, dirty_rows),
                                       _light_sums(columns.index_select(0, dirty_rows), table, out.dtype))
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
                counts.append(torch.zeros((2, max_cut), dtype=torch.int64, device=device))
        num_samples = self.direct.gbuffer.num_samples
        return FactorColumns(key, torch.full((max_cut,), -1, dtype=torch.int64, device=device), columns, counts,
                             torch.zeros((num_samples, num_factors, 3), dtype=self.direct.gbuffer.position.dtype,
                                         device=device), None,
                             torch.zeros(num_samples, dtype=torch.bool, device=device))

    def _factor_columns(self, batch: VisibilityBatch, cut_of: torch.Tensor, nodes: torch.Tensor, wanted: torch.Tensor,
                        touched: torch.Tensor | None, num_factors: int, rows: torch.Tensor | None = None
                        ) -> tuple[torch.Tensor, torch.Tensor]:
        """BRDF factors of a batch's merged cut (its visibility clusters merged with the
        illumination cut `nodes` (K,)), summed per wanted illumination-cut node.

        A visibility cluster spanning several illumination-cut nodes is refined into them: each
        node j inside it is one entry, in j's direction, weighted |C_j| <v>. A row's clusters
        partition the leaves, so a row meets each node so at most once: these entries are shaded
        on a (P, W) grid, one column per wanted node, whose factors are the column sums; each
        cell's cluster is a running sum over the row of the clusters' ranges of wanted nodes. A
        cluster inside one illumination-cut node is one entry in its own direction: such entries
        are laid out densely, (P, M), M the largest row (padding of weight 0), and summed into
        their columns. Either way a row's frame and material broadcast over its entries.

        Args:
            cut_of: (2L - 1,) int64 `merge.leaf_cut_index` of `nodes`.
            wanted: (K,) bool the columns to compute (W of them, in cut order).
            touched: (2L - 1,) bool the nodes sharing a leaf with a wanted node (`_touched_nodes`):
                only visibility clusters there are looked at; None: every cluster.
            rows: (P,) int64 rows of the batch to compute (default: all).

        Returns:
            ((P, F, W) float factor sums; (2, W) int64 merged and shaded entries per wanted node).
        """
        tree = self.cuts.tree
        node, local, visibility = batch.node, batch.local, batch.visibility
        if rows is None:
            rows = torch.arange(batch.rows.shape[0], device=node.device)
        else:   # a row's entries are contiguous (`local` ascending)
            bounds = torch.searchsorted(local, torch.stack((rows, rows + 1)).to(local.dtype))
            counts = bounds[1] - bounds[0]
            local = torch.repeat_interleave(torch.arange(rows.shape[0], device=node.device), counts)
            entry = (bounds[0] - (torch.cumsum(counts, 0) - counts)).index_select(0, local) + torch.arange(
                local.shape[0], device=node.device)
            node, visibility = node.index_select(0, entry), visibility.index_select(0, entry)
        if touched is not None:
            chosen = torch.nonzero(touched.index_select(0, node)).squeeze(1)
            node, local, visibility = node.index_select(0, chosen), local.index_select(0, chosen), \
                visibility.index_select(0, chosen)
        node, local = node.long(), local.long()
        num_rows, num_wanted, coat = rows.shape[0], int(wanted.sum()), num_factors == 6
        first = cut_of.index_select(0, tree.leftleaf.index_select(0, node))
        last = cut_of.index_select(0, node - tree.height.index_select(0, node))
        rank = torch.cumsum(wanted, 0)
        start = rank.index_select(0, first) - wanted.index_select(0, first).long()   # wanted nodes [start, end)
        end = rank.index_select(0, last)
        samples = batch.rows.index_select(0, rows)
        frame = batch.frame.index_select(0, rows)
        params = self.params.index(samples).with_sample_axis()
        wo_local = self._wo_local.index_select(0, samples).unsqueeze(1)
        # Clusters spanning several illumination-cut nodes: the grid.
        spanning = torch.nonzero((first != last) & (end > start)).squeeze(1)
        label = torch.arange(1, spanning.shape[0] + 1, device=node.device)
        base = local.index_select(0, spanning) * (num_wanted + 1)
        steps = torch.zeros(num_rows * (num_wanted + 1), dtype=torch.int64, device=node.device)
        steps.index_add_(0, base + start.index_select(0, spanning), label)
        steps.index_add_(0, base + end.index_select(0, spanning), -label)
        cluster = torch.cumsum(steps.view(num_rows, num_wanted + 1)[:, :num_wanted], dim=1)   # 0: none
        cell_visibility = torch.cat((visibility.new_zeros(1), visibility.index_select(0, spanning))).index_select(
            0, cluster.view(-1)).view(num_rows, num_wanted)
        wanted_nodes = nodes[wanted]
        wi_local = self._incident_local(wanted_nodes, samples, frame)
        weight = self._node_size.index_select(0, wanted_nodes) * cell_visibility * wi_local[..., 2]
        sums = preview_surface.split_factors(params, wo_local, wi_local, coat=coat, weight=weight)   # (F, P, W)
        merged_counts, shaded = (cluster > 0).sum(dim=0), (weight > 0).sum(dim=0)
        # Clusters inside one illumination-cut node: dense rows, summed into their columns.
        inside = torch.nonzero((first == last) & wanted.index_select(0, first)).squeeze(1)
        if inside.shape[0]:
            row, merged = local.index_select(0, inside), node.index_select(0, inside)
            column = start.index_select(0, inside)
            counts = torch.bincount(row, minlength=num_rows)
            width = int(counts.max())
            slot = row * width + torch.arange(row.shape[0], device=row.device) - (torch.cumsum(counts, 0) - counts
                                                                                   ).index_select(0, row)
            dense_node = torch.full((num_rows * width,), tree.root, dtype=merged.dtype, device=merged.device)
            dense_node.index_copy_(0, slot, merged)
            dense_cell = (torch.arange(num_rows, device=row.device).unsqueeze(1) * num_wanted).expand(
                num_rows, width).reshape(-1).index_copy(0, slot, row * num_wanted + column)
            dense_weight = visibility.new_zeros(dense_node.shape).index_copy_(
                0, slot, self._node_size.index_select(0, merged) * visibility.index_select(0, inside))
            wi_local = torch.bmm(self._incident_dense(dense_node, samples).view(num_rows, width, 3), frame)
            dense_weight = dense_weight.view(num_rows, width) * wi_local[..., 2]
            factors = preview_surface.split_factors(params, wo_local, wi_local, coat=coat, weight=dense_weight)
            sums.view(num_factors, -1).index_add_(1, dense_cell, factors.view(num_factors, -1))
            merged_counts += torch.bincount(column, minlength=num_wanted)
            shaded += torch.bincount(dense_cell[dense_weight.view(-1) > 0] % num_wanted, minlength=num_wanted)
        return sums.transpose(0, 1), torch.stack((merged_counts, shaded))

    def kept_bytes(self) -> int:
        """Bytes kept between frames: the merged visibility batches and the factor columns."""
        tensors = [t for batch in (self._visibility_batches or (0, []))[1]
                   for t in (batch.rows, batch.frame, batch.local, batch.node, batch.visibility)]
        if self._columns is not None:
            tensors += [*self._columns.columns, *self._columns.counts, self._columns.sums, self._columns.dirty]
        return sum(t.numel() * t.element_size() for t in tensors)

    def _incident_local(self, nodes: torch.Tensor, rows: torch.Tensor, frame: torch.Tensor) -> torch.Tensor:
        """(P, W, 3) directions towards the clusters `nodes` (W,) from every sub-sample `rows` (P,)
        in its local frame `frame` (P, 3, 3) (env: one matrix product for all of them)."""
        if self.mode == "env":
            world = self._node_directions.index_select(0, nodes)
            return (world @ frame.transpose(0, 1).reshape(3, -1)).view(nodes.shape[0], rows.shape[0], 3).transpose(0, 1)
        return torch.bmm(self._incident_dense(nodes.repeat(rows.shape[0]), rows).view(rows.shape[0], -1, 3), frame)

    def _incident_dense(self, node: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
        """(P M, 3) unit world directions towards merged clusters `node` (P M,) from sub-samples
        `rows` (P,), each sub-sample's M clusters consecutive."""
        if self.mode == "env":
            return self._node_directions.index_select(0, node)
        position = self.direct.gbuffer.position.index_select(0, rows)
        offset = self._node_position.index_select(0, node).view(rows.shape[0], -1, 3) - position.unsqueeze(1)
        return torch.nn.functional.normalize(offset, dim=-1).view(-1, 3)

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
            frames = torch.stack((g.tangent, g.bitangent, g.normal), dim=-1)
            batches = []
            for start in range(0, g.num_samples, batch_rows):
                rows = order[start:start + batch_rows]
                merged = self.merged_visibility(rows)
                visibility = self._visibility(merged, cuts.sample_weights[rows])
                # Clusters all three vertices see as dark stay dark however the illumination cut
                # would split them: they are dropped before the illumination cut is merged in.
                lit = visibility > 0
                batches.append(VisibilityBatch(rows, frames[rows], merged.row[lit].int(), merged.node[lit].int(),
                                               visibility[lit], int(inputs[rows].sum()), int((~lit).sum())))
            self._visibility_batches = (batch_rows, batches)
        return self._visibility_batches[1]

    def _visibility(self, merged: MergedCuts, weights: torch.Tensor) -> torch.Tensor:
        """(Q,) barycentric blend of the three vertices' cluster means; `weights` (P, 3) per row."""
        values = self.cuts.visibility.values
        return sum(weights[merged.row, j] * values[merged.cover[j]] for j in range(3))

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
    slot[new] = torch.nonzero(~used).squeeze(1)[:int(new.sum())]
    slot_node.fill_(-1)
    slot_node[slot] = nodes
    return slot, new


def _touched_nodes(tree: LightTree, nodes: torch.Tensor, wanted: torch.Tensor) -> torch.Tensor:
    """(2L - 1,) bool: the tree nodes sharing a leaf with a `wanted` (K,) node of the cut `nodes` (K,)."""
    leaf_wanted = torch.repeat_interleave(wanted, tree.size.index_select(0, nodes))
    return tree.aggregate(leaf_wanted.to(torch.float32)) > 0


def _light_sums(columns: torch.Tensor, table: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """(P, F, 3) factor sums (P, F, K) times the slots' light (K, 6), as `dtype`: diffuse light
    (first three columns) for the first two factors, specular light for the others."""
    products = (columns.reshape(-1, columns.shape[2]) @ table).view(columns.shape[0], columns.shape[1], 6).to(dtype)
    return torch.cat((products[:, :2, :3], products[:, 2:, 3:]), dim=1)
