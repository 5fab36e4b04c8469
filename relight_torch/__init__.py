"""The relighter: torch kernels, cache reading and the relighting methods (see docs/ARCHITECTURE.md).

Importing the package registers the project's codeless USD schemas, so that no stage can be
opened before they are known (USD reads plugin metadata once; see `relight_torch.schema`).
`__version__` is the installed distribution's version: pyproject.toml is where it is written.
`open_cache(path)` opens any cache for relighting (`relight_torch.opening`); what the relighter
it returns offers is `relight_torch.protocol.CacheRelighter`.
"""

from importlib import metadata

from relight_torch.schema import register_schemas

try:
    __version__ = metadata.version("relight")
except metadata.PackageNotFoundError:
    # A source tree put on sys.path without being pip-installed has no metadata to read; PEP 440's
    # local label says so instead of inventing a number (bakes also hash the sources themselves).
    __version__ = "0+unknown"

register_schemas()

from relight_torch.opening import open_cache  # noqa: E402  (after the schemas: it reads cache layers)

__all__ = ["open_cache"]
