"""The leaderboard heat maps: no text of one panel (tick labels, colour-bar labels, titles) runs over another's."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from socbench import plots

MODELS = ["rint", "thevenin", "pngv", "dp", "gnl", "improved_rc", "shepherd", "unnewehr", "nernst", "fang", "liu",
          "tremblay1", "tremblay2", "plett", "esc", "nrc"]
ESTIMATORS = ["coulomb", "ekf", "ukf", "pf"]


def _texts(fig):
    """(axes index, bounding box) of every visible, non-empty text drawn on the figure's axes and colour bars."""
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    out = []
    for k, ax in enumerate(fig.axes):
        items = [ax.title, ax.xaxis.label, ax.yaxis.label, *ax.get_xticklabels(), *ax.get_yticklabels()]
        for t in items:
            if t.get_visible() and t.get_text().strip():
                out.append((k, t.get_window_extent(renderer)))
    return out


@pytest.mark.parametrize("n_models", [2, 16])
def test_heatmap_panels_do_not_overlap(n_models):
    rng = np.random.default_rng(n_models)
    rows = MODELS[:n_models]
    # a SOC panel spanning two decades (log colour bar, the case whose minor labels crowded the bar's label)
    soc = [[float(v) for v in 10 ** rng.uniform(-1, 1, len(ESTIMATORS))] for _ in rows]
    soc[0][2] = None  # a failed cell
    volt = [[float(v) for v in rng.uniform(20, 700, len(ESTIMATORS))] for _ in rows]
    fig = plots.heatmap_figure([(soc, "SOC RMSE on flight-0kg", "SOC RMSE [%]"),
                                (volt, "voltage RMSE on flight-0kg", "voltage RMSE [mV]")], rows, ESTIMATORS)
    texts = _texts(fig)
    assert len(fig.axes) == 4  # two panels, two colour bars
    for (a, box_a), (b, box_b) in itertools.combinations(texts, 2):
        if a != b:
            assert not box_a.overlaps(box_b), f"text of axes {a} overlaps text of axes {b}: {box_a} / {box_b}"
    plots.plt.close(fig)
