"""The cache layer as USD: clean under UsdValidation, faithful round trip, hand edits refused."""

from __future__ import annotations

import os
import re

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdGeom, UsdUtils, UsdValidation

from cache_support import bake_bundled, copy_bake
from pipeline.bake.inputs import hash_inputs, input_files
from pipeline.scene import load_scene
from pipeline.scenes import SCENES
from relight_torch.cache.layer import CACHE_VERSION, file_sha256, is_cache_layer, read_cache_layer
from relight_torch.cache.validation import PAYLOAD_FILE_VALIDATOR, register_cache_validators
from relight_torch.errors import RelightError


@pytest.fixture(scope="module")
def baked(tmp_path_factory) -> os.PathLike:
    return bake_bundled("cornell_box", tmp_path_factory.mktemp("baked"))


@pytest.fixture
def cache(baked, tmp_path):
    """A private copy of the bake, free to damage."""
    return copy_bake(baked, tmp_path)


def _all_errors(layer) -> list[str]:
    register_cache_validators()
    registry = UsdValidation.ValidationRegistry()
    context = UsdValidation.ValidationContext(registry.GetOrLoadAllValidators())
    return [
        f"{e.GetName()}: {e.GetMessage()}"
        for e in context.Validate(Usd.Stage.Open(str(layer)))
        if e.GetType() == UsdValidation.ValidationErrorType.Error
    ]


def _edit(layer, prim_path: str, edit) -> None:
    """Apply `edit(prim_spec)` to the layer file, as a person editing it by hand would."""
    sdf = Sdf.Layer.FindOrOpen(str(layer))
    edit(sdf.GetPrimAtPath(prim_path))
    sdf.Save()


def test_written_layer_is_clean_under_every_usd_validator(baked):
    register_cache_validators()
    names = {v.GetMetadata().name for v in UsdValidation.ValidationRegistry().GetOrLoadAllValidators()}
    assert {
        "usdGeomValidators:StageMetadataChecker",
        "usdValidation:AttributeTypeMismatch",
        "usdUtilsValidators:MissingReferenceValidator",
        PAYLOAD_FILE_VALIDATOR,
    } <= names
    assert _all_errors(baked) == []


def test_layer_carries_the_shots_units_and_a_default_prim(baked):
    shot = Usd.Stage.Open(str(baked.parent.parent / "scene" / "cornell_box.usda"))
    stage = Usd.Stage.Open(str(baked))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.GetStageUpAxis(shot)
    assert UsdGeom.GetStageMetersPerUnit(stage) == UsdGeom.GetStageMetersPerUnit(shot)
    assert stage.GetDefaultPrim().GetTypeName() == "RelightCache"
    # Payload paths are anchored ("./x"), not search paths that a resolver may look up elsewhere.
    for prim in stage.GetDefaultPrim().GetChildren():
        assert prim.GetAttribute("relight:file").Get().path.startswith("./")


def test_payload_validator_reports_missing_and_resized_files(cache):
    (cache.parent / "cornell_box.occluders.npy").unlink()
    with open(cache.parent / "cornell_box.dfb.exr", "ab") as handle:
        handle.write(b"\0" * 7)
    errors = _all_errors(cache)
    assert any(e.startswith("PayloadFileMissing: /Cache/occluders") for e in errors), errors
    resized = [e for e in errors if e.startswith("PayloadSizeMismatch")]
    recorded = read_cache_layer(cache).payload("deepFramebuffer").num_bytes
    assert len(resized) == 1 and f"is {recorded + 7} bytes, relight:bytes records {recorded}" in resized[0]


def test_round_trip_of_the_description(baked):
    description = read_cache_layer(baked)
    assert description.method == "direct" and description.resolution == (32, 32)
    assert description.source == str((baked.parent.parent / "scene" / "cornell_box.usda").resolve())
    assert set(description.inputs) == {description.source}
    deep = description.payload("deepFramebuffer")
    assert deep.file == "cornell_box.dfb.exr" and deep.format == "exr"
    assert deep.num_bytes == os.path.getsize(baked.parent / deep.file)
    occluders = description.payload("occluders")
    assert occluders.dtype == "float32" and occluders.shape[1:] == (3, 3)
    assert np.allclose(np.linalg.det(description.world_from_camera[:3, :3]), 1.0)
    assert is_cache_layer(baked)
    assert not is_cache_layer(baked.parent.parent / "scene" / "cornell_box.usda")


def _bump_version(prim):
    prim.attributes["relight:version"].default = CACHE_VERSION + 1


def _remove_sha(prim):
    prim.RemoveProperty(prim.attributes["relight:sha256"])


def _remove_version(prim):
    prim.RemoveProperty(prim.attributes["relight:version"])


def _retype_bytes(prim):
    prim.RemoveProperty(prim.attributes["relight:bytes"])
    Sdf.AttributeSpec(prim, "relight:bytes", Sdf.ValueTypeNames.String).default = "13000"


def _drop_a_hash(prim):
    prim.attributes["relight:inputHashes"].default = []


def _drop_a_constant(prim):
    prim.attributes["relight:constantValues"].default = list(prim.attributes["relight:constantValues"].default)[1:]


def _bad_sha(prim):
    prim.attributes["relight:sha256"].default = "not a digest"


@pytest.mark.parametrize(
    "prim_path, edit, message",
    [
        ("/Cache", _bump_version, f"cache version {CACHE_VERSION + 1} is not supported"),
        # Without the authored value the schema's fallback (version 1, sha "") would stand in silently.
        ("/Cache", _remove_version, "/Cache.relight:version is missing"),
        ("/Cache/deepFramebuffer", _remove_sha, "/Cache/deepFramebuffer.relight:sha256 is missing"),
        ("/Cache/deepFramebuffer", _retype_bytes, "/Cache/deepFramebuffer.relight:bytes = '13000' is not a int64"),
        ("/Cache", _drop_a_hash, "relight:inputHashes has 0 entries for 1 relight:inputFiles"),
        ("/Cache/deepFramebuffer", _drop_a_constant, "relight:constantValues has"),
        ("/Cache/deepFramebuffer", _bad_sha, "relight:sha256 'not a digest' is not a sha256 hex digest"),
    ],
)
def test_hand_edited_layer_is_refused_naming_the_attribute(cache, prim_path, edit, message):
    _edit(cache, prim_path, edit)
    with pytest.raises(RelightError, match=re.escape(message)) as error:
        read_cache_layer(cache)
    assert str(cache) in str(error.value) and "\n" not in str(error.value)


def test_inputs_inside_a_usdz_are_recorded_as_the_package(tmp_path):
    shot = SCENES["cornell_box"].write(tmp_path / "scene")
    wrapper = tmp_path / "scene" / "shot.usda"
    layer = Sdf.Layer.CreateNew(str(wrapper))
    layer.subLayerPaths.append("./cornell_box.usda")
    layer.Save()
    package = tmp_path / "shot.usdz"
    assert UsdUtils.CreateNewUsdzPackage(str(wrapper), str(package))
    scene = load_scene(package, width=8, height=8)
    # The shot's layers are shot.usdz[shot.usda] and shot.usdz[cornell_box.usda]: one file on disk.
    assert input_files(scene) == [str(package.resolve())]
    assert hash_inputs(input_files(scene)) == {str(package.resolve()): file_sha256(package)}
    unpacked = input_files(load_scene(wrapper, width=8, height=8))
    assert unpacked == sorted([str(shot.resolve()), str(wrapper.resolve())])
