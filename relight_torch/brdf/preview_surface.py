"""UsdPreviewSurface as Storm evaluates it (usd-core 26.11 `previewSurface.glslfx`,
`evaluateLight`), for one light direction:

    a = max(roughness, 0.001)^2,  k = a/2,  fres = (1 - E.h)^5,  R = (1 - ior)/(1 + ior)
    spec(F0, F90, a) = mix(F0, F90, fres) G(k) D(a) / (4 N.L N.E + 0.001)
    specular workflow: F0 = specularColor, F90 = 1
    metallic workflow: c = mix(1, diffuseColor, metallic); F0 = mix(R^2 c, c, metallic); F90 = c;
                       diffuse *= 1 - metallic
    diffuse = diffuseColor/pi (1 - mix(F0, F90, fres))
    clearcoat = clearcoat spec(R^2, 1, clearcoatRoughness)   (on top, no energy taken away)

The BRDF here is Storm's output divided by N.L (the cosine is not part of f_r). Emission,
occlusion and opacity are not part of it: opacity is applied by the caller according to
opacityMode. Light `diffuse` / `specular` multipliers scale the two parts of `split`.

One departure from Storm, decided on purpose: D is the exact GGX a^2 / (pi ((N.h)^2 (a^2 - 1) + 1)^2),
not Storm's (a^2 + 0.001) numerator (`storm_ggx_d`). Storm's variant scales the lobe's energy by
1 + 0.001/r^4: x1.016 at roughness 0.5, x11 at 0.1, x1e5 at 0.01 (clearcoat 1 at the fallback
clearcoatRoughness 0.01 would reflect ~4000 at normal incidence). Storm only evaluates it for
point-like lights, where it shows as a tiny hot highlight; a path tracer, area and dome lights and
every indirect method integrate it, so it would be that much energy. Renderers that integrate
UsdPreviewSurface (hdEmbree, Karma, RenderMan) use the exact GGX too.

Physics notes, checked by tests: the model is reciprocal (E.h = L.h, everything else is
symmetric in L and E). Diffuse (1 - F(h)) plus the specular lobe exceeds 1 near grazing views
(white dielectric: 1.08 at roughness 0.5, 1.02 at 0.7, 89 deg).

Sampling: a mixture of the cosine (diffuse), and GGX visible normals of width a (specular) and
of the clearcoat width (clearcoat); the exact GGX is both sampled and evaluated. Lobe probabilities are proportional to
an albedo estimate at wo (Schlick F at N.E for the specular lobes).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TypeVar

import torch

from relight_torch.brdf.common import above_horizon, check_pair, check_sample_args, where_above
from relight_torch.brdf.params import BrdfParams, colour, flag, scalar
from relight_torch.math.microfacet import (
    STORM_EPSILON,
    ggx_d,
    ggx_reflection_pdf,
    half_cosines,
    sample_ggx_reflection,
    schlick_fresnel,
    storm_schlick_ggx_g,
)
from relight_torch.math.sampling import cosine_hemisphere, cosine_hemisphere_pdf

MIN_ROUGHNESS = 0.001
"""Storm clamps both roughnesses to at least this before squaring."""


@dataclass(frozen=True)
class PreviewSurfaceParams(BrdfParams):
    """UsdPreviewSurface inputs, one row per shading point (names follow the USD inputs).

    Attributes:
        diffuse_color, emissive_color, specular_color: (N, 3) linear RGB.
        metallic, roughness, clearcoat, clearcoat_roughness, ior, opacity: (N,).
        use_specular_workflow: (N,) bool.
    """

    diffuse_color: torch.Tensor = colour()
    emissive_color: torch.Tensor = colour()
    specular_color: torch.Tensor = colour()
    metallic: torch.Tensor = scalar()
    roughness: torch.Tensor = scalar()
    clearcoat: torch.Tensor = scalar()
    clearcoat_roughness: torch.Tensor = scalar()
    ior: torch.Tensor = scalar()
    opacity: torch.Tensor = scalar()
    use_specular_workflow: torch.Tensor = flag()


USD_INPUT_FIELDS = {
    "diffuseColor": "diffuse_color",
    "emissiveColor": "emissive_color",
    "specularColor": "specular_color",
    "metallic": "metallic",
    "roughness": "roughness",
    "clearcoat": "clearcoat",
    "clearcoatRoughness": "clearcoat_roughness",
    "ior": "ior",
    "opacity": "opacity",
    "useSpecularWorkflow": "use_specular_workflow",
}
"""UsdPreviewSurface input name -> `PreviewSurfaceParams` field."""


GLOSSY_ROUGHNESS = 0.5
"""Roughness below which a lobe counts as glossy (`glossy`)."""


def glossy(params: PreviewSurfaceParams) -> torch.Tensor:
    """(N,) bool: points whose specular lobe, or clearcoat where there is one, is smoother than
    GLOSSY_ROUGHNESS: their highlights need many light samples."""
    coat = (params.clearcoat > 0) & (params.clearcoat_roughness < GLOSSY_ROUGHNESS)
    return (params.roughness < GLOSSY_ROUGHNESS) | coat


def storm_alpha(roughness: torch.Tensor) -> torch.Tensor:
    """GGX width Storm uses for a roughness (...): max(roughness, 0.001)^2."""
    return roughness.clamp_min(MIN_ROUGHNESS) ** 2


def _dielectric_f0(params: PreviewSurfaceParams) -> torch.Tensor:
    """R^2 = ((1 - ior)/(1 + ior))^2, (...,) Fresnel at normal incidence of the dielectric."""
    reflectance = (1.0 - params.ior) / (1.0 + params.ior)
    return reflectance * reflectance


def _specular_colors(params: PreviewSurfaceParams) -> tuple[torch.Tensor, torch.Tensor]:
    """(F0, F90), each (..., 3), of the specular lobe for either workflow."""
    metallic = params.metallic.unsqueeze(-1)
    spec_color = torch.lerp(torch.ones_like(params.diffuse_color), params.diffuse_color, metallic)
    metallic_f0 = torch.lerp(_dielectric_f0(params).unsqueeze(-1) * spec_color, spec_color, metallic)
    specular_workflow = params.use_specular_workflow.unsqueeze(-1)
    f0 = torch.where(specular_workflow, params.specular_color, metallic_f0)
    f90 = torch.where(specular_workflow, torch.ones_like(spec_color), spec_color)
    return f0, f90


def diffuse_albedo(params: PreviewSurfaceParams) -> torch.Tensor:
    """(N, 3) colour a diffuse-only gather uses: diffuseColor, times (1 - metallic) in the
    metallic workflow (the specular workflow ignores metallic)."""
    metallic_scale = torch.where(params.use_specular_workflow, torch.ones_like(params.metallic), 1.0 - params.metallic)
    return params.diffuse_color * metallic_scale.unsqueeze(-1)


def _storm_lobe(alpha: torch.Tensor, cos_l: torch.Tensor, cos_e: torch.Tensor, cos_h: torch.Tensor) -> torch.Tensor:
    """Storm's `evaluateDirectSpecular` without F, with the exact GGX D: D G / (4 N.L N.E + 0.001)."""
    microfacet = ggx_d(cos_h, alpha) * storm_schlick_ggx_g(cos_e, cos_l, alpha)
    return microfacet / (4.0 * cos_l * cos_e + STORM_EPSILON)


def _half_angles(wo_local: torch.Tensor, wi_local: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """(N.E, N.L, N.h clamped to >= 0; E.h, 0 below the horizon; above (bool)), each (...)."""
    cos_e = wo_local[..., 2].clamp_min(0.0)
    cos_l = wi_local[..., 2].clamp_min(0.0)
    # The half vector enters only through N.h and E.h, computed as scalars (on the CPU (..., 3)
    # vector ops cost several times as much) by the same function as the GGX density's N.h
    # (`half_cosines`). Likewise the horizon rule multiplies scalars before they meet the colours.
    cos_h, e_dot_h = half_cosines(wo_local, wi_local)
    cos_h = cos_h.clamp_min(0.0)
    above = above_horizon(wo_local, wi_local)
    e_dot_h = torch.where(above, e_dot_h, 0.0)  # what is masked below may be anything, even NaN
    return cos_e, cos_l, cos_h, e_dot_h, above


def split(
    params: PreviewSurfaceParams, wo_local: torch.Tensor, wi_local: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """The diffuse and the specular (+ clearcoat) parts of the BRDF, each (..., 3) in 1/sr.

    Args:
        params: rows broadcasting against the directions' batch axes.
        wo_local: (..., 3) unit direction to the viewer (E), local frame.
        wi_local: (..., 3) unit direction to the light (L), local frame.

    Returns:
        (diffuse, specular), 0 where either direction is below the horizon.
    """
    check_pair(wo_local, wi_local)
    cos_e, cos_l, cos_h, e_dot_h, above = _half_angles(wo_local, wi_local)
    f0, f90 = _specular_colors(params)
    fresnel = schlick_fresnel(f0, f90, e_dot_h.unsqueeze(-1))
    lobe = _storm_lobe(storm_alpha(params.roughness), cos_l, cos_e, cos_h)
    specular = fresnel * torch.where(above, lobe, 0.0).unsqueeze(-1)
    if bool(params.clearcoat.any()):  # most materials have no coat: skip its lobe entirely
        coat_lobe = _storm_lobe(storm_alpha(params.clearcoat_roughness), cos_l, cos_e, cos_h)
        coat_fresnel = schlick_fresnel(_dielectric_f0(params).unsqueeze(-1), 1.0, e_dot_h.unsqueeze(-1))
        specular = specular + coat_fresnel * torch.where(above, params.clearcoat * coat_lobe, 0.0).unsqueeze(-1)
    diffuse = diffuse_albedo(params) / math.pi * (1.0 - fresnel) * above.to(fresnel.dtype).unsqueeze(-1)
    return diffuse, specular


def split_factors(
    params: PreviewSurfaceParams,
    cos_e: torch.Tensor,
    cos_l: torch.Tensor,
    e_dot_l: torch.Tensor,
    coat: bool,
    weight: torch.Tensor | None = None,
    view_sq: torch.Tensor | float = 1.0,
    light_sq: torch.Tensor | float = 1.0,
) -> torch.Tensor:
    """The scalars (F, ...) that `split` is linear in, for lights summed over many directions.

    With s = (1 - E.h)^5 the Schlick weight and g, g_c the base and clearcoat lobes of `split`
    (0 below the horizon), F = 4 (6 with `coat`): [above, above s, g, g s (, g_c, g_c s)].
    Schlick's F = F0 + (F90 - F0) s is linear in s, so for lights Ld, Ls (..., 3) per direction,
    sum over directions of (diffuse Ld + specular Ls) = `combine_factors` of the sums of the
    first two factors times Ld and of the others times Ls. The factor axis comes first: stacking
    it last costs as much as the rest on the CPU.

    The BRDF is isotropic: the factors need only the dot products of the shading normal N and the
    directions to the viewer E and to the light L, so no frame (`split_factors_cosines`, without
    its cosine).

    Args:
        params: materials, broadcasting as in `split`.
        cos_e, cos_l, e_dot_l: N.E, N.L and E.L (broadcasting).
        coat: whether the clearcoat's two factors are wanted.
        weight: multiplies every factor (e.g. a cosine and a solid angle), or None.
        view_sq, light_sq: |E|^2 and |L|^2 where the directions are not unit.
    """
    roughnesses = (params.roughness, params.clearcoat_roughness)[: 1 + coat]
    batch = torch.broadcast_shapes(  # type: ignore[no-untyped-call]  # unannotated in torch
        cos_e.shape, cos_l.shape, e_dot_l.shape, *(r.shape for r in roughnesses), () if weight is None else weight.shape
    )
    out = cos_l.new_empty(2 + 2 * len(roughnesses), *batch)
    return split_factors_cosines(
        roughnesses,
        cos_e,
        cos_l,
        e_dot_l,
        1.0 if weight is None else weight,
        out,
        cos_l.new_empty(4, *batch),
        view_sq,
        light_sq,
        cosine=False,
    )


# `split_factors_cosines`' factor blocks: one (F, P, M) tensor, or F (P, M) tensors (compiled callers).
_Blocks = TypeVar("_Blocks", bound=torch.Tensor | Sequence[torch.Tensor])


def split_factors_cosines(
    roughnesses: tuple[torch.Tensor, ...],
    cos_e: torch.Tensor,
    cos_l: torch.Tensor,
    e_dot_l: torch.Tensor,
    weight: torch.Tensor | float,
    out: _Blocks,
    scratch: torch.Tensor | Sequence[torch.Tensor],
    view_sq: torch.Tensor | float = 1.0,
    light_sq: torch.Tensor | float = 1.0,
    cosine: bool = True,
) -> _Blocks:
    """`split_factors` times max(N.L, 0) (or without it: `cosine` False) from dot products,
    computed in place: for P points with M light directions each, in blocks that stay in cache.

    The half vector h = E + L enters only through |h|^2 = |E|^2 + |L|^2 + 2 E.L, N.h = N.E + N.L
    and E.h = |E|^2 + E.L, so the factors need N.E, |E|^2 per point and N.L, E.L (and |L|^2 unless
    unit) per direction: no 3-vectors. The same formulas as `split_factors` (exact GGX, Storm's G
    and denominator, (1 - c)(1 + c) for sin^2), in about thirty in-place passes: ~6-10 ns per
    direction on one CPU core against ~45 ns. Equal to `split_factors(weight=weight * N.L)` to
    float rounding, for local directions of any length (a frame stored in low precision is not
    quite orthonormal).

    Args:
        roughnesses: (P, 1) roughness, then (P, 1) clearcoat roughness if the coat's factors are wanted.
        cos_e: (P, 1) N.E. cos_l, e_dot_l: (P, M) N.L and E.L (may be strided views).
        weight: (P, M) e.g. solid angle times visibility (the cosine is applied here), or a number.
        out: (F, P, M) the factors (F = 2 + 2 len(roughnesses)), written (or a sequence of F (P, M)).
        scratch: (4, P, M) work space of the same dtype, overwritten (or a sequence of 4 (P, M)).
        view_sq: |E|^2, (P, 1) or 1. light_sq: |L|^2, (P, M) or 1.
        cosine: whether the factors carry max(N.L, 0).
        (Any shapes broadcasting to out's (P, M) will do.)

    Returns:
        `out`: [lit, lit s, g, g s (, g_c, g_c s)] as `split_factors`, each times weight (and
        max(N.L, 0)); 0 below either horizon.
    """
    lit, schlick = out[0], out[1]
    temp, temp2, cos_h, lit_cos = scratch[0], scratch[1], scratch[2], scratch[3]
    cos_e_clamped = cos_e.clamp(0.0, 1.0)
    torch.clamp(cos_l, 0.0, 1.0, out=temp2)  # N.L, 0 below the horizon
    torch.mul(temp2 if cosine else temp2 > 0, weight, out=lit)
    if torch.compiler.is_compiling() or not bool((cos_e > 0).all()):  # compiled: no data-dependent branch
        lit.mul_(cos_e > 0)
    torch.mul(lit, temp2, out=lit_cos)  # the N.L of G1(N.L) (times the cosine's)
    torch.add(e_dot_l, view_sq, out=schlick)  # E.h |h|
    torch.add(schlick, light_sq, out=temp)
    temp.add_(e_dot_l).clamp_min_(1e-24).rsqrt_()  # 1 / |h|
    schlick.mul_(temp).clamp_(0.0, 1.0)  # E.h
    torch.add(cos_l, cos_e, out=cos_h)
    cos_h.mul_(temp).clamp_(0.0, 1.0)  # N.h
    schlick.neg_().add_(1.0)
    torch.mul(schlick, schlick, out=temp)
    temp.mul_(temp)
    schlick.mul_(temp)  # (1 - E.h)^5
    for index, roughness in enumerate(roughnesses):
        alpha = storm_alpha(roughness)
        a2, k = alpha * alpha, 0.5 * alpha
        # D G / (4 N.L N.E + eps) = a^2 / pi G1(N.E) N.L / (sin^2 + a^2 cos^2)^2 / (N.L (1 - k) + k) / (4 N.L N.E + eps)
        scale = a2 / math.pi * cos_e_clamped / (cos_e_clamped * (1.0 - k) + k)
        lobe = out[2 + 2 * index]
        torch.neg(cos_h, out=temp)
        temp.add_(1.0)
        torch.add(cos_h, 1.0, out=lobe)
        temp.mul_(lobe)
        torch.mul(cos_h, cos_h, out=lobe)
        temp.add_(lobe.mul_(a2))
        temp.mul_(temp)
        torch.mul(temp2, 1.0 - k, out=lobe)
        temp.mul_(lobe.add_(k))
        torch.mul(temp2, 4.0 * cos_e_clamped, out=lobe)
        temp.mul_(lobe.add_(STORM_EPSILON))
        torch.div(lit_cos, temp, out=lobe)
        lobe.mul_(scale)
        torch.mul(lobe, schlick, out=out[3 + 2 * index])
    schlick.mul_(lit)
    return out


def factor_colours(params: PreviewSurfaceParams, coat: bool) -> torch.Tensor:
    """(F, N, 3) the colour each `split_factors` factor is weighted by (F = 4, or 6 with `coat`).

    Diffuse: albedo / pi (1 - F0) and -albedo / pi (F90 - F0); specular: F0 and F90 - F0;
    clearcoat: clearcoat R2 and clearcoat (1 - R2), R2 the dielectric F0. They depend on the
    materials only, so a relighter computes them once (`combine_factors`).
    """
    f0, f90 = _specular_colors(params)
    diffuse = diffuse_albedo(params) / math.pi
    columns = [diffuse * (1.0 - f0), -diffuse * (f90 - f0), f0, f90 - f0]
    if coat:
        r2 = _dielectric_f0(params).unsqueeze(-1)
        clearcoat = params.clearcoat.unsqueeze(-1)
        columns += [(clearcoat * r2).expand_as(f0), (clearcoat * (1.0 - r2)).expand_as(f0)]
    return torch.stack(columns)


def combine_factors(colours: torch.Tensor, sums: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(diffuse, specular) (N, 3) reflected light from sums of `split_factors` times light.

    Args:
        colours: (F, N, 3) `factor_colours` of the N points' materials.
        sums: (F, N, 3) or (F, N, 1) per factor, its sum times the light: the first two factors
            times the diffuse light, the others times the specular light.

    Summed slab by slab (multiply-adds of (N, 3) rows), which the CPU streams; a reduction over
    the factor axis of a (N, F, 3) product ran several times slower.
    """
    diffuse = torch.addcmul(colours[0] * sums[0], colours[1], sums[1])
    specular = torch.addcmul(colours[2] * sums[2], colours[3], sums[3])
    for f in range(4, sums.shape[0]):
        specular.addcmul_(colours[f], sums[f])
    return diffuse, specular


def eval(params: PreviewSurfaceParams, wo_local: torch.Tensor, wi_local: torch.Tensor) -> torch.Tensor:
    """BRDF value (..., 3) in 1/sr, diffuse + specular + clearcoat; 0 below the horizon."""
    diffuse, specular = split(params, wo_local, wi_local)
    return diffuse + specular


def lobe_probabilities(params: PreviewSurfaceParams, wo_local: torch.Tensor, diffuse: bool = True) -> torch.Tensor:
    """Probabilities (..., 3) of sampling the diffuse, specular and clearcoat lobes at wo.

    `diffuse=False` leaves the diffuse lobe out (probability 0): the sampler of the specular and
    clearcoat part alone (`split`'s second value), for callers that integrate the diffuse part by
    other means (the transfer bake's glossy rows). A material without either lobe then samples the
    specular one.

    Proportional to the mean over RGB of each lobe's albedo estimate: Schlick F at N.E for the
    specular lobes, diffuse albedo (1 - F0) for the diffuse one. A black material samples the
    diffuse lobe.

    The diffuse estimate takes F at normal incidence, not at N.E: the diffuse lobe's value is
    scaled by 1 - F(E.h), which stays near 1 - F0 for most light directions however grazing the
    view. With 1 - F(N.E), which vanishes as N.E -> 0, a grazing view (a silhouette, a normal-mapped
    point) sampled the diffuse lobe with probability ~5 N.E while the glossy lobe's density did not
    cover it, so a diffuse sample weighed ~1 / (5 N.E): 1600 at N.E = 1e-4 (the reference's fireflies).
    Now a diffuse sample's weight f cos / pdf is at most the sum of the three estimates (< 3).
    """
    cos_o = wo_local[..., 2]
    f0, f90 = _specular_colors(params)
    specular_fresnel = schlick_fresnel(f0, f90, cos_o.unsqueeze(-1))
    coat_fresnel = schlick_fresnel(_dielectric_f0(params), 1.0, cos_o)
    weights = torch.stack(
        (
            (diffuse_albedo(params) * (1.0 - f0)).mean(-1).expand_as(cos_o) * float(diffuse),
            specular_fresnel.mean(-1),
            params.clearcoat * coat_fresnel,
        ),
        dim=-1,
    ).clamp_min(0.0)
    total = weights.sum(-1, keepdim=True)
    black = torch.tensor([1.0, 0.0, 0.0] if diffuse else [0.0, 1.0, 0.0], device=weights.device, dtype=weights.dtype)
    return torch.where(total > 0, weights / total.clamp_min(torch.finfo(weights.dtype).tiny), black)


def sample(
    params: PreviewSurfaceParams, wo_local: torch.Tensor, u: torch.Tensor, diffuse: bool = True
) -> tuple[torch.Tensor, torch.Tensor]:
    """wi (..., 3) from the lobe mixture, with the mixture pdf (...) (0 for lost samples).

    u[..., 0] picks the lobe and is then rescaled to [0, 1) within the lobe's interval, so two
    numbers per sample suffice. `diffuse=False`: the specular and clearcoat lobes only
    (`lobe_probabilities`), with their own mixture pdf (`pdf(..., diffuse=False)`).
    """
    check_sample_args(wo_local, u)
    probabilities = lobe_probabilities(params, wo_local, diffuse)
    batch = torch.broadcast_shapes(  # type: ignore[no-untyped-call]  # unannotated in torch
        probabilities.shape[:-1], u.shape[:-1]
    )
    probabilities = probabilities.expand(*batch, 3)
    upper = probabilities.cumsum(-1)
    # Scaled by the rounded total so that u < 1 never selects a trailing lobe of probability 0.
    u_select = u[..., 0] * upper[..., 2]
    lobe = (u_select.unsqueeze(-1) >= upper[..., :2]).sum(-1, keepdim=True)
    lower = torch.cat((torch.zeros_like(upper[..., :1]), upper[..., :2]), dim=-1).gather(-1, lobe).squeeze(-1)
    width = probabilities.gather(-1, lobe).squeeze(-1)
    finfo = torch.finfo(width.dtype)
    u_rescaled = ((u_select - lower) / width.clamp_min(finfo.tiny)).clamp(0.0, 1.0 - finfo.eps)
    u_lobe = torch.stack((u_rescaled, u[..., 1]), dim=-1)
    # Every lobe's warp runs for every sample and the chosen one is gathered: cheaper on a GPU
    # than compacting the samples per lobe, and the warps are a few dozen flops each.
    wi_diffuse, _ = cosine_hemisphere(u_lobe)
    wi_specular, _ = sample_ggx_reflection(wo_local, storm_alpha(params.roughness), u_lobe)
    wi_coat, _ = sample_ggx_reflection(wo_local, storm_alpha(params.clearcoat_roughness), u_lobe)
    wis = torch.broadcast_tensors(  # type: ignore[no-untyped-call]  # unannotated in torch
        wi_diffuse, wi_specular, wi_coat
    )
    candidates = torch.stack(wis, dim=-2)
    wi_local = candidates.gather(-2, lobe.unsqueeze(-1).expand(*lobe.shape[:-1], 1, 3)).squeeze(-2)
    return wi_local, pdf(params, wo_local, wi_local, diffuse)


def pdf(
    params: PreviewSurfaceParams, wo_local: torch.Tensor, wi_local: torch.Tensor, diffuse: bool = True
) -> torch.Tensor:
    """Mixture density (...) of `sample` (with the same `diffuse`) at wi, in 1/sr; 0 below the horizon."""
    check_pair(wo_local, wi_local)
    probabilities = lobe_probabilities(params, wo_local, diffuse)
    densities = torch.stack(
        torch.broadcast_tensors(  # type: ignore[no-untyped-call]  # unannotated in torch
            cosine_hemisphere_pdf(wi_local),
            ggx_reflection_pdf(wo_local, wi_local, storm_alpha(params.roughness)),
            ggx_reflection_pdf(wo_local, wi_local, storm_alpha(params.clearcoat_roughness)),
        ),
        dim=-1,
    )
    return where_above((probabilities * densities).sum(-1), wo_local, wi_local)
