"""A UsdValidation validator for cache layers: every payload file is there, whole.

    relight:PayloadFileValidator   (prim validator, RelightPayload prims)
        error PayloadFileMissing     relight:file does not resolve to an existing file
        error PayloadSizeMismatch    the file's size differs from relight:bytes

It runs with USD's own validators (`ValidationRegistry().GetOrLoadAllValidators()` once
registered), so one UsdValidation pass says whether a cache layer is both well-formed USD and
complete. It checks sizes, not hashes: validation should stay cheap; `relight info` and the
loader (`relight_torch.cache.load`) compare sha256 too.
"""

from __future__ import annotations

import os

from pxr import Usd, UsdValidation

from relight_torch.schema import register_schemas

PAYLOAD_FILE_VALIDATOR = "relight:PayloadFileValidator"


def payload_file_path(prim: Usd.Prim) -> str:
    """Absolute path a RelightPayload's relight:file names ('' if unauthored), anchored at its layer."""
    attribute = prim.GetAttribute("relight:file")
    asset = attribute.Get() if attribute else None
    if not asset or not asset.path:
        return ""
    if asset.resolvedPath:
        return str(asset.resolvedPath)
    layer = attribute.GetPropertyStack(Usd.TimeCode.Default())[0].layer
    return str(layer.ComputeAbsolutePath(asset.path))


def _error(prim: Usd.Prim, name: str, message: str) -> UsdValidation.ValidationError:
    site = UsdValidation.ValidationErrorSite(prim.GetStage(), prim.GetPath())
    return UsdValidation.ValidationError(name, UsdValidation.ValidationErrorType.Error, [site], message)


def _check_payload_file(
    prim: Usd.Prim, time_range: UsdValidation.ValidationTimeRange
) -> list[UsdValidation.ValidationError]:
    """Prim task of PAYLOAD_FILE_VALIDATOR (the time range is unused: nothing is animated)."""
    if prim.GetTypeName() != "RelightPayload":
        return []
    path = payload_file_path(prim)
    if not path or not os.path.isfile(path):
        return [
            _error(prim, "PayloadFileMissing", f"{prim.GetPath()}: relight:file {path or '(empty)'} does not exist")
        ]
    recorded = prim.GetAttribute("relight:bytes").Get()
    size = os.path.getsize(path)
    if size != recorded:
        return [
            _error(
                prim,
                "PayloadSizeMismatch",
                f"{prim.GetPath()}: {path} is {size} bytes, relight:bytes records {recorded}",
            )
        ]
    return []


def register_cache_validators() -> UsdValidation.Validator:
    """Register PAYLOAD_FILE_VALIDATOR with USD's validation registry (idempotent); returns it."""
    register_schemas()
    registry = UsdValidation.ValidationRegistry()
    if not registry.HasValidator(PAYLOAD_FILE_VALIDATOR):
        payload_type = Usd.SchemaRegistry.GetTypeFromName("RelightPayload").typeName
        metadata = UsdValidation.ValidatorMetadata(
            name=PAYLOAD_FILE_VALIDATOR,
            doc="A RelightPayload's relight:file exists beside its cache layer with relight:bytes bytes.",
            keywords=["relight"],
            schemaTypes=[payload_type],
        )
        registry.RegisterPrimValidator(metadata, _check_payload_file)
    return registry.GetOrLoadValidatorByName(PAYLOAD_FILE_VALIDATOR)
