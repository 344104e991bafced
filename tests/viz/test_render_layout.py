"""The demos' matplotlib figures: a legend of long labels goes below the axes and must not
cover the x label (the committed figures had it over "t [s]")."""

import numpy as np
import pytest

pytest.importorskip("matplotlib")


def test_a_legend_below_the_axes_leaves_the_x_label_readable(monkeypatch, tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from dolfinx_lopinf.viz import render

    kept = []
    monkeypatch.setattr(plt, "close", lambda fig=None: kept.append(fig))
    t = np.linspace(0.0, 2.0, 200)
    series = {"FOM (unseen load)": np.sin(5 * t),
              "L-OpInf r=8, scheme newmark(beta=0.25, gamma=0.5)": np.sin(5 * t),
              "opinf peer r=8 (first order, 16 states)": np.cos(5 * t)}
    render.curves(tmp_path / "tip.png", t, series, ylabel="tip [m]", title="a long title " * 6)
    fig = kept[-1]
    ax = fig.axes[0]
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    legend = ax.get_legend().get_window_extent(renderer)
    label = ax.xaxis.label.get_window_extent(renderer)
    assert legend.y1 <= label.y0, (legend, label)  # entirely below the x label
    assert (tmp_path / "tip.png").stat().st_size > 0
