"""Mitsuba's ``path`` at many samples per pixel, rendered in chunks: the experiments'
references and their path-traced curves. One wavefront of 480 x 480 x 2048 samples would
hold half a billion lanes; chunks bound the memory and let a progress line come per chunk."""
from __future__ import annotations

from typing import Callable, Optional, Tuple

import mitsuba as mi
import numpy as np

from ..timing import timed

__all__ = ["path_in_chunks"]


def path_in_chunks(scene, spp: int, seed: int, chunk_spp: int, integrator=None,
                   say: Optional[Callable[[str], None]] = None,
                   label: str = "path") -> Tuple[np.ndarray, float]:
    """``spp`` samples per pixel of ``integrator`` (default Mitsuba's ``path``) in chunks of at
    most ``chunk_spp``, chunk c seeded ``seed + c`` (mod 2^32, mi.render's range), averaged
    by their sample counts; returns the (H, W, 3) image and the seconds the renders took.
    ``say`` receives a line per chunk when there is more than one."""
    integrator = integrator or mi.load_dict({"type": "path"})
    chunks = max(1, -(-spp // chunk_spp))
    total, seconds = None, 0.0
    for c in range(chunks):
        n = min(chunk_spp, spp - c * chunk_spp)
        if say is not None and chunks > 1:
            say(f"{label}, chunk {c + 1} of {chunks} ({n} spp)")
        img, t = timed(lambda: mi.render(scene, integrator=integrator, spp=n,
                                         seed=(seed + c) % 2**32))
        img = np.array(img, dtype=np.float64)[..., :3] * n
        total, seconds = (img if total is None else total + img), seconds + t
    return total / spp, seconds
