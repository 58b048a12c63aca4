"""Pictures for people: tone-mapped images, signed difference heat maps, comparison sheets.

Uses matplotlib's non-interactive Agg backend, so it works on machines without a display.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .metrics import tonemap

__all__ = ["luminance", "difference_range", "save_heatmap", "save_comparison"]


def luminance(img) -> np.ndarray:
    """Rec. 709 luminance of a linear RGB image (a single-channel image is returned as is)."""
    a = np.asarray(img, np.float64)
    if a.ndim == 2:
        return a
    if a.shape[2] == 1:
        return a[..., 0]
    return a[..., 0] * 0.2126 + a[..., 1] * 0.7152 + a[..., 2] * 0.0722


def difference_range(*diffs, percentile: float = 99.0) -> float:
    """A symmetric colour range for signed differences: the given percentile of |diff|.

    A percentile rather than the maximum, so a few pixels (the light's antialiased edge) do
    not wash out the rest; never zero.
    """
    values = np.concatenate([np.abs(np.asarray(d, np.float64)).ravel() for d in diffs])
    v = float(np.percentile(values, percentile)) if values.size else 0.0
    return v if v > 0 else 1e-6


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def _show_difference(ax, diff, vmax, title):
    im = ax.imshow(diff, cmap="RdBu_r", vmin=-vmax, vmax=vmax, interpolation="nearest")
    ax.set_title(title, fontsize=9)
    ax.set_axis_off()
    return im


def save_heatmap(path, img, ref, title: str = "", vmax: float | None = None):
    """Write the signed luminance difference ``img - ref`` as a heat map with a colour bar.

    Red: ``img`` brighter; blue: darker; white: equal. ``vmax`` fixes the colour range (default
    :func:`difference_range`) so several heat maps can share one scale.
    """
    plt = _plt()
    diff = luminance(img) - luminance(ref)
    vmax = difference_range(diff) if vmax is None else vmax
    h, w = diff.shape
    fig, ax = plt.subplots(figsize=(4.2, 4.2 * h / w + 0.4), dpi=max(100, w // 4))
    im = _show_difference(ax, diff, vmax, title)
    fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04, label="luminance difference")
    fig.tight_layout()
    fig.savefig(Path(path))
    plt.close(fig)
    return vmax


def save_comparison(path, images: dict, differences: dict, vmax: float | None = None,
                    suptitle: str = ""):
    """A sheet: the images in the top row, signed difference heat maps below, one colour bar.

    Parameters
    ----------
    images : dict title -> linear image
    differences : dict title -> (img, ref), shown as luminance ``img - ref``
    vmax : float, optional
        Colour range of the heat maps (default: :func:`difference_range` over all of them).
    """
    plt = _plt()
    diffs = {t: luminance(a) - luminance(b) for t, (a, b) in differences.items()}
    vmax = difference_range(*diffs.values()) if vmax is None else vmax
    cols = max(len(images), len(diffs))
    fig, axes = plt.subplots(2, cols, figsize=(3.2 * cols, 6.9), squeeze=False)
    for ax in axes.ravel():
        ax.set_axis_off()
    for ax, (title, img) in zip(axes[0], images.items()):
        ax.imshow(tonemap(img), interpolation="nearest")
        ax.set_title(title, fontsize=9)
    im = None
    for ax, (title, diff) in zip(axes[1], diffs.items()):
        im = _show_difference(ax, diff, vmax, title)
    if im is not None:
        fig.colorbar(im, ax=list(axes[1]), fraction=0.02, pad=0.02,
                     label="luminance difference")
    if suptitle:
        fig.suptitle(suptitle, fontsize=10)
    fig.savefig(Path(path), dpi=110, bbox_inches="tight")
    plt.close(fig)
    return vmax
