"""What a viewer sees of a frame: the view (beauty, a light group, the reference), exposure and the
sRGB view transform, encoded as PNG; and the linear frame as EXR.

Tone mapping happens here and in `relight_torch.io.preview` only (the data stays linear): the view
is scaled by 2^exposure, clamped to [0, 1] and sRGB-encoded (`linear_to_srgb`). PNG bytes are
encoded in memory by Pillow (OpenImageIO's Python binding writes files only).
"""

from __future__ import annotations

import io
import math
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from pipeline.errors import RelightError
from pipeline.serve.session import Frame
from relight_torch.io.exr import write_rgb_exr
from relight_torch.io.preview import linear_to_srgb
from relight_torch.metrics import psnr

MAX_EXPOSURE = 64.0
"""Largest |exposure| in stops (2^64 already maps any float32 radiance to white or black)."""
BEAUTY, REFERENCE, GROUP = "beauty", "reference", "group:"


@dataclass(frozen=True)
class Display:
    """A viewer's display settings: `view` is 'beauty', 'reference' or 'group:<name>'; `exposure` in stops."""

    view: str = BEAUTY
    exposure: float = 0.0

    @staticmethod
    def parse(view: object = BEAUTY, exposure: object = 0.0) -> Display:
        """Checked settings from a client's values (JSON or query strings).

        Raises:
            RelightError: an exposure that is no finite number within +-MAX_EXPOSURE, or a view of
                another form.
        """
        try:
            stops = float(exposure)  # type: ignore[arg-type]
        except (TypeError, ValueError, OverflowError):
            raise RelightError(f"exposure {exposure!r:.80} is not a number") from None
        if isinstance(exposure, bool) or not (math.isfinite(stops) and abs(stops) <= MAX_EXPOSURE):
            raise RelightError(f"exposure {exposure!r:.80} must be finite and within +-{MAX_EXPOSURE:g} stops")
        if not isinstance(view, str) or not (view in (BEAUTY, REFERENCE) or view.startswith(GROUP)):
            raise RelightError(f"view {view!r:.80} must be 'beauty', 'reference' or 'group:<name>'")
        return Display(view, stops)

    @property
    def group(self) -> str | None:
        return self.view[len(GROUP) :] if self.view.startswith(GROUP) else None


def view_image(frame: Frame, display: Display, reference: np.ndarray | None) -> np.ndarray:
    """(H, W, 3) linear image of the frame seen through `display`.

    Raises:
        RelightError: the reference view without a reference, or a light group the frame lacks
            (a frame rendered without groups has none).
    """
    if display.view == REFERENCE:
        if reference is None:
            raise RelightError("view 'reference': the session has no --reference image")
        return reference
    group = display.group
    if group is None:
        return frame.image
    if frame.groups is None or group not in frame.groups:
        have = ", ".join(sorted(frame.groups or {})) or "none rendered"
        raise RelightError(f"view {display.view!r:.80}: no such light group (groups: {have})")
    return frame.groups[group]


def png_bytes(linear: np.ndarray, exposure: float = 0.0, compress_level: int = 1) -> bytes:
    """8-bit sRGB PNG of an (H, W, 3) linear image scaled by 2^exposure.

    Args:
        compress_level: zlib level (1: fast, the frames are streamed over loopback).
    """
    encoded = linear_to_srgb(np.asarray(linear, np.float32) * np.float32(2.0**exposure))
    pixels = np.round(encoded * 255.0).astype(np.uint8)
    buffer = io.BytesIO()
    Image.fromarray(pixels, "RGB").save(buffer, format="PNG", compress_level=compress_level)
    return buffer.getvalue()


def exr_bytes(linear: np.ndarray, layers: dict[str, np.ndarray] | None = None) -> bytes:
    """A float EXR (R, G, B and `layers` as <layer>.R/G/B) of a linear image, through the project's writer."""
    with tempfile.TemporaryDirectory(prefix="relight-serve-") as folder:
        path = Path(folder) / "frame.exr"
        write_rgb_exr(path, linear, layers)
        return path.read_bytes()


def frame_psnr(frame: Frame, reference: np.ndarray | None) -> float | None:
    """PSNR (dB, `relight_torch.metrics.psnr`) of the frame against the reference; None without one."""
    if reference is None:
        return None
    value = psnr(frame.image, reference)
    return value if math.isfinite(value) else None
