"""World transforms of USD prims, with one line naming the op that pxr cannot evaluate.

An xformOp authored with a value of another type (`string xformOp:translate = "x"`) makes pxr's
transform computations raise `Tf.ErrorException` with a multi-line text naming no prim; the shot
walker, the light reader and the camera reader go through `world_from_local` instead.
"""

from __future__ import annotations

import numpy as np
from pxr import Usd, UsdGeom


def world_from_local(cache: UsdGeom.XformCache, prim: Usd.Prim, relative_to: Usd.Prim | None = None) -> np.ndarray:
    """(4, 4) float64 column-vector transform of `prim` to the world (or to `relative_to`'s space).

    Raises:
        ValueError: an op of the prim or an ancestor is not a transform (`unreadable_op`).
    """
    try:
        if relative_to is None:
            matrix = cache.GetLocalToWorldTransform(prim)
        else:
            matrix = cache.ComputeRelativeTransform(prim, relative_to)[0]
    except Exception:  # pxr's Tf.ErrorException
        raise ValueError(f"{prim.GetPath()}: {unreadable_op(prim, cache.GetTime())}") from None
    return np.array(matrix, np.float64).T


def unreadable_op(prim: Usd.Prim, time: Usd.TimeCode) -> str:
    """Which xformOp of `prim` or an ancestor pxr cannot turn into a matrix, as a message."""
    start = prim
    while prim:
        ops = UsdGeom.Xformable(prim).GetOrderedXformOps() if prim.IsA(UsdGeom.Xformable) else []
        for op in ops:
            try:
                op.GetOpTransform(time)
            except Exception:  # Tf.ErrorException, as above
                where = "" if prim == start else f" of {prim.GetPath()}"
                value = op.GetAttr().Get(time)
                return f"{op.GetName()}{where} = {value!r} (authored as {op.GetTypeName()}) is not a transform"
        prim = prim.GetParent()
    return "world transform cannot be computed"
