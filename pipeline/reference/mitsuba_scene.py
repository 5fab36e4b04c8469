"""Our `Scene` as a Mitsuba 3 scene dict: the independent renderer the reference is checked against.

Needs Mitsuba 3 (the `test` extra); used by `tests/test_reference_mitsuba.py` and
`pipeline.benchmarks.reference_agreement`.

Only what the reference comparison needs, and nothing that maps loosely (anything else raises
ValueError naming it):

* Geometry: one triangle mesh per material (`mi.Mesh` from `Geometry.positions`, per-corner
  shading normals as vertex normals).
* Materials: UsdPreviewSurface without textures, as a Mitsuba BSDF written here in Dr.Jit from
  Storm's `previewSurface.glslfx` (`evaluateLight`), independently of `relight_torch.brdf`, and
  made two-sided with Mitsuba's `twosided`. Mitsuba's built-ins do not fit: 'diffuse' is
  Lambertian while the preview surface's diffuse lobe is scaled by 1 - F(E.h) and carries a
  Schlick specular lobe rising to 1 at grazing (even with specularColor 0), and 'roughconductor'
  uses a complex-IOR Fresnel and Smith masking, not Schlick F0/F90 and Schlick-GGX k = a/2.
  D is the exact GGX, the project's documented departure from Storm's (a^2 + 0.001) numerator.
  Sampled as cosine-weighted diffuse and GGX visible normals half and half (GGX only for
  metals), a different strategy from ours.
* Lights: RectLight as an area emitter on a 'rectangle', SphereLight as one on a 'sphere', a
  zero-angle DistantLight as 'directional', with the
  UsdLux radiance intensity * 2^exposure * color (/ area if normalize), emitting along local -Z
  (rect, one-sided) or outward (sphere). DomeLight (poleAxis Y) as a 'constant' emitter, or with a
  lat-long texture as an 'envmap' with the dome's rotation as to_world: Mitsuba's envmap looks up
  u = atan2(x, -z) / 2 pi mod 1, v = acos(y) / pi, which is the UsdLux convention
  u = 0.5 - atan2(x, z) / 2 pi (the two differ by a half turn of atan2's branch, i.e. nothing;
  `tests/test_reference_mitsuba.py` probes it texel by texel). Mitsuba filters the envmap
  bilinearly and we look up the nearest texel, so the image is handed over upsampled
  `ENVMAP_UPSAMPLING` times by replication: bilinear filtering then differs from nearest only
  within half a fine texel of the texels' edges. No rect texture, shaping, colour temperature,
  Barzel, or per-lobe multipliers. The emitters' shapes are black (they absorb what reaches them), whereas
  our lights are invisible to every ray that is not looking for them: compare pixels away from
  the lights' silhouettes (`light_footprint_mask`).
* Camera: 'perspective' pinhole with our horizontal field of view and transform, box pixel
  filter (a sample counts in the pixel it falls in, as in ours).
* Opacity: Mitsuba's 'mask' around the surface, for a constant opacity or a binary alpha
  cut-out (`_opacity`); scenes with masks use 'volpath', whose shadow rays pass masks.
* Integrator: 'path' with max_depth = max_bounces + 2 (Mitsuba counts the camera segment and the
  segment to the light: max_depth 2 is direct light) and hide_emitters (our lights are not seen
  by camera rays).
"""

from __future__ import annotations

import math

import mitsuba as mi
import numpy as np
import torch

from pipeline.scene.camera import camera_rays
from pipeline.scene.types import Camera, Material, Scene
from pipeline.tracing import Tracer
from relight_torch.lights.emission import intersect_light
from relight_torch.lights.light import Light, LightKind

VARIANT = "scalar_rgb"
"""Mitsuba's LLVM variants would trace the Python BSDF into vectorised kernels, but Dr.Jit 1.x emits
`llvm.minimum`, which the LLVM 14/15 of Debian 12 cannot compile ("Cannot select: fminimum"); the
scalar variant calls the BSDF from Python at each vertex (~20k paths/s, enough for small images).
Set on import: the BSDF class derives from the variant's `mi.BSDF`."""
mi.set_variant(VARIANT)

_MIN_ROUGHNESS = 0.001
_STORM_EPSILON = 0.001
"""Storm's EPSILON, kept in the specular denominator. Its NDF numerator a^2 + 0.001 is NOT kept:
the project uses the exact GGX D on purpose (`relight_torch.brdf.preview_surface` module doc), and
this converter follows the project's definition. With Storm's numerator the gold sphere (roughness
0.2) reflects 1.6x the energy, which this comparison detects (block z down to -13 at one bounce)."""


class StormPreviewSurface(mi.BSDF):
    """Storm's UsdPreviewSurface `evaluateLight` (clearcoat included; exact GGX D) as a one-sided
    Mitsuba BSDF.

    Mitsuba's `si.wi` is our wo (towards the viewer, E) and its `wo` our wi (towards the light, L).
    `eval` returns f_r * N.L, as Mitsuba BSDFs do. Plain Python float arithmetic: in the scalar
    variant it is several times faster than Dr.Jit calls on scalars.

    Properties: diffuse_color, specular_color (lists of 3 floats), metallic, roughness, clearcoat,
    clearcoat_roughness, ior (floats), use_specular_workflow (bool).
    """

    def __init__(self, props: mi.Properties):
        mi.BSDF.__init__(self, props)
        diffuse = np.asarray(props["diffuse_color"], np.float64)
        specular = np.asarray(props["specular_color"], np.float64)
        metallic, ior = props["metallic"], props["ior"]
        reflectance = (1.0 - ior) / (1.0 + ior)
        if props["use_specular_workflow"]:
            f0, f90 = specular, np.ones(3)
        else:
            spec_color = 1.0 + (diffuse - 1.0) * metallic
            f0 = reflectance**2 * spec_color + (spec_color - reflectance**2 * spec_color) * metallic
            f90 = spec_color
            diffuse = diffuse * (1.0 - metallic)
        self.diffuse, self.f0, self.f90 = ([float(v) for v in c] for c in (diffuse, f0, f90))
        self.coat_f0 = reflectance**2
        self.clearcoat = float(props["clearcoat"])
        self.alpha = max(props["roughness"], _MIN_ROUGHNESS) ** 2
        self.coat_alpha = max(props["clearcoat_roughness"], _MIN_ROUGHNESS) ** 2
        self.ggx = mi.MicrofacetDistribution(mi.MicrofacetType.GGX, self.alpha, True)
        self.diffuse_probability = 0.5 if max(self.diffuse) > 0 else 0.0
        self.m_flags = mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide
        self.m_components = [
            mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide,
            mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide,
        ]

    @staticmethod
    def _lobe(alpha: float, cos_l: float, cos_e: float, cos_h: float) -> float:
        """D G / (4 N.L N.E + 0.001) without Fresnel: Storm's, with the exact GGX D (below)."""
        alpha2 = alpha * alpha
        denominator = cos_h * cos_h * (alpha2 - 1.0) + 1.0
        d = alpha2 / (math.pi * denominator * denominator)
        k = 0.5 * alpha
        g = cos_e / (cos_e * (1.0 - k) + k) * cos_l / (cos_l * (1.0 - k) + k)
        return d * g / (4.0 * cos_l * cos_e + _STORM_EPSILON)

    def _eval_pdf(self, wi_view, wo_light) -> tuple[mi.Color3f, float]:
        """(f_r N.L, pdf of `sample`), both 0 unless both directions are above the surface."""
        ex, ey, ez = wi_view[0], wi_view[1], wi_view[2]
        lx, ly, lz = wo_light[0], wo_light[1], wo_light[2]
        if ez <= 0.0 or lz <= 0.0:
            return mi.Color3f(0.0), 0.0
        hx, hy, hz = ex + lx, ey + ly, ez + lz
        h_length = math.sqrt(hx * hx + hy * hy + hz * hz)
        hx, hy, hz = hx / h_length, hy / h_length, hz / h_length
        e_dot_h = ex * hx + ey * hy + ez * hz
        fresnel = max(0.0, 1.0 - e_dot_h) ** 5
        lobe = self._lobe(self.alpha, lz, ez, hz)
        coat = (
            self.clearcoat * (self.coat_f0 + (1.0 - self.coat_f0) * fresnel) * self._lobe(self.coat_alpha, lz, ez, hz)
        )
        value = []
        for diffuse, f0, f90 in zip(self.diffuse, self.f0, self.f90, strict=True):
            specular_f = f0 + (f90 - f0) * fresnel
            value.append((diffuse / math.pi * (1.0 - specular_f) + specular_f * lobe + coat) * lz)
        h = mi.Vector3f(hx, hy, hz)
        specular_pdf = self.ggx.pdf(wi_view, h) / (4.0 * e_dot_h)
        pdf = self.diffuse_probability * lz / math.pi + (1.0 - self.diffuse_probability) * specular_pdf
        return mi.Color3f(*value), pdf

    def sample(self, ctx, si, sample1, sample2, active=True):
        bs = mi.BSDFSample3f()
        diffuse_chosen = sample1 < self.diffuse_probability
        if diffuse_chosen:
            bs.wo = mi.warp.square_to_cosine_hemisphere(sample2)
        else:
            normal, _ = self.ggx.sample(si.wi, sample2)
            bs.wo = mi.reflect(si.wi, normal)
        value, bs.pdf = self._eval_pdf(si.wi, bs.wo)
        bs.eta = 1.0
        bs.sampled_type = int(mi.BSDFFlags.DiffuseReflection if diffuse_chosen else mi.BSDFFlags.GlossyReflection)
        bs.sampled_component = 0 if diffuse_chosen else 1
        return bs, (value / bs.pdf if bs.pdf > 0 else mi.Color3f(0.0))

    def eval(self, ctx, si, wo, active=True):
        return self._eval_pdf(si.wi, wo)[0]

    def pdf(self, ctx, si, wo, active=True):
        return self._eval_pdf(si.wi, wo)[1]

    def eval_pdf(self, ctx, si, wo, active=True):
        return self._eval_pdf(si.wi, wo)

    def to_string(self):
        return f"StormPreviewSurface[diffuse={self.diffuse}, f0={self.f0}, alpha={self.alpha}]"


def _use_variant() -> None:
    """Select our variant and (re-)register the BSDF: another test in the same process may have
    switched Mitsuba to another variant, which drops plugins registered for this one."""
    mi.set_variant(VARIANT)
    mi.register_bsdf("storm_preview_surface", lambda props: StormPreviewSurface(props))


_use_variant()


def _material_bsdf(material: Material) -> dict:
    """Two-sided Storm BSDF dict of an untextured material (a textured opacity allowed), inside
    Mitsuba's 'mask' where it is not opaque (`_opacity`)."""
    textured = [
        name
        for name in (
            "diffuse_color",
            "specular_color",
            "metallic",
            "roughness",
            "clearcoat",
            "clearcoat_roughness",
            "ior",
            "normal",
            "emissive_color",
        )
        if getattr(material, name).texture is not None
    ]
    if textured:
        raise ValueError(f"{material.path}: textured inputs {textured} are not converted")
    if float(material.emissive_color.value.max()) > 0:
        raise ValueError(f"{material.path}: emissive materials are not converted")
    scalar = {
        name: float(getattr(material, name).value[0])
        for name in ("metallic", "roughness", "clearcoat", "clearcoat_roughness", "ior")
    }
    surface = {
        "type": "twosided",
        "material": {
            "type": "storm_preview_surface",
            "diffuse_color": [float(v) for v in material.diffuse_color.value],
            "specular_color": [float(v) for v in material.specular_color.value],
            "use_specular_workflow": bool(material.use_specular_workflow),
            **scalar,
        },
    }
    opacity = _opacity(material)
    return surface if opacity is None else {"type": "mask", "opacity": opacity, "material": surface}


def _opacity(material: Material) -> float | dict | None:
    """Mitsuba's mask opacity of a material: None when opaque, a float for a constant, or a
    'bitmap' of the opacity channel (Mitsuba's bitmap puts uv (0, 0) at the image's lower-left
    texel corner like UsdUVTexture). A cut-out (opacityThreshold > 0) is converted as the
    thresholded texels with nearest filtering, which equals bilinear filtering then the threshold
    for an image whose alpha is 0 or 1 only (the boundary falls half-way between texel centres
    either way); other images raise."""
    opacity_input = material.opacity
    threshold = material.opacity_threshold
    if opacity_input.texture is None:
        value = float(np.clip(opacity_input.value[0], 0.0, 1.0))
        value = float(value >= threshold) if threshold > 0 else value
        return None if value >= 1.0 else value
    texture = opacity_input.texture
    if texture.output != "a" or texture.pixels.shape[2] != 4 or not np.array_equal(texture.st_from_uv, np.eye(3)):
        raise ValueError(f"{material.path}: only the alpha of an RGBA image read through 'st' is converted")
    alpha = texture.pixels[..., 3] * texture.scale[3] + texture.bias[3]
    if threshold <= 0 or not np.all((alpha == 0) | (alpha == 1)):
        raise ValueError(f"{material.path}: only binary alpha cut-outs are converted")
    wrap = {"repeat": "repeat", "clamp": "clamp", "mirror": "mirror"}
    if texture.wrap_s != texture.wrap_t or texture.wrap_s not in wrap:
        raise ValueError(f"{material.path}: wrap modes {texture.wrap_s}, {texture.wrap_t} are not converted")
    data = np.ascontiguousarray((alpha >= threshold).astype(np.float32)[..., None])
    return {
        "type": "bitmap",
        "bitmap": mi.Bitmap(data),
        "raw": True,
        "filter_type": "nearest",
        "wrap_mode": wrap[texture.wrap_s],
    }


def _meshes(scene: Scene) -> dict:
    """One Mitsuba mesh (soup: 3 vertices per triangle) per material id."""
    geometry = scene.geometry
    meshes = {}
    for material_id in np.unique(geometry.material_ids):
        rows = geometry.material_ids == material_id
        num_triangles = int(rows.sum())
        textured = scene.materials[material_id].opacity.texture is not None
        mesh = mi.Mesh(
            f"material_{material_id}",
            3 * num_triangles,
            num_triangles,
            has_vertex_normals=True,
            has_vertex_texcoords=textured,
        )
        params = mi.traverse(mesh)
        buffers = {
            "vertex_positions": geometry.positions[rows],
            "vertex_normals": geometry.normals[rows],
            "faces": np.arange(3 * num_triangles, dtype=np.uint32),
        }
        if textured:
            buffers["vertex_texcoords"] = geometry.uvs[rows]
        for name, values in buffers.items():
            params[name] = type(params[name])(np.ascontiguousarray(values).reshape(-1))
        params.update()
        mesh.set_bsdf(mi.load_dict(_material_bsdf(scene.materials[material_id])))
        meshes[f"mesh_{material_id}"] = mesh
    return meshes


ENVMAP_UPSAMPLING = 32


def light_radiance(light: Light) -> np.ndarray:
    """(3,) UsdLux radiance, written from the schema doc: intensity 2^exposure color [/ area]
    (times the texture, for a dome)."""
    unsupported = {
        "texture": light.texture is not None and light.kind is not LightKind.DOME,
        "shaping": light.shaping is not None,
        "colorTemperature": light.enable_color_temperature,
        "barzel": light.barzel is not None,
        "diffuse/specular": light.diffuse != 1.0 or light.specular != 1.0,
    }
    if any(unsupported.values()):
        raise ValueError(f"{light.path}: {[k for k, v in unsupported.items() if v]} not converted")
    radiance = light.intensity * 2.0**light.exposure * np.asarray(light.color, np.float64)
    if light.normalize and light.kind is not LightKind.DOME:  # the dome's sizeFactor is 1
        linear = light.world_from_light[:3, :3]
        if light.kind is LightKind.RECT:
            area = light.width * light.height * np.linalg.norm(np.cross(linear[:, 0], linear[:, 1]))
        else:
            area = 4.0 * math.pi * (light.radius * np.linalg.norm(linear[:, 0])) ** 2
        radiance = radiance / area
    return radiance


def _dome_emitter(light: Light) -> dict:
    """A 'constant' or 'envmap' emitter of the dome (see the module doc)."""
    if light.pole_axis != "Y":
        raise ValueError(f"{light.path}: poleAxis {light.pole_axis} is not converted")
    radiance = light_radiance(light)
    if light.texture is None:
        return {"type": "constant", "radiance": {"type": "rgb", "value": radiance.tolist()}}
    linear = light.world_from_light[:3, :3]
    rotation = np.eye(4)
    rotation[:3, :3] = linear / np.linalg.norm(linear, axis=0)  # directions ignore the scale
    pixels = np.repeat(
        np.repeat(light.texture * radiance.astype(np.float32), ENVMAP_UPSAMPLING, axis=0), ENVMAP_UPSAMPLING, axis=1
    )
    return {
        "type": "envmap",
        "bitmap": mi.Bitmap(np.ascontiguousarray(pixels, np.float32)),
        "to_world": mi.ScalarTransform4f(rotation.tolist()),
    }


def _emitter(light: Light) -> dict:
    """A black shape with an area emitter of the light's radiance, or the dome's emitter."""
    if light.kind is LightKind.DOME:
        return _dome_emitter(light)
    emitter = {"type": "area", "radiance": {"type": "rgb", "value": light_radiance(light).tolist()}}
    black = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}}
    if light.kind is LightKind.RECT:
        # Mitsuba's rectangle spans [-1, 1]^2 and emits along +Z: scale it, then turn +Z to -Z.
        light_from_rectangle = np.diag([0.5 * light.width, -0.5 * light.height, -1.0, 1.0])
        to_world = light.world_from_light @ light_from_rectangle
        return {
            "type": "rectangle",
            "to_world": mi.ScalarTransform4f(to_world.tolist()),
            "emitter": emitter,
            "bsdf": black,
        }
    if light.kind is LightKind.SPHERE and light.radius > 0:
        to_world = light.world_from_light @ np.diag([light.radius, light.radius, light.radius, 1.0])
        return {
            "type": "sphere",
            "to_world": mi.ScalarTransform4f(to_world.tolist()),
            "emitter": emitter,
            "bsdf": black,
        }
    if light.kind is LightKind.DISTANT and light.angle == 0.0:
        # A zero-angle DistantLight is a delta light whose irradiance is its radiance (UsdLux).
        direction = -light.world_from_light[:3, 2] / np.linalg.norm(light.world_from_light[:3, 2])
        return {
            "type": "directional",
            "direction": direction.tolist(),
            "irradiance": {"type": "rgb", "value": light_radiance(light).tolist()},
        }
    raise ValueError(f"{light.path}: {light.kind.value} is not converted")


def _sensor(camera: Camera, spp: int, seed: int) -> dict:
    """Pinhole with our horizontal fov. Mitsuba's camera looks down +Z with +X to the left of the
    image, ours down -Z with +X to the right: a half turn about Y maps one onto the other."""
    if camera.horizontal_aperture_offset or camera.vertical_aperture_offset:
        raise ValueError(f"{camera.path}: aperture offsets are not converted")
    fov = math.degrees(2.0 * math.atan(0.5 * camera.horizontal_aperture / camera.focal_length))
    to_world = camera.world_from_camera @ np.diag([-1.0, 1.0, -1.0, 1.0])
    return {
        "type": "perspective",
        "fov": fov,
        "fov_axis": "x",
        "near_clip": float(camera.clipping_range[0]),
        "far_clip": float(camera.clipping_range[1]),
        "to_world": mi.ScalarTransform4f(to_world.tolist()),
        "sampler": {"type": "independent", "sample_count": spp, "seed": seed},
        "film": {
            "type": "hdrfilm",
            "width": camera.width,
            "height": camera.height,
            "rfilter": {"type": "box"},
            "pixel_format": "rgb",
            "component_format": "float32",
        },
    }


def scene_dict(scene: Scene, camera: Camera, max_bounces: int, spp: int, seed: int = 0) -> dict:
    """The Mitsuba scene dict of our scene seen by `camera`.

    Args:
        scene: a scene whose materials, lights and camera convert (see the module doc).
        camera: the camera; its width and height are the film's.
        max_bounces: our `ReferenceSettings.max_bounces` (0 = direct light only).
        spp: samples per pixel; seed: the sampler's seed.
    """
    if camera.exposure_scale != 1.0:
        raise ValueError(f"{camera.path}: camera exposure is not converted")
    # 'volpath' carries shadow rays through masks (null BSDFs); 'path' stops them at any surface.
    masked = any(_opacity(scene.materials[index]) is not None for index in np.unique(scene.geometry.material_ids))
    result = {
        "type": "scene",
        "integrator": {"type": "volpath" if masked else "path", "max_depth": max_bounces + 2, "hide_emitters": True},
        "sensor": _sensor(camera, spp, seed),
    }
    result.update(_meshes(scene))
    for index, light in enumerate(scene.lights):
        result[f"light_{index}"] = _emitter(light)
    return result


def render(scene: Scene, camera: Camera, max_bounces: int, spp: int, seed: int = 0) -> np.ndarray:
    """(H, W, 3) float32 Mitsuba render of our scene (linear radiance, row 0 at the top)."""
    _use_variant()
    mitsuba_scene = mi.load_dict(scene_dict(scene, camera, max_bounces, spp, seed))
    return np.array(mi.render(mitsuba_scene, spp=spp, seed=seed), dtype=np.float32)


def light_footprint_mask(scene: Scene, camera: Camera, num_offsets: int = 4) -> np.ndarray:
    """(H, W) bool: pixels where some camera ray (a num_offsets^2 grid over the pixel, edges
    included) meets a light before any surface; there Mitsuba sees the black emitter and we see
    what lies behind the (invisible) light."""
    tracer = Tracer(scene.geometry)
    grid = np.linspace(0.0, 1.0, num_offsets, dtype=np.float32)
    covered = np.zeros((camera.height, camera.width), bool)
    for dy in grid:
        for dx in grid:
            offsets = np.broadcast_to(np.array([dx, dy], np.float32), (camera.height, camera.width, 2))
            origins, directions = (a.reshape(-1, 3) for a in camera_rays(camera, np.ascontiguousarray(offsets)))
            surface = tracer.intersect(origins, directions).distance
            for light in scene.lights:
                to_light = intersect_light(light, torch.from_numpy(origins), torch.from_numpy(directions)).numpy()
                covered |= (to_light < surface).reshape(camera.height, camera.width)
    return covered
