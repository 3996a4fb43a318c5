"""Figures (matplotlib, Agg): each function draws on the axes it is given and knows nothing about files or stores.

Units on the axes follow the tables people read: SOC in %, voltage errors in mV, time in minutes.
"""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def figure(nrows: int = 1, ncols: int = 1, width: float = 7.0, height: float = 4.0, **kw):
    """A new figure and its axes (always an array), laid out by matplotlib's constrained layout (panels, colour bars
    and their labels never overlap; ``layout=...`` overrides)."""
    kw.setdefault("layout", "constrained")
    fig, axes = plt.subplots(nrows, ncols, figsize=(width, height), squeeze=False, **kw)
    return fig, axes


def heatmap(ax, values, row_labels, col_labels, title: str, unit: str, fmt: str = "{:.2f}") -> None:
    """A model × estimator heat map; ``None`` entries (no successful run) are hatched grey and marked "failed"."""
    arr = np.array([[np.nan if v is None else float(v) for v in row] for row in values], dtype=float)
    masked = np.ma.masked_invalid(arr)
    cmap = matplotlib.colormaps["viridis_r"].with_extremes(bad="#d9d9d9")
    finite = arr[np.isfinite(arr)]
    if finite.size and finite.min() > 0 and finite.max() / finite.min() > 50:
        norm = matplotlib.colors.LogNorm(vmin=finite.min(), vmax=finite.max())
    else:
        norm = None
    im = ax.imshow(masked, cmap=cmap, norm=norm, aspect="auto")
    ax.set_xticks(range(len(col_labels)), labels=col_labels)
    ax.set_yticks(range(len(row_labels)), labels=row_labels)
    ax.set_title(title, fontsize=10)
    cb = ax.figure.colorbar(im, ax=ax, label=unit, shrink=0.85)
    if norm is not None:  # log scale: plain numbers at 1, 2, 5 × 10^k, no minor labels (they crowd the bar's label)
        ticker = matplotlib.ticker
        cb.ax.yaxis.set_major_locator(ticker.LogLocator(subs=(1.0, 2.0, 5.0)))
        cb.ax.yaxis.set_major_formatter(ticker.FuncFormatter(lambda v, _: f"{v:g}"))
        cb.ax.yaxis.set_minor_formatter(ticker.NullFormatter())
    small = len(row_labels) * len(col_labels) <= 96
    for i in range(arr.shape[0]):
        for j in range(arr.shape[1]):
            if not np.isfinite(arr[i, j]):
                ax.text(j, i, "failed", ha="center", va="center", fontsize=7, color="#555555")
            elif small:  # dark text on the light (good) end of viridis_r, light text on the dark end
                shade = float(im.norm(arr[i, j])) if finite.size > 1 else 0.0
                ax.text(j, i, fmt.format(arr[i, j]), ha="center", va="center", fontsize=7,
                        color="white" if shade > 0.55 else "black")


def heatmap_figure(panels, row_labels, col_labels):
    """Heat maps side by side, one per ``(values, title, unit)`` in ``panels``, sized for the number of rows."""
    fig, axes = figure(1, len(panels), width=5.5 * len(panels), height=max(3.0, 0.35 * len(row_labels) + 1.5))
    for ax, (values, title, unit) in zip(axes[0], panels):
        heatmap(ax, values, row_labels, col_labels, title, unit)
    return fig


def soc_error_band(ax, trace: dict, label: str, color=None) -> None:
    """SOC error ẑ − z of one run [%] with its ±3σ band (σ the filter's own SOC standard deviation)."""
    t = np.asarray(trace["time_s"], dtype=float) / 60.0
    err = 100.0 * np.asarray(trace["soc_err"], dtype=float)
    line = ax.plot(t, err, lw=1.2, label=label, color=color)[0]
    if trace.get("soc_std") is not None:
        band = 300.0 * np.asarray(trace["soc_std"], dtype=float)
        ax.fill_between(t, -band, band, color=line.get_color(), alpha=0.18, lw=0, label=f"±3σ ({label})")
    ax.axhline(0.0, color="black", lw=0.6)
    ax.set_xlabel("time [min]")
    ax.set_ylabel("SOC error [%]")


def voltage_profile(ax_v, ax_dev, traces: dict, title: str) -> None:
    """The paper's voltage profile (measured and each model's predicted voltage) over its deviation panel.

    ``traces``: label -> trace with ``time_s, v_meas, v_pred``; the measured voltage is taken from the first trace.
    """
    colors = matplotlib.colormaps["tab20"]
    first = next(iter(traces.values()))
    t0 = np.asarray(first["time_s"], dtype=float) / 60.0
    ax_v.plot(t0, first["v_meas"], color="black", lw=1.6, label="measured")
    for k, (label, tr) in enumerate(traces.items()):
        t = np.asarray(tr["time_s"], dtype=float) / 60.0
        vp = np.asarray(tr["v_pred"], dtype=float)
        dev = 1000.0 * (np.asarray(tr["v_meas"], dtype=float) - vp)
        c = colors(k % 20)
        ax_v.plot(t, vp, lw=0.8, color=c, label=label)
        ax_dev.plot(t, dev, lw=0.8, color=c)
    ax_dev.axhline(0.0, color="black", lw=0.6)
    ax_v.set_ylabel("terminal voltage [V]")
    ax_v.set_title(title, fontsize=10)
    ax_v.legend(fontsize=6, ncol=4, loc="best")
    ax_dev.set_ylabel("deviation v_meas − v_pred [mV]")
    ax_dev.set_xlabel("time [min]")


def save(fig, path) -> None:
    """Save as PNG atomically (an interrupted report never leaves half an image)."""
    import io

    from .io import atomic_write_bytes

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())
