"""Plots of rate estimates: per axis, the estimate, its ±1σ band and the reference (sedelnikov2024
Figures 9/12 show the same comparison against the gyro)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from fsw.files import atomic_file


def check_plot_path(path) -> str:
    """The image format of a plot path, from its suffix; ValueError when matplotlib cannot write it.
    Tools call it at start, so that a fit is not lost to a typo in the plot's name."""
    from matplotlib.figure import Figure

    suffix = Path(path).suffix.lstrip(".").lower()
    known = Figure().canvas.get_supported_filetypes()
    if suffix not in known:
        raise ValueError(f"{path}: cannot write a plot as {suffix or 'a file without a suffix'!r}; "
                         f"give one of .{', .'.join(sorted(known))}")
    return suffix


def check_plot_path_or_exit(ap, path, option: str = "--plot") -> None:
    """`check_plot_path` at a tool's start: a path matplotlib cannot write is the parser's usage error."""
    if path:
        try:
            check_plot_path(path)
        except ValueError as e:
            ap.error(f"{option} {e}")


def save_figure(fig, path, **kwargs) -> None:
    """`fig.savefig` to `path` atomically (`fsw.files.atomic_file`), in the format of its suffix."""
    with atomic_file(path, "wb") as f:
        fig.savefig(f, format=check_plot_path(path), **kwargs)


def plot_rates(path, t_s: np.ndarray, w_radps: np.ndarray, sigma_radps: np.ndarray | None = None,
               w_ref_radps: np.ndarray | None = None, *, title: str = "", perpendicular_only: bool = False) -> None:
    """Write a PNG with one panel per body axis (°/s); samples whose σ is inf (no information) are
    marked, without a band."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.asarray(t_s, float)
    w = np.degrees(np.asarray(w_radps, float))
    fig, axes = plt.subplots(3, 1, sharex=True, figsize=(9, 7))
    label = "estimate (⊥ B only)" if perpendicular_only else "estimate"
    for i, (ax, name) in enumerate(zip(axes, "xyz")):
        if w_ref_radps is not None:
            ax.plot(t, np.degrees(w_ref_radps[:, i]), color="k", lw=1.0, label="reference")
        ax.plot(t, w[:, i], color="C0", lw=0.9, label=label)
        if sigma_radps is not None:
            s = np.degrees(np.asarray(sigma_radps, float)[:, i])
            s_band = np.where(np.isfinite(s), s, np.nan)         # σ = inf (no information): no band
            ax.fill_between(t, w[:, i] - s_band, w[:, i] + s_band, color="C0", alpha=0.25, lw=0, label="±1σ")
            none = np.isinf(s) & np.isfinite(w[:, i])
            if none.any():
                ax.plot(t[none], w[none, i], "x", color="C3", ms=4, label="σ = ∞ (no information)")
        ax.set_ylabel(f"ω{name} °/s")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper right", fontsize=8)
    axes[-1].set_xlabel("t s")
    if title:
        axes[0].set_title(title, fontsize=9)
    fig.tight_layout()
    try:
        save_figure(fig, path, dpi=110)
    finally:
        plt.close(fig)
