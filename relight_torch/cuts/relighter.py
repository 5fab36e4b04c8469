"""Relighting with seed 004's nonlinear cut approximation: precomputed visibility cuts merged per
pixel with a per-frame illumination cut, the BRDF evaluated per merged cluster so materials stay
editable.

Per frame, every leaf light gets its light (`CutsRelighter.leaf_light`: environment mode, the dome
lights integrated over each leaf's cell; indirect mode, the direct light reflected by each
surface point) and the illumination cut refines the tree by intensity up to `max_cut` nodes. Per
covered sub-sample, the cuts of its three lattice vertices are merged (`merge.merge`; once, then
kept across frames: `CutsRelighter.visibility_batches`) and the illumination cut is merged into
that (`merge.refine_nodes`, per frame; kept across material edits), then

    B = sum_k |C_k| <l_k> f_r(wo, <x_k>) cos(<x_k>) (w1 <v1_k> + w2 <v2_k> + w3 <v3_k>)

with <x_k> the direction to the merged cluster (its mean direction, or its mean position in
indirect mode, where <v_k> is visibility times the leaves' solid angle), f_r UsdPreviewSurface from the
sub-sample's current parameters (`relight_torch.brdf.preview_surface.split`; a dome's diffuse and
specular multipliers apply per lobe). What each edit recomputes: a material edit, the BRDF and
the sums; a light edit, also the illumination cut and its merge; neither, the visibility merge.
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
from relight_torch.cuts.merge import MergedCuts, merge, refine_nodes
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
    """

    max_cut: int = 256
    rows_per_batch: int = 2048


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
            three vertices, dropped before the illumination cut is merged in), 'shaded' (entries
            whose BRDF was evaluated: lit, above the horizon), and 'illumination_cut' (its size).
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
        self.params = params.to(self.params.diffuse_color.device, self.params.diffuse_color.dtype)
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
            self._samples = self.cut_samples(self._cut_lights(), emission=True)
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

    def cut_samples(self, lights: list[Light], emission: bool = False) -> torch.Tensor:
        """(N, 3) radiance of every covered sub-sample from `lights` by cuts (env: their domes;
        indirect: their bounce, plus the surfaces' emission bounced with `emission`), camera
        exposure not applied. Env: domes with a light link are merged separately and masked to
        the linked objects (shadow links are not honoured: the visibility cuts hold every occluder)."""
        links: dict[tuple[str, ...] | None, list[Light]] = {}
        for light in lights if self.mode == "env" else ():
            links.setdefault(light.light_link, []).append(light)
        if set(links) - {None}:
            total = torch.zeros_like(self.direct.gbuffer.position)
            for link, members in links.items():
                part = self._merged_samples(members, emission)
                total += part if link is None else part * self._link_mask(link)
            return total
        return self._merged_samples(lights, emission)

    def _link_mask(self, link: tuple[str, ...]) -> torch.Tensor:
        """(N, 1) 1 on the sub-samples of the objects a light link includes, else 0."""
        g = self.direct.gbuffer
        if self.direct.object_paths is None:
            raise ValueError("light linking needs the cache's object paths (re-bake the cache)")
        return linked_points(self.direct.object_paths, link, g.object_id).to(g.position.dtype).unsqueeze(-1)

    def _merged_samples(self, lights: list[Light], emission: bool) -> torch.Tensor:
        """`cut_samples` of lights sharing one light link (or indirect mode).

        Per batch of cached merged visibility clusters (`visibility_batches`, sub-samples of
        similar cut sizes together) the illumination cut is merged in (`refine_nodes`) and the
        refined clusters are laid out densely, (P, M) with M the batch's largest merged cut
        (padding has weight 0), so that a sub-sample's frame and material broadcast over its
        clusters instead of being gathered per cluster.
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
        light_table = torch.cat((diffuse_light, specular_light), dim=1)
        tree = self.cuts.tree
        size = tree.size.to(out.dtype)
        for batch in self.visibility_batches():
            self.stats["inputs"] += batch.inputs
            self.stats["dark"] += batch.dark
            parent, node, light = refine_nodes(tree, batch.node.long(), nodes)
            self.stats["merged"] += int(node.shape[0])
            local = batch.local.index_select(0, parent).long()
            counts = torch.bincount(local, minlength=batch.rows.shape[0])
            width = int(counts.max())
            slot = local * width + torch.arange(local.shape[0], device=local.device) - (torch.cumsum(counts, 0) - counts
                                                                                         ).index_select(0, local)
            dense_node = torch.full((batch.rows.shape[0] * width,), tree.root, dtype=node.dtype, device=node.device)
            dense_node.index_copy_(0, slot, node)
            dense_light = torch.zeros_like(dense_node).index_copy_(0, slot, light)
            weight = out.new_zeros(dense_node.shape).index_copy_(
                0, slot, size.index_select(0, node) * batch.visibility.index_select(0, parent))
            shape = (batch.rows.shape[0], width)
            wi_local = torch.bmm(self._incident_dense(dense_node, batch.rows).view(*shape, 3), batch.frame)
            cos = wi_local[..., 2]
            weight = weight.view(shape) * cos
            self.stats["shaded"] += int((weight > 0).sum())
            params = self.params.index(batch.rows).with_sample_axis()
            diffuse, specular = preview_surface.split(params, self._wo_local.index_select(0, batch.rows).unsqueeze(1),
                                                      wi_local)
            light_rows = light_table.index_select(0, dense_light).view(*shape, 6)
            radiance = (diffuse * light_rows[..., :3] + specular * light_rows[..., 3:]) * weight.unsqueeze(-1)
            out.index_add_(0, batch.rows, radiance.sum(dim=1))
        return out

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
