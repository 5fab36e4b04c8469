"""The codeless schema plugin: registration, what USD knows about our API, generated files in sync."""

from __future__ import annotations

from pathlib import Path

from pxr import Plug, Sdf, Usd, UsdLux

from relight_torch.schema import PLUGIN_NAME, register_schemas, schema_dir
from relight_torch.schemas import generate

BARZEL_FALLBACKS = {
    "relight:barzel:window:enable": False,
    "relight:barzel:window:width": 1.0,
    "relight:barzel:window:height": 1.0,
    "relight:barzel:window:edge": 0.0,
    "relight:barzel:window:roundness": 1.0,
    "relight:barzel:barnDoor:left": 180.0,
    "relight:barzel:barnDoor:right": 180.0,
    "relight:barzel:barnDoor:top": 180.0,
    "relight:barzel:barnDoor:bottom": 180.0,
    "relight:barzel:near:start": 0.0,
    "relight:barzel:near:end": 0.0,
    "relight:barzel:far:start": -1.0,
    "relight:barzel:far:end": -1.0,
    "relight:barzel:falloff:smooth": True,
    "relight:lightGroup": "",
}


def test_register_is_idempotent():
    register_schemas()
    register_schemas()
    plugins = [p for p in Plug.Registry().GetAllPlugins() if p.name == PLUGIN_NAME]
    assert len(plugins) == 1
    assert Path(plugins[0].path).resolve() == schema_dir().resolve()


def test_schema_registry_knows_barzel_api_and_fallbacks():
    register_schemas()
    registry = Usd.SchemaRegistry()
    assert registry.IsAppliedAPISchema("RelightBarzelLightAPI")
    assert not registry.IsMultipleApplyAPISchema("RelightBarzelLightAPI")
    definition = registry.FindAppliedAPIPrimDefinition("RelightBarzelLightAPI")
    names = set(definition.GetPropertyNames())
    assert names == set(BARZEL_FALLBACKS) | {
        "relight:barzel:cookie:file",
        "relight:barzel:cookie:scale",
        "relight:barzel:cookie:offset",
    }
    for name, fallback in BARZEL_FALLBACKS.items():
        assert definition.GetAttributeFallbackValue(name) == fallback, name
    assert tuple(definition.GetAttributeFallbackValue("relight:barzel:cookie:scale")) == (1.0, 1.0)


def test_applied_api_brings_fallbacks_to_a_light():
    register_schemas()
    stage = Usd.Stage.CreateInMemory()
    light = UsdLux.RectLight.Define(stage, "/Key").GetPrim()
    assert not light.GetAttribute("relight:barzel:barnDoor:top")
    light.ApplyAPI("RelightBarzelLightAPI")
    assert "RelightBarzelLightAPI" in light.GetAppliedSchemas()
    assert light.GetAttribute("relight:barzel:barnDoor:top").Get() == 180.0
    assert not light.GetAttribute("relight:barzel:barnDoor:top").IsAuthored()


def test_every_attribute_is_documented_in_the_source():
    layer = Sdf.Layer.FindOrOpen(str(schema_dir() / "schema.usda"))
    spec = layer.GetPrimAtPath(Sdf.Path("/RelightBarzelLightAPI"))
    assert spec.documentation
    for attribute in spec.attributes:
        assert len(attribute.documentation) > 20, attribute.name


def test_generated_files_match_schema_source(tmp_path):
    generate.generate(tmp_path)
    for name in ("generatedSchema.usda", "plugInfo.json"):
        stale = f"{name} is stale: run python -m relight_torch.schemas.generate"
        assert (tmp_path / name).read_text() == (schema_dir() / name).read_text(), stale
    assert "@PLUG_INFO" not in (tmp_path / "plugInfo.json").read_text()
