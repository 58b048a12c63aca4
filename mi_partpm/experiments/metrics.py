"""Image metrics for comparing renderings: RMSE, relative MSE, MARE, SSIM, error spread.

All functions take linear-radiance images as NumPy arrays of shape (H, W) or (H, W, C) and
return Python floats. ``img`` is the image under test, ``ref`` the one it is compared with.
"""
from __future__ import annotations

import numpy as np

__all__ = ["rmse", "rel_mse", "display_rel_mse", "mare", "ssim", "tonemap",
           "block_errors", "block_error_share", "mean_ratio", "compare_images"]

#: Added to the reference in relative metrics, so near-black pixels do not divide by ~0.
EPSILON = 1e-2


def _pair(img, ref):
    a, b = np.asarray(img, np.float64), np.asarray(ref, np.float64)
    if a.shape != b.shape:
        raise ValueError(f"images differ in shape: {a.shape} vs {b.shape}")
    return a, b


def rmse(img, ref) -> float:
    """Root mean squared error over all pixels and channels."""
    a, b = _pair(img, ref)
    return float(np.sqrt(np.mean((a - b) ** 2)))


def rel_mse(img, ref, eps: float = EPSILON) -> float:
    """Relative MSE, mean of (img - ref)^2 / (ref^2 + eps)."""
    a, b = _pair(img, ref)
    return float(np.mean((a - b) ** 2 / (b ** 2 + eps)))


def display_rel_mse(img, ref, eps: float = EPSILON) -> float:
    """Relative MSE of the images clamped to the display range [0, 1].

    Clamping keeps the emitter's own pixels (radiance far above 1, antialiased differently at
    different sample counts) from swamping the error of the lit scene.
    """
    a, b = _pair(img, ref)
    return rel_mse(np.minimum(a, 1.0), np.minimum(b, 1.0), eps)


def mare(img, ref, eps: float = EPSILON) -> float:
    """Mean absolute relative error, mean of |img - ref| / (|ref| + eps)."""
    a, b = _pair(img, ref)
    return float(np.mean(np.abs(a - b) / (np.abs(b) + eps)))


def mean_ratio(img, ref) -> float:
    """Mean of img over mean of ref: the overall brightness agreement."""
    a, b = _pair(img, ref)
    return float(a.mean() / b.mean()) if b.mean() != 0 else float("nan")


def tonemap(img) -> np.ndarray:
    """Display values in [0, 1]: clamp and apply the sRGB transfer curve (as the PNGs are)."""
    x = np.clip(np.asarray(img, np.float64), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def ssim(img, ref) -> float:
    """Structural similarity (Wang et al. 2004) of the tone-mapped images, in [-1, 1].

    Computed by scikit-image's ``structural_similarity`` on :func:`tonemap` output (data range
    1, 7x7 window, colour channels averaged).
    """
    from skimage.metrics import structural_similarity

    a, b = _pair(img, ref)
    a, b = tonemap(a), tonemap(b)
    if min(a.shape[:2]) < 7:
        raise ValueError(f"SSIM needs images of at least 7x7 pixels, got {a.shape[:2]}")
    channel_axis = 2 if a.ndim == 3 else None
    return float(structural_similarity(a, b, data_range=1.0, channel_axis=channel_axis))


def block_errors(img, ref, block: int = 8) -> np.ndarray:
    """Each block x block tile's share of the total squared error, as a 2D grid summing to 1.

    Edge tiles that do not fill a whole block are included. All zeros when the images agree.
    """
    a, b = _pair(img, ref)
    err = (a - b) ** 2
    if err.ndim == 3:
        err = err.sum(axis=2)
    h, w = err.shape
    ph, pw = -h % block, -w % block
    err = np.pad(err, ((0, ph), (0, pw)))
    tiles = err.reshape((h + ph) // block, block, (w + pw) // block, block).sum(axis=(1, 3))
    total = tiles.sum()
    return tiles / total if total > 0 else tiles


def block_error_share(img, ref, block: int = 8) -> float:
    """The largest share of the total squared error held by one block x block tile.

    An error spread evenly over an image of B tiles gives about 1/B; an error concentrated in
    one place gives up to 1.
    """
    return float(block_errors(img, ref, block).max())


def compare_images(img, ref) -> dict:
    """Every metric of this module for one pair, as a dict of floats."""
    return {"rmse": rmse(img, ref), "rel_mse": rel_mse(img, ref),
            "display_rel_mse": display_rel_mse(img, ref), "mare": mare(img, ref),
            "ssim": ssim(img, ref), "mean_ratio": mean_ratio(img, ref),
            "max_block_error_share": block_error_share(img, ref)}
