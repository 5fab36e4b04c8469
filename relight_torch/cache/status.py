"""Is a cache usable? Every check the loader makes, collected instead of raised (for `relight info`).

A cache is 'valid' when every payload passes `load.check_payload` (present, header as recorded,
size and sha256 as recorded) and every input the bake read is unchanged; 'corrupt' when a payload
fails; 'stale' when only inputs changed. A layer that cannot be read at all still raises, as in
`layer.read_cache_layer`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from relight_torch.cache.layer import CacheDescription, Payload, read_cache_layer
from relight_torch.cache.load import check_payload, stale_inputs
from relight_torch.errors import RelightError


@dataclass(frozen=True)
class PayloadStatus:
    """One payload file as found on disk.

    Attributes:
        payload: what the layer records.
        path: the file the layer names, resolved.
        num_bytes: its size on disk, None when missing.
        problem: None when it passes every check, else the loader's one-line error.
    """

    payload: Payload
    path: Path
    num_bytes: int | None
    problem: str | None


@dataclass(frozen=True)
class CacheStatus:
    """A cache layer's description and what was found checking it.

    Attributes:
        path: the cache layer.
        description: what the layer records.
        payloads: one status per payload, in the layer's order.
        stale_inputs: input file -> 'missing' or 'changed', for the inputs that are not as baked.
    """

    path: Path
    description: CacheDescription
    payloads: tuple[PayloadStatus, ...]
    stale_inputs: dict[str, str]

    @property
    def verdict(self) -> str:
        """'corrupt' (a payload fails), 'stale' (an input changed) or 'valid'."""
        if any(status.problem for status in self.payloads):
            return "corrupt"
        return "stale" if self.stale_inputs else "valid"


def cache_status(path: str | os.PathLike[str]) -> CacheStatus:
    """Check a cache layer's payloads and inputs without loading the payloads' pixels.

    Raises:
        RelightError: the layer itself is missing, unreadable or malformed.
    """
    path = Path(path)
    description = read_cache_layer(path)
    statuses = []
    for payload in description.payloads:
        file = (path.parent / payload.file).resolve()
        try:
            check_payload(path, description, payload)
            problem = None
        except RelightError as error:
            problem = str(error)
        size = file.stat().st_size if file.is_file() else None
        statuses.append(PayloadStatus(payload=payload, path=file, num_bytes=size, problem=problem))
    return CacheStatus(
        path=path, description=description, payloads=tuple(statuses), stale_inputs=stale_inputs(description)
    )
