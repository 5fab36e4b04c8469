"""The relighter: torch kernels, cache reading and `Relighter` (see docs/ARCHITECTURE.md).

Importing the package registers the project's codeless USD schemas, so that no stage can be
opened before they are known (USD reads plugin metadata once; see `relight_torch.schema`).
"""

from relight_torch.schema import register_schemas

register_schemas()
