"""UsdLux light and shadow linking: the `collection:lightLink` / `collection:shadowLink` of a light
resolved to the object prims it lights / that shadow it, and per-object masks from them.

A link is stored on `Light` as a tuple of object prim paths (geometry prims and point instancers,
instance proxies included) or None, meaning every object (the UsdLux default: `includeRoot = 1`,
nothing excluded). Membership is resolved by `Usd.CollectionAPI.ComputeMembershipQuery()`, so
includes, excludes, `includeRoot` and membership expressions all follow USD's own rules.

Objects of a point instancer are named '<instancer>[i]/<prototype path>' in the scene's object
list (`pipeline.scene.types.SceneObject`); they belong to a link when their instancer does.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from pxr import Sdf, Usd, UsdGeom


def _linkable(prim: Usd.Prim) -> bool:
    """Whether a prim is an object a link can name: a geometry prim or a point instancer."""
    return bool(prim.IsA(UsdGeom.Gprim) or prim.IsA(UsdGeom.PointInstancer))


def _links_everything(collection: Usd.CollectionAPI) -> bool:
    """True when the collection has its default, all-including opinion (no traversal needed)."""
    expression = collection.GetMembershipExpressionAttr().Get()
    return (
        bool(collection.GetIncludeRootAttr().Get())
        and not collection.GetExcludesRel().GetTargets()
        and (expression is None or expression.IsEmpty())
    )


def read_link(collection: Usd.CollectionAPI) -> tuple[str, ...] | None:
    """The object prim paths a light-link or shadow-link collection includes.

    Args:
        collection: `UsdLux.LightAPI(prim).GetLightLinkCollectionAPI()` (or the shadow link's).

    Returns:
        The included object paths in namespace order, or None when the collection includes every
        object of the stage.
    """
    if _links_everything(collection):
        return None
    query = collection.ComputeMembershipQuery()
    stage = collection.GetPrim().GetStage()
    objects = [
        prim
        for prim in Usd.PrimRange(stage.GetPseudoRoot(), Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate))
        if _linkable(prim)
    ]
    included = tuple(str(prim.GetPath()) for prim in objects if query.IsPathIncluded(prim.GetPath()))
    return None if len(included) == len(objects) else included


def write_link(collection: Usd.CollectionAPI, link: tuple[str, ...] | None) -> None:
    """Author a link on the stage's edit target, overriding whatever the layers below say.

    None authors the default (includeRoot on, no includes or excludes, no expression); a tuple
    authors exactly those paths as explicit includes with includeRoot off.
    """
    collection.CreateIncludeRootAttr(link is None)
    collection.CreateIncludesRel().SetTargets([] if link is None else [Sdf.Path(path) for path in link])
    collection.CreateExcludesRel().SetTargets([])
    collection.CreateMembershipExpressionAttr(Sdf.PathExpression())


def linked_objects(object_paths: Sequence[str], link: tuple[str, ...] | None) -> np.ndarray:
    """(O,) bool: which of the scene's objects (by path, in object-id order) the link includes."""
    if link is None:
        return np.ones(len(object_paths), bool)
    members = set(link)
    return np.array([path in members or path.split("[", 1)[0] in members for path in object_paths], bool)


def linked_points(object_paths: Sequence[str], link: tuple[str, ...], object_id: torch.Tensor) -> torch.Tensor:
    """(N,) bool on `object_id`'s device: whether light link `link` includes each point's object
    (`object_id` (N,) indexes `object_paths`)."""
    return torch.from_numpy(linked_objects(object_paths, link)).to(object_id.device)[object_id.long()]


def encode_paths(paths: Sequence[str]) -> np.ndarray:
    """(B,) uint8 UTF-8 bytes of the paths joined by newlines (a pickle-free .npy payload)."""
    return np.frombuffer("\n".join(paths).encode("utf-8"), np.uint8).copy()


def decode_paths(encoded: np.ndarray) -> list[str]:
    """Inverse of `encode_paths`."""
    text = np.asarray(encoded, np.uint8).tobytes().decode("utf-8")
    return text.split("\n") if text else []
