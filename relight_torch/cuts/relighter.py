"""Relighting with Cheslack-Postava et al. 2008's nonlinear cut approximation: precomputed visibility cuts merged per
pixel with a per-frame illumination cut, the BRDF evaluated per merged cluster so materials stay
editable.

Per frame, every leaf light gets its light (`CutsRelighter.leaf_light`: environment mode, the dome
lights integrated over each leaf's cell; indirect mode, the direct light reflected by each
surface point) and the illumination cut refines the tree by intensity up to `max_cut` nodes. Per
covered sub-sample, the cuts of its three lattice vertices are merged (`merge.merge`; once, then
kept across frames: `CutsRelighter.visibility_batches`) and the illumination cut is merged into
that (as `merge.refine_nodes`, batched in `FactorEvaluator.columns`), then

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
from collections.abc import Mapping
from dataclasses import dataclass

import torch

from relight_torch.brdf import preview_surface
from relight_torch.brdf.preview_surface import PreviewSurfaceParams
from relight_torch.cuts.batches import VisibilityBatch, VisibilityBatches
from relight_torch.cuts.columns import ColumnsFrame, FactorColumns
from relight_torch.cuts.cuts import Cuts, intensity_cut
from relight_torch.cuts.env import cell_pattern, dome_leaf_light
from relight_torch.cuts.factors import FactorEvaluator
from relight_torch.cuts.merge import MergedCuts
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
        self.stats: collections.Counter[str] = collections.Counter()
        g, tree = direct.gbuffer, cuts.tree
        # The BRDF is evaluated in the stored frames, as `preview_surface.split` is given
        # `to_local` directions: stored in low precision they are not quite orthonormal, and
        # sharp lobes see it, so dot products are taken with the frame's vectors, not world ones.
        frames = torch.stack((g.tangent, g.bitangent, g.normal), dim=-1)
        wo_local = to_local(g.wo_world(), g.tangent, g.bitangent, g.normal)
        self._cos_e, self._view_sq = wo_local[:, 2], (wo_local * wo_local).sum(-1)
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
        geometry = torch.cat((frames, (frames @ wo_local.unsqueeze(-1))), dim=-1)
        self._batches = VisibilityBatches(tree, cuts.visibility, cuts.sample_vertices, cuts.sample_weights, geometry)
        # The last illumination cut: (key of its lights, the lights (kept alive, so their ids stay
        # theirs), (nodes, diffuse, specular)).
        self._illumination: tuple[tuple, list[Light], tuple[torch.Tensor, torch.Tensor, torch.Tensor]] | None = None
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

    @property
    def material_paths(self) -> list[str] | None:
        return self.direct.material_paths

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

    @property
    def params(self) -> PreviewSurfaceParams:
        """The current material parameters of every sub-sample: the direct relighter's."""
        return self.direct.gbuffer.params

    def set_params(self, params: PreviewSurfaceParams) -> None:
        """Replace the material parameters of every sub-sample (rows as the G-buffer's): the direct
        relighter's lights (`Relighter.set_params`) and the cuts' light follow them."""
        before = self.params
        self.direct.set_params(params)
        self._follow_materials(before)

    def set_material_edits(self, edits: Mapping[int | str, Mapping[str, object]]) -> None:
        """`CacheRelighter.set_material_edits`: the direct relighter's, which the cuts' light follows."""
        before = self.params
        self.direct.set_material_edits(edits)
        self._follow_materials(before)

    def edit_material(self, material: int | str, **values: object) -> None:
        """Set UsdPreviewSurface inputs (field names of `PreviewSurfaceParams`, constants) on the
        sub-samples of one material (id or prim path), e.g. `edit_material(3, diffuse_color=(0.1, 0.5, 0.15))`:
        the direct relighter's (`Relighter.edit_material`), which the cuts' light follows."""
        before = self.params
        self.direct.edit_material(material, **values)
        self._follow_materials(before)

    def _follow_materials(self, before: PreviewSurfaceParams) -> None:
        """The cuts' light after the direct relighter's materials changed from `before`."""
        params = self.params
        if params is before:
            return
        if self._columns is not None:  # only the lobes' widths enter the kept factors
            self._columns.dirty |= (params.roughness != before.roughness) | (
                params.clearcoat_roughness != before.clearcoat_roughness
            )
        self._samples = None
        self._edits += 1

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
        illumination cut and the rows whose lobes changed, then the products (`ColumnsFrame`).
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
        cut = self._illumination[2]
        self.stats["illumination_cut"] = int(cut[0].shape[0])
        settings = self.settings
        num_factors = 6 if bool(self.params.clearcoat.any()) else 4
        state_key = (settings.max_cut, num_factors, settings.factor_dtype, settings.rows_per_batch)
        # Another image of the kept columns' lights (a light group holding every dome) reuses them.
        keep = keep or (self._columns is not None and self._columns.light_key == key)
        state = self._columns if keep else None
        if state is None or state.key != state_key:
            batches = self.visibility_batches() if keep else []
            state = FactorColumns.empty(state_key, batches, g.num_samples, g.position.dtype, g.position.device)
            if keep:
                self._columns = state
        position = None if self.mode == "env" else g.position
        factors = FactorEvaluator(
            self._node_points, self._cos_e, self._view_sq, position, self.params, settings.compiled
        )
        frame = ColumnsFrame.start(state, keep, key, cut, self.cuts.tree, self._node_size, factors)
        batches = self.visibility_batches()
        # Batches on the kept worker threads (`relight_torch.parallel`): much of a batch's
        # bookkeeping (nonzero, bincount, cumsum, scatters) runs on one thread under OpenMP.
        threads = 1 if settings.compiled else tile_threads(out.device)

        def frame_batch(index: int) -> collections.Counter[str]:
            return frame.batch(index, batches[index], self._batches.entries_by_node)

        for stats in parallel_map(frame_batch, range(len(batches)), threads):
            self.stats.update(stats)
        state.dirty.zero_()
        colours = preview_surface.factor_colours(self.params, state.sums.shape[1] > 4)
        diffuse, specular = preview_surface.combine_factors(colours, state.sums.movedim(1, 0))
        return diffuse + specular

    def visibility_batches(self) -> list[VisibilityBatch]:
        """The merged visibility cuts of every covered sub-sample, in batches of
        `settings.rows_per_batch`: computed on first use, then kept (`VisibilityBatches.batches`)."""
        return self._batches.batches(self.settings.rows_per_batch)

    def merged_visibility(self, rows: torch.Tensor) -> MergedCuts:
        """The merged visibility cuts of the three lattice vertices of sub-samples `rows` (P,)."""
        return self._batches.merged(rows)

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
        tensors = self._batches.tensors() + (self._columns.tensors() if self._columns is not None else [])
        return sum(t.numel() * t.element_size() for t in tensors)
