"""Closed-form unshadowed irradiance from a sphere light: the projected solid angle of a spherical cap.

A sphere of radius r whose centre lies at distance d from the receiver is seen as a cap of
half-angle alpha, sin alpha = r / d, of uniform radiance (UsdLux spheres emit the same radiance
in every outward direction). With theta the angle between the receiver's unit normal n and the
direction to the centre, the cosine-weighted solid angle over the receiver's upper hemisphere,

    G = integral over the cap of max(n . omega, 0) d omega,

is (Snyder 1996, "Area light sources for real-time graphics", MSR-TR-96-11; in the form of
Lagarde & de Rousiers 2014, "Moving Frostbite to physically based rendering", eq. 18):

    pi sin^2(alpha) max(cos theta, 0)                      |cos theta| >= sin alpha
    (cos theta acos(y) - x sin theta sqrt(1 - y^2)) sin^2(alpha)
        + atan(sin theta sqrt(1 - y^2) / x)                  otherwise (the horizon cuts the cap)

with x = cot alpha and y = -x cot theta. G is in sr (pi for a cap covering the hemisphere), 0 for a
receiver inside the sphere (nothing reaches it), and an untextured, unshaped sphere light of
radiance L gives the irradiance E = L G. For a normal n that is not unit (normals stored in half
precision), G is |n| times G of n / |n|: the integral is homogeneous of degree 1 in n, as the
rect light's closed form is (`polygon.rect_cosine_integral`).
"""

from __future__ import annotations

import math

import torch

from relight_torch.lights.geometry import world_radius
from relight_torch.lights.light import Light, LightKind


def has_sphere_closed_form(light: Light) -> bool:
    """Whether `sphere_cosine_integral` gives the light's unshadowed irradiance (per unit radiance):
    a SphereLight of positive radius (radius 0 is a point light, sampled exactly)."""
    return light.kind is LightKind.SPHERE and world_radius(light) > 0.0


def sphere_cosine_integral(light: Light, points: torch.Tensor, normals: torch.Tensor) -> torch.Tensor:
    """G (N,) of a SphereLight's visible cap at receivers (N, 3) with normals (N, 3) (module doc).

    The horizon-cut band (|cos theta| < sin alpha, a thin band for a small light) is evaluated in
    float64: its terms are O(alpha) each and cancel to O(alpha^3), which float32 would lose for a
    light of a few milliradians.
    """
    radius = world_radius(light)
    centre = torch.as_tensor(light.world_from_light[:3, 3], device=points.device, dtype=points.dtype)
    to_centre = centre - points
    distance2 = (to_centre * to_centre).sum(-1)
    normal_length = normals.norm(dim=-1)
    # cos theta d |n|: the cosine without the two square roots' divisions until needed.
    projection = (to_centre * normals).sum(-1)
    outside = distance2 > radius * radius
    sin2_alpha = torch.where(outside, radius * radius / distance2.clamp_min(torch.finfo(points.dtype).tiny), 1.0)
    denominator = (distance2.sqrt() * normal_length).clamp_min(torch.finfo(points.dtype).tiny)
    cos_theta = (projection / denominator).clamp(-1.0, 1.0)
    value = (math.pi * sin2_alpha) * cos_theta.clamp_min(0.0)
    band = torch.nonzero(outside & (cos_theta.square() < sin2_alpha) & (normal_length > 0)).squeeze(-1)
    if band.numel():
        value.index_copy_(0, band, _horizon_cut(cos_theta[band], sin2_alpha[band]).to(value.dtype))
    return torch.where(outside, value * normal_length, 0.0)


def _horizon_cut(cos_theta: torch.Tensor, sin2_alpha: torch.Tensor) -> torch.Tensor:
    """G (M,) of caps that the receiver's horizon cuts (|cos theta| < sin alpha), in float64."""
    cos_theta, sin2_alpha = cos_theta.double(), sin2_alpha.double()
    sin_theta = (1.0 - cos_theta.square()).clamp_min(0.0).sqrt()
    x = (1.0 / sin2_alpha - 1.0).clamp_min(0.0).sqrt()  # cot alpha
    # sin theta > 0 here: |cos theta| < sin alpha <= 1.
    y = (-x * cos_theta / sin_theta).clamp(-1.0, 1.0)
    s = sin_theta * (1.0 - y.square()).clamp_min(0.0).sqrt()
    # atan2(s, x) = atan(s / x), and pi / 2 for a receiver on the sphere's surface (x = 0).
    value = (cos_theta * torch.acos(y) - x * s) * sin2_alpha + torch.atan2(s, x)
    return value.clamp_min(0.0)
