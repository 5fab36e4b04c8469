"""The relighter: torch kernels, cache reading and the relighting methods (see docs/ARCHITECTURE.md).

Importing the package registers the project's codeless USD schemas, so that no stage can be
opened before they are known (USD reads plugin metadata once; see `relight_torch.schema`).
`open_cache(path)` opens any cache for relighting (`relight_torch.opening`); what the relighter
it returns offers is `relight_torch.protocol.CacheRelighter`.
"""

from relight_torch.schema import register_schemas

register_schemas()

from relight_torch.opening import open_cache  # noqa: E402  (after the schemas: it reads cache layers)

__all__ = ["open_cache"]
