"""The table (and a figure) of a campaign's results: per figure, over the runs, the count, mean, standard
deviation, and the 5/50/95 % points and extremes; made from the results file, or from results in memory."""
from __future__ import annotations

import math

import numpy as np

from bench.campaign import results as rs

STATS = ("runs", "mean", "sd", "min", "p5", "median", "p95", "max")


def figure_values(table, figures) -> dict[str, np.ndarray]:
    """Each figure's values over the stored runs (from the ``r.<name>`` columns; None, a missing value, as NaN)."""
    out = {}
    for f in figures:
        col = f"r.{f}"
        vals = table.column(col).to_pylist() if col in table.column_names else []
        out[f] = np.array([math.nan if v is None else float(v) for v in vals], float)
    return out


def statistics(values: np.ndarray) -> dict:
    v = values[np.isfinite(values)]
    if not v.size:
        return {"runs": 0}
    p5, p50, p95 = np.percentile(v, [5, 50, 95])
    return {"runs": int(v.size), "mean": float(v.mean()), "sd": float(v.std(ddof=1)) if v.size > 1 else math.nan,
            "min": float(v.min()), "p5": float(p5), "median": float(p50), "p95": float(p95), "max": float(v.max())}


def markdown(stats: dict[str, dict]) -> str:
    lines = ["| figure | " + " | ".join(STATS) + " |", "|---|" + "---:|" * len(STATS)]
    for name, s in stats.items():
        cells = [str(s.get("runs", 0))] + [f"{s[k]:.4g}" if k in s and math.isfinite(s[k]) else "–"
                                           for k in STATS[1:]]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def from_file(path, figures=None) -> tuple[dict, dict[str, dict], dict[str, np.ndarray]]:
    """(the campaign's configuration, the statistics per figure, the values) of results file `path`; `figures`:
    default the campaign's, else every scalar result."""
    config, table = rs.read(path)
    if figures is None:
        figures = config.get("figures") or [c[2:] for c in table.column_names if c.startswith("r.")]
    values = figure_values(table, figures)
    return config, {f: statistics(v) for f, v in values.items()}, values


def plot(values: dict[str, np.ndarray], path: str, title: str = "") -> None:
    """One histogram per figure."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    n = len(values)
    fig, axes = plt.subplots(n, 1, figsize=(6, 2.2 * n), squeeze=False)
    for ax, (name, v) in zip(axes[:, 0], values.items()):
        v = v[np.isfinite(v)]
        ax.hist(v, bins=max(5, min(40, int(math.sqrt(max(v.size, 1))) * 2)))
        ax.set_xlabel(name)
        ax.set_ylabel("runs")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
