"""BRDFs as sums of coloured primitive terms (the deep-framebuffer papers' material model).

A material is a list of terms (colour, name, params); its BRDF is

    f(wo, wi) = sum over terms of colour * BRDF_name(params; wo, wi).

The names are the keys of `TERM_MODULES`; each module exposes eval / sample / pdf.
"""

from __future__ import annotations

from collections.abc import Sequence
from types import ModuleType
from typing import NamedTuple

import torch

from relight_torch.brdf import (
    blinn_phong,
    cook_torrance,
    lambert,
    minnaert,
    oren_nayar,
    phong,
    preview_surface,
    ward,
)
from relight_torch.brdf.common import check_pair
from relight_torch.brdf.params import BrdfParams
from relight_torch.math.checks import check_last_dim

TERM_MODULES: dict[str, ModuleType] = {
    "lambert": lambert,
    "phong": phong,
    "blinn_phong": blinn_phong,
    "cook_torrance": cook_torrance,
    "oren_nayar": oren_nayar,
    "minnaert": minnaert,
    "ward": ward,
    "preview_surface": preview_surface,
}


class BrdfTerm(NamedTuple):
    """One term: colour (N, 3) weighting the primitive BRDF `name` with its `params`."""

    colour: torch.Tensor
    name: str
    params: BrdfParams


def term_module(name: str) -> ModuleType:
    """The BRDF module of a term name; ValueError naming the known ones otherwise."""
    if name not in TERM_MODULES:
        raise ValueError(f"unknown BRDF term {name!r}; known terms: {', '.join(TERM_MODULES)}")
    return TERM_MODULES[name]


def eval_terms(
    terms: Sequence[tuple[torch.Tensor, str, BrdfParams]], wo_local: torch.Tensor, wi_local: torch.Tensor
) -> torch.Tensor:
    """Sum of colour x primitive BRDF over `terms`, (..., 3) in 1/sr.

    Args:
        terms: (colour (N, 3), term name, params) triples, e.g. `BrdfTerm`s; at least one.
        wo_local, wi_local: (..., 3) unit directions in the local shading frame.

    Raises:
        ValueError: no terms, an unknown name, or a colour not shaped (..., 3).
    """
    if not terms:
        raise ValueError("eval_terms needs at least one BRDF term")
    check_pair(wo_local, wi_local)
    total: torch.Tensor | None = None
    for colour, name, params in terms:
        check_last_dim(colour, 3, f"colour of BRDF term {name!r}")
        value = colour * term_module(name).eval(params, wo_local, wi_local)
        total = value if total is None else total + value
    assert total is not None  # terms is not empty
    return total
