"""Shared fixtures: the Mitsuba variant, with the plugins registered, and small helpers."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

import mitsuba as mi

VARIANT = os.environ.get("PARTPM_TEST_VARIANT", "llvm_ad_rgb")
mi.set_variant(VARIANT)
import mi_partpm  # noqa: E402  (registers the plugins for the variant)

ARTIFACTS = Path(os.environ.get("PARTPM_TEST_ARTIFACTS", Path(__file__).parent / "artifacts"))


@pytest.fixture(scope="session", autouse=True)
def variant():
    """Every test runs under the JIT RGB variant with mi_partpm's plugins registered."""
    mi.set_variant(VARIANT)
    mi_partpm.register()
    return VARIANT


def render(scene, integrator, seed=0, spp=None):
    """Render and return the image as a float64 (H, W, 3) NumPy array."""
    kwargs = {"spp": spp} if spp else {}
    return np.array(mi.render(scene, integrator=integrator, seed=seed, **kwargs),
                    dtype=np.float64)[..., :3]


def save_failure(name, **images):
    """Write the images of a failed comparison as EXR for a person to look at."""
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    for key, img in images.items():
        mi.Bitmap(np.asarray(img, dtype=np.float32)).write(str(ARTIFACTS / f"{name}_{key}.exr"))
    return ARTIFACTS
