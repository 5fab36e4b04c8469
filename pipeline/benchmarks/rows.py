"""The sweep row every method's benchmark writes, and its CSV and JSON files.

One row per (method, parameters, scene, light edit), the same columns for every method:

    method,scene,width,height,light_edit,params,psnr_db,psnr_indirect_db,rel_mse,cache_bytes,bake_s,relight_ms,device

`params` is space-separated key=value (`format_params`), numbers are NaN where they do not apply
(written as 'nan' in CSV, null in JSON). Files are written atomically.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

from pipeline.bake.adapter import parse_params
from relight_torch.io.atomic import write_text_atomic

NAN = float("nan")


@dataclass(frozen=True)
class SweepRow:
    """One measured point of a method's sweep.

    Attributes:
        method: 'direct', 'transfer', 'gather', 'cuts', 'multiview', or a comparison row's name
            ('reference-equal-time', 'reference-full').
        scene: bundled scene name.
        width, height: image size in pixels.
        light_edit: 'shot' or the example light edit's name.
        params: the method's parameters, space-separated key=value (`format_params`).
        psnr_db: PSNR of the relit image against the reference with the matching bounce count.
        psnr_indirect_db: PSNR of the indirect part alone (NaN for direct-only methods).
        rel_mse: relative MSE against the same reference.
        cache_bytes: bytes of the cache's payloads (NaN where nothing is cached).
        bake_s: bake wall time in seconds.
        relight_ms: median wall time of one light edit re-rendered, warm, in ms (NaN where not timed).
        device: what relight_ms was measured on ('cpu', 'cuda:0 <name>').
    """

    method: str
    scene: str
    width: int
    height: int
    light_edit: str
    params: str
    psnr_db: float = NAN
    psnr_indirect_db: float = NAN
    rel_mse: float = NAN
    cache_bytes: float = NAN
    bake_s: float = NAN
    relight_ms: float = NAN
    device: str = "cpu"

    def parameters(self) -> dict[str, str]:
        """`params` as a mapping (values as written)."""
        return parse_params(self.params)


COLUMNS = tuple(field.name for field in dataclasses.fields(SweepRow))
_NUMBER_COLUMNS = ("psnr_db", "psnr_indirect_db", "rel_mse", "cache_bytes", "bake_s", "relight_ms")


def _cell(value: object) -> str:
    if isinstance(value, float):
        return "nan" if math.isnan(value) else f"{value:.6g}"
    return str(value)


def csv_line(row: SweepRow) -> str:
    """One CSV line (no newline) of `row`, in COLUMNS order."""
    buffer = io.StringIO()
    csv.writer(buffer, lineterminator="").writerow([_cell(getattr(row, name)) for name in COLUMNS])
    return buffer.getvalue()


def write_csv(rows: Iterable[SweepRow], path: str | Path) -> None:
    """The header and one line per row, atomically."""
    lines = [",".join(COLUMNS)] + [csv_line(row) for row in rows]
    write_text_atomic(path, "\n".join(lines) + "\n")


def read_csv(path: str | Path) -> list[SweepRow]:
    """Rows written by `write_csv` (or any CSV with exactly COLUMNS as its header).

    Raises:
        ValueError: the header differs from COLUMNS.
    """
    with open(path, newline="") as handle:
        reader = csv.reader(handle)
        header = tuple(next(reader))
        if header != COLUMNS:
            raise ValueError(f"{path}: header {header} differs from the sweep columns {COLUMNS}")
        return [_row({name: cell for name, cell in zip(COLUMNS, cells, strict=True)}) for cells in reader if cells]


def _row(cells: Mapping[str, object]) -> SweepRow:
    values = dict(cells)
    for name in _NUMBER_COLUMNS:
        values[name] = NAN if values[name] in (None, "", "nan") else float(values[name])
    values["width"], values["height"] = int(values["width"]), int(values["height"])
    return SweepRow(**values)


def write_json(rows: Iterable[SweepRow], path: str | Path, context: Mapping[str, object] | None = None) -> None:
    """{"columns": [...], "context": {...}, "rows": [{column: value}]} atomically; NaN as null."""

    def plain(value: object) -> object:
        return None if isinstance(value, float) and not math.isfinite(value) else value

    document = {
        "columns": list(COLUMNS),
        "context": dict(context or {}),
        "rows": [{name: plain(getattr(row, name)) for name in COLUMNS} for row in rows],
    }
    write_text_atomic(path, json.dumps(document, indent=1) + "\n")


def read_json(path: str | Path) -> list[SweepRow]:
    """Rows written by `write_json`."""
    return [_row(item) for item in json.loads(Path(path).read_text())["rows"]]
