"""The cuts relighter's factorised BRDF (`preview_surface.split_factors` / `combine_factors`) and
its column slots: exact rewrites of `split` and of the illumination cut's bookkeeping."""

from __future__ import annotations

import torch

from relight_torch.brdf import preview_surface
from relight_torch.cuts.columns import assign_slots


def _random_params(n: int, generator: torch.Generator) -> preview_surface.PreviewSurfaceParams:
    def uniform(*shape: int) -> torch.Tensor:
        return torch.rand(*shape, generator=generator, dtype=torch.float64)

    return preview_surface.PreviewSurfaceParams(
        diffuse_color=uniform(n, 3),
        emissive_color=torch.zeros(n, 3, dtype=torch.float64),
        specular_color=uniform(n, 3),
        metallic=uniform(n),
        roughness=uniform(n),
        clearcoat=uniform(n),
        clearcoat_roughness=uniform(n),
        ior=1.0 + uniform(n),
        opacity=torch.ones(n, dtype=torch.float64),
        use_specular_workflow=uniform(n) > 0.5,
    )


def _factors(params, wo: torch.Tensor, wi: torch.Tensor, coat: bool, weight: torch.Tensor | None = None):
    """`split_factors` of local directions wo, wi (of any length) through their dot products."""
    return preview_surface.split_factors(
        params, wo[..., 2], wi[..., 2], (wo * wi).sum(-1), coat, weight, (wo * wo).sum(-1), (wi * wi).sum(-1)
    )


def test_factors_sum_to_split_times_light():
    # Sums over S directions of the factors times the light, combined with the colours, equal
    # the sum of split()'s diffuse and specular parts times the light (both workflows, clearcoat,
    # directions below the horizon included).
    generator = torch.Generator().manual_seed(3)
    n, s = 64, 9
    params = _random_params(n, generator)
    wo = torch.nn.functional.normalize(torch.randn(n, 1, 3, generator=generator, dtype=torch.float64), dim=-1)
    wi = torch.nn.functional.normalize(torch.randn(n, s, 3, generator=generator, dtype=torch.float64), dim=-1)
    diffuse_light, specular_light = (torch.rand(n, s, 3, generator=generator, dtype=torch.float64) for _ in range(2))
    diffuse, specular = preview_surface.split(params.with_sample_axis(), wo, wi)
    expected = (diffuse * diffuse_light + specular * specular_light).sum(dim=1)
    factors = _factors(params.with_sample_axis(), wo, wi, coat=True).movedim(0, -1)
    assert factors.shape == (n, s, 6)
    weight = torch.randn(n, s, generator=generator, dtype=torch.float64)
    torch.testing.assert_close(
        _factors(params.with_sample_axis(), wo, wi, coat=True, weight=weight),
        factors.movedim(-1, 0) * weight,
        rtol=1e-12,
        atol=0.0,
    )
    sums_d = torch.einsum("nsf,nsc->nfc", factors[..., :2], diffuse_light)
    sums_s = torch.einsum("nsf,nsc->nfc", factors[..., 2:], specular_light)
    combined = sum(
        preview_surface.combine_factors(
            preview_surface.factor_colours(params, coat=True), torch.cat((sums_d, sums_s), dim=1).movedim(1, 0)
        )
    )
    torch.testing.assert_close(combined, expected, rtol=1e-10, atol=1e-12)
    # Without a coat the first four factors give the same as clearcoat 0.
    uncoated = preview_surface.PreviewSurfaceParams(
        **{**params.__dict__, "clearcoat": torch.zeros(n, dtype=torch.float64)}
    )
    diffuse, specular = preview_surface.split(uncoated.with_sample_axis(), wo, wi)
    four = _factors(uncoated.with_sample_axis(), wo, wi, coat=False).movedim(0, -1)
    torch.testing.assert_close(four, factors[..., :4])
    combined = sum(
        preview_surface.combine_factors(
            preview_surface.factor_colours(uncoated, coat=False),
            torch.cat(
                (
                    torch.einsum("nsf,nsc->nfc", four[..., :2], diffuse_light),
                    torch.einsum("nsf,nsc->nfc", four[..., 2:], specular_light),
                ),
                dim=1,
            ).movedim(1, 0),
        )
    )
    torch.testing.assert_close(
        combined, (diffuse * diffuse_light + specular * specular_light).sum(dim=1), rtol=1e-10, atol=1e-12
    )


def test_slots_keep_the_nodes_a_new_cut_keeps():
    slot_node = torch.full((5,), -1, dtype=torch.int64)
    slot, new = assign_slots(slot_node, torch.tensor([3, 7, 12]), 31)
    assert new.all() and sorted(slot.tolist()) == [0, 1, 2]
    first = dict(zip([3, 7, 12], slot.tolist(), strict=True))
    slot, new = assign_slots(slot_node, torch.tensor([3, 5, 6, 12, 20]), 31)
    assert new.tolist() == [False, True, True, False, True]
    assert slot[0] == first[3] and slot[3] == first[12]  # kept nodes keep their columns
    assert len(set(slot.tolist())) == 5  # 7's slot is free for a new node
    assert sorted(slot_node.tolist()) == [3, 5, 6, 12, 20]
    assert torch.equal(slot_node[slot], torch.tensor([3, 5, 6, 12, 20]))


def test_factors_from_cosines_equal_split_factors():
    # The in-place kernel on dot products equals split_factors with the cosine in the weight,
    # with and without a coat, directions below either horizon and of length != 1 (a frame
    # stored in low precision) included; float64 to 1e-10, float32 within 4 times split_factors'
    # own float32 error against the float64 truth (measured 2.6 times: sharp lobes, ~1e-5).
    generator = torch.Generator().manual_seed(5)
    n, s = 48, 40
    params = _random_params(n, generator)
    params = preview_surface.PreviewSurfaceParams(**{**params.__dict__, "roughness": params.roughness**2})
    wo = torch.nn.functional.normalize(torch.randn(n, 1, 3, generator=generator, dtype=torch.float64), dim=-1)
    wi = torch.nn.functional.normalize(torch.randn(n, s, 3, generator=generator, dtype=torch.float64), dim=-1)
    wo[:4, :, 2] = wo[:4, :, 2].abs()
    wo = wo * (1.0 + 1e-3 * torch.randn(n, 1, 1, generator=generator, dtype=torch.float64))
    wi = wi * (1.0 + 1e-3 * torch.randn(n, s, 1, generator=generator, dtype=torch.float64))
    weight = torch.rand(n, s, generator=generator, dtype=torch.float64)
    rows = params.with_sample_axis()
    for coat in (False, True):
        expected = _factors(rows, wo, wi, coat=coat, weight=weight * wi[..., 2])
        rounded = _factors(rows.to(dtype=torch.float32), wo.float(), wi.float(), coat, (weight * wi[..., 2]).float())
        rounding = (rounded.double() - expected).abs().amax(dim=(1, 2)) / expected.abs().amax(dim=(1, 2))
        roughnesses = (rows.roughness, rows.clearcoat_roughness)[: 1 + coat]
        for dtype, tolerance in ((torch.float64, 1e-10), (torch.float32, 4.0 * float(rounding.max()))):
            factors = preview_surface.split_factors_cosines(
                tuple(r.to(dtype) for r in roughnesses),
                wo[..., 2].to(dtype),
                wi[..., 2].to(dtype),
                (wo * wi).sum(-1).to(dtype),
                weight.to(dtype),
                torch.empty((4 + 2 * coat, n, s), dtype=dtype),
                torch.empty((4, n, s), dtype=dtype),
                (wo * wo).sum(-1).to(dtype),
                (wi * wi).sum(-1).to(dtype),
            )
            assert factors.shape == expected.shape
            error = (factors.double() - expected).abs().amax(dim=(1, 2)) / expected.abs().amax(dim=(1, 2))
            assert float(error.max()) < tolerance, (dtype, coat, error, rounding)
            assert torch.equal(factors[:, expected[0] == 0], torch.zeros_like(factors[:, expected[0] == 0]))
    wo, wi = torch.nn.functional.normalize(wo, dim=-1), torch.nn.functional.normalize(wi, dim=-1)
    torch.testing.assert_close(  # unit directions: |L|^2 = |E|^2 = 1 by default
        preview_surface.split_factors_cosines(
            (rows.roughness,),
            wo[..., 2],
            wi[..., 2],
            (wi * wo).sum(-1),
            weight,
            torch.empty((4, n, s), dtype=torch.float64),
            torch.empty((4, n, s), dtype=torch.float64),
        ),
        _factors(rows, wo, wi, coat=False, weight=weight * wi[..., 2]),
        rtol=1e-10,
        atol=1e-12,
    )
