"""Figures: pyvista off-screen field renders and matplotlib curves.

pyvista and matplotlib are imported lazily, so the numpy core never needs them.
Every function writes one PNG and returns its path. Every curve figure has a title saying
what is plotted and labelled axes; its legend sits beside the axes, never over the data, and
long titles are wrapped rather than cut.
"""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np


def _pyvista():
    try:
        import pyvista
    except ImportError as exc:  # pragma: no cover
        raise ImportError("rendering needs pyvista: pip install pyvista") from exc
    pyvista.OFF_SCREEN = True
    return pyvista


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


#: where a legend goes: beside the axes (upper left corner just right of them), so it never
#: covers a curve; ``savefig(bbox_inches="tight")`` keeps it in the picture
BESIDE = {"loc": "upper left", "bbox_to_anchor": (1.01, 1.0), "borderaxespad": 0.0}
#: ... or below the axes (under the x label) when its labels are long: beside them, a legend
#: of long labels would squeeze the axes into a narrow strip
BELOW = {"loc": "upper left", "borderaxespad": 0.0}
#: labels longer than this put the legend below the axes
LONG_LABEL = 34


def _wrap(title: str, width: int = 70) -> str:
    """A long title on several lines instead of cut at the figure's edge."""
    return "\n".join(textwrap.fill(line, width) for line in str(title).split("\n"))


def _finish(fig, ax, path, *, xlabel: str, ylabel: str, title: str, legend: dict | None = None) -> Path:
    """Label, grid, legend (beside the axes - below them when a label is longer than
    LONG_LABEL characters - unless ``legend``, extra ``ax.legend`` arguments, says otherwise),
    save and close a one-axis matplotlib figure."""
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(_wrap(title))
    ax.grid(True, which="both", alpha=0.3)
    handles = (legend or {}).get("handles") or ax.get_legend_handles_labels()[0]
    longest = max((len(h.get_label()) for h in handles), default=0)
    below_axes = longest > LONG_LABEL
    where = BESIDE
    if below_axes:  # below the x label: where it ends, in axes coordinates
        fig.tight_layout()
        fig.canvas.draw()
        box = ax.xaxis.label.get_window_extent(fig.canvas.get_renderer())
        below = ax.transAxes.inverted().transform((0.0, box.y0))[1] - 0.03
        where = BELOW | {"bbox_to_anchor": (0.0, below)}
    ax.legend(fontsize=8, **(where | (legend or {})))
    if not below_axes:  # a legend below keeps the layout it was placed in: laid out again,
        fig.tight_layout()  # the axes would shrink to make room and it would cover the x label
    fig.savefig(path, dpi=130, bbox_inches="tight")
    import matplotlib.pyplot as plt

    plt.close(fig)
    return Path(path)


def beam_shapes(path, x: np.ndarray, shapes: dict, times: list, *, title: str = "") -> Path:
    """Render 1D beam deflections as 3D tubes (pyvista, off-screen), one panel per time.

    Args:
        x: (n,) node coordinates.
        shapes: label -> (n, len(times)) deflections; the first entry is drawn as a thick
            grey tube (the reference), the others as thin coloured lines on top.
        times: the time of each column.
    """
    pv = _pyvista()
    colors = ["silver", "crimson", "royalblue", "darkorange"]
    reference = next(iter(shapes.values()))
    amplitude = max(np.abs(s).max() for s in shapes.values())
    scale = 0.1 * (x[-1] - x[0]) / amplitude  # largest deflection = a tenth of the span
    n_panels = len(times)
    plotter = pv.Plotter(shape=(n_panels, 1), off_screen=True, window_size=(1100, 260 * n_panels),
                         border=False)
    for j, t in enumerate(times):
        plotter.subplot(j, 0)
        lines = [f"t = {t:.3f} s"]
        for i, (label, s) in enumerate(shapes.items()):
            # later entries sit slightly towards the camera so they are drawn on top
            pts = np.column_stack([x, scale * s[:, j], np.full_like(x, 0.05 * i)])
            line = pv.lines_from_points(pts)
            if i == 0:
                plotter.add_mesh(line.tube(radius=0.008 * (x[-1] - x[0])), color=colors[0])
            elif i == 1:
                plotter.add_mesh(line, color=colors[i], line_width=3)
            else:
                plotter.add_mesh(pv.PolyData(pts[::6]), color=colors[i % len(colors)],
                                 point_size=9, render_points_as_spheres=True)
            if i:
                err = np.linalg.norm(s[:, j] - reference[:, j]) / np.linalg.norm(reference[:, j])
                lines.append(f"{label}: rel. error {err:.1e}")
        plotter.add_mesh(pv.Line((x[0], 0, -0.1), (x[-1], 0, -0.1)), color="black", line_width=1)
        plotter.add_text("\n".join(lines), font_size=9, position="upper_left")
        if j == 0:
            legend = [[label, colors[i % len(colors)]] for i, label in enumerate(shapes)]
            plotter.add_legend(legend, bcolor="white", face="circle", size=(0.22, 0.3),
                               loc="lower right")
        plotter.view_xy()
        plotter.camera.focal_point = (0.5 * (x[0] + x[-1]), 0.0, 0.0)
        plotter.camera.position = (0.5 * (x[0] + x[-1]), 0.0, 3.0)
        plotter.camera.parallel_projection = True
        plotter.camera.parallel_scale = 0.15 * (x[-1] - x[0])
    if title:
        plotter.subplot(n_panels - 1, 0)
        plotter.add_text(title, font_size=8, position="lower_right")
    path = Path(path)
    plotter.screenshot(str(path))
    plotter.close()
    return path


def error_vs_r(path, rows: list[dict], *, title: str = "",
               series=(("train_error", "train"), ("test_error", "test")),
               floors=(("projection_error_test", "projection (test)"),),
               ylabel: str = "relative state error") -> Path:
    """Relative error against r for every method: ``series`` are (row key, label) pairs drawn
    solid, dashed, dash-dotted, ... (default: the training and test errors), ``floors`` the
    projection errors of the L-OpInf rows (dotted, black and grey) - what no ROM in this basis
    can beat. The legend has one entry per method (colour and marker), one per series (line
    style, e.g. "train [0, 0.03] s" solid, "test [0.03, 0.18] s" dashed) and the floors."""
    plt = _pyplot()
    from matplotlib.lines import Line2D

    fig, ax = plt.subplots(figsize=(7.6, 4.4))
    # distinct markers so coinciding curves stay visible (L-OpInf: large hollow markers)
    styles = {"intrusive": ("intrusive", "C2", "^", 5, None),
              "opinf": ("standard OpInf", "C3", "x", 7, None),
              "lopinf": ("L-OpInf", "C0", "o", 10, "none"),
              "lopinf_nsd": ("L-OpInf, Kh <= 0", "C1", "D", 7, "none"),
              "lopinf_del": ("L-OpInf, DEL data", "C4", "s", 8, "none"),
              "lopinf_fd": ("L-OpInf, finite differences", "C5", "v", 7, "none"),
              "lopinf_mass_I": ("L-OpInf, Mh = I", "C6", "P", 7, "none")}
    lines = ["-", "--", "-.", (0, (1, 1))]
    handles = []
    for method, (label, color, marker, size, face) in styles.items():
        sel = sorted((r for r in rows if r["method"] == method), key=lambda r: r["r"])
        if not sel:
            continue
        rs = [r["r"] for r in sel]
        kw = dict(color=color, marker=marker, markersize=size, markerfacecolor=face)
        for i, (key, _) in enumerate(series):
            ax.semilogy(rs, [min(r[key], 1e3) for r in sel], linestyle=lines[i % len(lines)], **kw)
        handles.append(Line2D([], [], linestyle="none", label=label, **kw))
    handles += [Line2D([], [], color="0.3", linestyle=lines[i % len(lines)], label=name)
                for i, (_, name) in enumerate(series)]
    sel = sorted((r for r in rows if r["method"] == "lopinf"), key=lambda r: r["r"])
    for i, (key, name) in enumerate(floors):
        if sel and all(key in r for r in sel):
            handles += ax.semilogy([r["r"] for r in sel], [r[key] for r in sel], ":",
                                   color=("k", "0.55")[i % 2], lw=1.6, label=name)
    ax.set_xticks(sorted({r["r"] for r in rows}))
    return _finish(fig, ax, path, xlabel="reduced dimension r", ylabel=ylabel, title=title,
                   legend={"handles": handles})


def curves(path, t: np.ndarray | dict, series: dict, *, ylabel: str, title: str = "",
           logy: bool = False, vline: float | None = None, xlabel: str = "t [s]",
           colors: list | None = None, markers: bool = False) -> Path:
    """Time series (label -> values) on one axis; ``t`` may be one array or label -> array.
    The first series is drawn thicker (the reference); ``colors`` overrides the palette.
    ``markers``: a distinct marker per series (for few points, e.g. against r; coinciding
    curves stay visible), and integer x ticks at the points when every x is a whole number."""
    colors = colors or ["C7", "C0", "C3", "C2", "C1"]
    shapes = ["o", "x", "^", "s", "v", "D", "P"]
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7.0, 3.8))
    xs = []
    for i, (label, values) in enumerate(series.items()):
        tt = np.asarray(t[label] if isinstance(t, dict) else t, dtype=float)
        xs.append(tt)
        values = np.asarray(values, dtype=float)
        if logy:
            values = np.where(values > 0, values, np.nan)
        kw = dict(marker=shapes[i % len(shapes)], markersize=9 - i % 4, markerfacecolor="none") \
            if markers else {}
        ax.plot(tt, values, lw=1.0 if i else 1.6, label=label, color=colors[i % len(colors)], **kw)
    if logy:
        ax.set_yscale("log")
    x_all = np.concatenate(xs) if xs else np.array([])
    if markers and x_all.size and np.all(x_all == np.round(x_all)):
        ax.set_xticks(sorted(set(x_all.astype(int).tolist())))
    if vline is not None:
        ax.axvline(vline, color="k", ls=":", lw=1, label="end of training")
    return _finish(fig, ax, path, xlabel=xlabel, ylabel=ylabel, title=title)


def wave_shapes(path, x: np.ndarray, series: dict, *, title: str = "") -> Path:
    """Pairs of curves 'FOM t=..' / 'ROM .. t=..' on one panel per time (label suffix)."""
    plt = _pyplot()
    times = sorted({label.split("t=")[-1] for label in series}, key=float)
    fig, axes = plt.subplots(len(times), 1, figsize=(7.5, 2.2 * len(times)), sharex=True)
    axes = np.atleast_1d(axes)
    for ax, t in zip(axes, times):
        for i, (label, values) in enumerate((k, v) for k, v in series.items() if k.endswith(f"t={t}")):
            ax.plot(x, values, lw=3.0 if i == 0 else 1.2, color="C7" if i == 0 else "C3",
                    ls="-" if i == 0 else "--", label=label.rsplit(" t=", 1)[0])
        ax.set_ylabel(f"q(x, {t})")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8, **BESIDE)
    axes[0].set_title(_wrap(title))
    axes[-1].set_xlabel("x")
    fig.tight_layout()
    fig.savefig(path, dpi=130, bbox_inches="tight")
    plt.close(fig)
    return Path(path)


def speed_vs_error(path, points: dict, *, fom_seconds: float | None = None, title: str = "") -> Path:
    """Scatter of (seconds, error) per label, with the FOM time as a vertical line."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    markers = ["o", "D", "x", "^", "*", "s", "v", "P"]
    for i, (label, (secs, errs)) in enumerate(points.items()):
        ax.loglog(secs, errs, markers[i % len(markers)], label=label, markersize=8 if i else 10,
                  markerfacecolor="none" if i < 2 else None, color=f"C{i}")
    if fom_seconds:
        ax.axvline(fom_seconds, color="k", ls=":", label=f"FOM {fom_seconds:.1f} s")
    return _finish(fig, ax, path, xlabel="wall time [s]", ylabel="relative test error", title=title)


def grid_on_root(V):
    """The mesh of a Lagrange-type space ``V`` as one pyvista UnstructuredGrid on rank 0
    (None on the other ranks), its points the global dof blocks of V: point i carries dof
    block i, so a global dof vector u (e.g. ``state_map.to_dofs(state)``) is drawn as
    ``u.reshape(-1, bs)`` on any number of ranks. Collective (every rank sends its owned
    cells, from ``dolfinx.plot.vtk_mesh(V)``, and the coordinates of its local dof blocks;
    shared blocks are one point). On one rank: the grid of ``vtk_mesh(V)`` as it is."""
    from dolfinx import plot

    pv = _pyvista()
    comm = V.mesh.comm
    topology, cell_types, geometry = plot.vtk_mesh(V)
    if comm.size == 1:
        return pv.UnstructuredGrid(topology, cell_types, geometry)
    imap = V.dofmap.index_map
    glob = imap.local_to_global(np.arange(imap.size_local + imap.num_ghosts, dtype=np.int32))
    # VTK's flat topology: per cell its number of points, then the points (local blocks); a
    # space's cells all have the same number (vtk_mesh of a FunctionSpace)
    n_cells = len(cell_types)
    topo = np.asarray(topology, dtype=np.int64).reshape(n_cells, -1 if n_cells else 1).copy()
    topo[:, 1:] = glob[topo[:, 1:]]
    pieces = comm.gather((topo.ravel(), np.asarray(cell_types), glob, np.asarray(geometry)), root=0)
    if comm.rank != 0:
        return None
    points = np.zeros((imap.size_global, 3))
    for _, _, g, x in pieces:
        points[g] = x
    return pv.UnstructuredGrid(np.concatenate([p[0] for p in pieces]),
                               np.concatenate([p[1] for p in pieces]), points)


#: the fishtail's view: from above, lateral bending in the image plane
TOP_VIEW = [(0.0, 0.45, 0.12), (0.0, 0.0, 0.12), (1, 0, 0)]


#: the colour bar of a deformed-shape panel when the caller gives none: three labels of two
#: digits inside the panel (pyvista's five labels of three digits overlap in a narrow panel)
DEFAULT_BAR = {"n_labels": 3, "fmt": "%.2g", "width": 0.6, "position_x": 0.3, "position_y": 0.04,
               "title_font_size": 14, "label_font_size": 12}


def deformed_side_by_side(path, grid, frames: list[dict], *, magnify: float, titles=None,
                          clim=None, camera=None, parallel_scale: float | None = None,
                          panel=(420, 360), title: str | None = None,
                          scalar_bar: dict | None = None) -> Path:
    """3D deformed shapes, one row per frame, one column per label (e.g. FOM | ROM).

    Args:
        grid: a pyvista UnstructuredGrid of the undeformed mesh (points in dof order).
        frames: list of {label: (n_points, 3) displacement}; one row each.
        magnify: displacement magnification.
        titles: optional row titles (e.g. times).
        camera: pyvista camera position (default :data:`TOP_VIEW`); ``parallel_scale`` makes
            the projection parallel with that scale (true proportions across panels).
        panel: (width, height) of one panel in pixels.  title: a caption (lower right).
        scalar_bar: the colour bar's ``scalar_bar_args``; it is then drawn in the last row's
            first panel (default: in the first row's last panel, pyvista's placement).
    """
    pv = _pyvista()
    labels = list(frames[0])
    plotter = pv.Plotter(shape=(len(frames), len(labels)), off_screen=True,
                         window_size=(panel[0] * len(labels), panel[1] * len(frames)), border=False)
    if clim is None:
        clim = (0.0, max(np.linalg.norm(u, axis=1).max() for f in frames for u in f.values()))
    outline = grid.extract_surface(algorithm=None).extract_feature_edges()
    bar_at = (len(frames) - 1, 0) if scalar_bar is not None else (0, len(labels) - 1)
    for i, frame in enumerate(frames):
        for j, label in enumerate(labels):
            plotter.subplot(i, j)
            g = grid.copy()
            g.point_data["u"] = frame[label]
            g.point_data["|u| [m]"] = np.linalg.norm(frame[label], axis=1)
            warped = g.warp_by_vector("u", factor=magnify)
            plotter.add_mesh(outline, color="grey", line_width=1, opacity=0.5)  # undeformed outline
            plotter.add_mesh(warped, scalars="|u| [m]", cmap="viridis", clim=clim,
                             show_scalar_bar=(i, j) == bar_at,
                             scalar_bar_args=scalar_bar or DEFAULT_BAR)
            text = label if titles is None else f"{label}  {titles[i]}"
            plotter.add_text(text, font_size=9 if scalar_bar is None else 8, position="upper_left")
            if title and i == len(frames) - 1 and j == len(labels) - 1:
                plotter.add_text(title, font_size=7, position="lower_right")
            plotter.camera_position = camera or TOP_VIEW
            if parallel_scale is not None:
                plotter.camera.parallel_projection = True
                plotter.camera.parallel_scale = parallel_scale
    path = Path(path)
    plotter.screenshot(str(path))
    plotter.close()
    return path


def animation(path, grid, series: dict, *, magnify: float, fps: int = 10, titles=None) -> Path:
    """GIF of deformed shapes, one panel per label, frames in time (needs imageio)."""
    pv = _pyvista()
    labels = list(series)
    n_frames = len(next(iter(series.values())))
    clim = (0.0, max(np.linalg.norm(u, axis=1).max() for s in series.values() for u in s))
    plotter = pv.Plotter(shape=(1, len(labels)), off_screen=True, window_size=(420 * len(labels), 380))
    path = Path(path)
    plotter.open_gif(str(path), fps=fps)
    meshes = []
    for j, label in enumerate(labels):
        plotter.subplot(0, j)
        g = grid.copy()
        g.point_data["u"] = series[label][0]
        g.point_data["|u| [m]"] = np.linalg.norm(series[label][0], axis=1)
        warped = g.warp_by_vector("u", factor=magnify)
        plotter.add_mesh(grid.extract_surface(algorithm=None).extract_feature_edges(), color="grey",
                         line_width=1, opacity=0.5)  # undeformed outline
        plotter.add_mesh(warped, scalars="|u| [m]", cmap="viridis", clim=clim, show_scalar_bar=False)
        plotter.add_text(label, font_size=9, name=f"title{j}")
        plotter.camera_position = [(0.0, 0.45, 0.12), (0.0, 0.0, 0.12), (1, 0, 0)]
        meshes.append((g, warped))
    for k in range(n_frames):
        for j, label in enumerate(labels):
            g, warped = meshes[j]
            u = series[label][k]
            warped.points[:] = g.points + magnify * u
            warped.point_data["|u| [m]"] = np.linalg.norm(u, axis=1)
            if titles is not None:
                plotter.subplot(0, j)
                plotter.add_text(f"{label}  {titles[k]}", font_size=9, name=f"title{j}")
        plotter.write_frame()
    plotter.close()
    return path


def output_error_energy(path, t: np.ndarray, outputs: dict, energies: dict, *, ylabel: str,
                        title: str = "", vline: float | None = None,
                        t_energy: np.ndarray | None = None) -> Path:
    """Three stacked panels against time: outputs (label -> y; the first is the reference),
    each ROM's error ``|y - y_ref| / max|y_ref|`` (log), and energies (label -> E; first =
    reference) at ``t_energy`` (default ``t``)."""
    plt = _pyplot()
    colors = ["C7", "C0", "C3", "C2", "C1"]
    fig, axes = plt.subplots(3, 1, figsize=(7.5, 7.5), sharex=True)
    ref = np.asarray(next(iter(outputs.values())), dtype=float)
    scale = max(np.abs(ref).max(), 1e-300)
    for i, (label, y) in enumerate(outputs.items()):
        axes[0].plot(t, y, lw=1.0 if i else 1.8, color=colors[i % 5], label=label)
        if i:
            err = np.abs(np.asarray(y) - ref) / scale
            axes[1].semilogy(t, np.where(err > 0, err, np.nan), lw=0.9, color=colors[i % 5], label=label)
    for i, (label, e) in enumerate(energies.items()):
        axes[2].plot(t if t_energy is None else t_energy, e, lw=1.0 if i else 1.8,
                     color=colors[i % 5], label=label)
    axes[0].set_ylabel(ylabel)
    axes[1].set_ylabel("|y - y_FOM| / max|y_FOM|")
    axes[2].set_ylabel("energy [J]")
    axes[2].set_xlabel("t [s]")
    for ax in axes:
        if vline is not None:
            ax.axvline(vline, color="k", ls=":", lw=1)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, **BESIDE)
    axes[0].set_title(_wrap(title + ("  (dotted: end of training)" if vline is not None else "")))
    fig.tight_layout()
    fig.savefig(path, dpi=130, bbox_inches="tight")
    plt.close(fig)
    return Path(path)


#: the parametric demos' methods: label, colour, marker
PARAM_STYLES = {"lopinf": ("parametric L-OpInf", "C0", "o"),
                "intrusive": ("intrusive parametric Galerkin", "C2", "^"),
                "opinf": ("opinf parametric (peer)", "C3", "x"),
                "projection": ("projection floor", "k", ".")}


def error_vs_parameter(path, rows: list[dict], *, index: int = 0, name: str = "mu",
                       train_values=None, title: str = "", select=None, labels=None) -> Path:
    """Test error against one parameter (``index`` of mu), one panel per r, one line per
    method (:data:`PARAM_STYLES`); the training values marked, the training range shaded.
    ``select(row)``: which rows (e.g. those on one line through a 2-D parameter box);
    ``labels``: method -> legend text, replacing :data:`PARAM_STYLES`' labels."""
    plt = _pyplot()
    rows = [r for r in rows if (select is None or select(r))]
    r_values = sorted({r["r"] for r in rows})
    fig, axes = plt.subplots(1, len(r_values), figsize=(4.6 * len(r_values), 3.9), squeeze=False,
                             sharey=True)
    for ax, rv in zip(axes[0], r_values):
        for method, (label, color, marker) in PARAM_STYLES.items():
            sel = sorted((r for r in rows if r["r"] == rv and r["method"] == method),
                         key=lambda r: r["mu"][index])
            if not sel:
                continue
            label = (labels or {}).get(method, label)
            if any("note" in r for r in sel):
                label = "intrusive Galerkin, assembled at each mu"
            x = [r["mu"][index] for r in sel]
            y = [min(r["test_error"], 1e3) for r in sel]
            ls = ":" if method == "projection" else "-"
            ax.semilogy(x, y, ls, color=color, marker=marker, label=label,
                        markerfacecolor="none" if method == "lopinf" else None, markersize=8)
            bad = [(xi, yi) for xi, yi, r in zip(x, y, sel) if not r["stable"]]
            if bad:
                ax.plot(*zip(*bad), "s", color="red", markersize=11, markerfacecolor="none")
        if train_values is not None:
            tv = np.asarray(train_values, dtype=float)
            ax.axvspan(tv.min(), tv.max(), color="C0", alpha=0.06, label="training range")
            for v in tv:
                ax.axvline(v, color="C0", lw=0.6, alpha=0.4)
        ax.set_title(f"r = {rv}")
        ax.set_xlabel(name)
        ax.grid(True, which="both", alpha=0.3)
    axes[0][0].set_ylabel("relative state error (test input)")
    axes[0][-1].legend(fontsize=7)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)
    return Path(path)


def scalar_fields(path, grid, frames: list[dict], *, titles=None, warp: float | None = None,
                  clim=None, title: str | None = None, panel=(330, 300), overlay=None) -> Path:
    """2D scalar fields (membrane displacement) as coloured, optionally warped surfaces: one
    row per frame, one column per label (e.g. ``FOM``, ``L-OpInf``, ``|error|``). A label starting
    with '|' gets its own colour range (an error), the others share one (symmetric).
    ``overlay``: (k, 2) points of an outline drawn on the flat panels (an inclusion)."""
    pv = _pyvista()
    labels = list(frames[0])
    plotter = pv.Plotter(shape=(len(frames), len(labels)), off_screen=True,
                         window_size=(panel[0] * len(labels), panel[1] * len(frames)), border=False)
    top = max(np.abs(v).max() for f in frames for k, v in f.items() if not k.startswith("|"))
    clim = clim or (-top, top)
    etop = max([np.abs(v).max() for f in frames for k, v in f.items() if k.startswith("|")] or [1])
    for i, frame in enumerate(frames):
        for j, label in enumerate(labels):
            plotter.subplot(i, j)
            g = grid.copy()
            err = label.startswith("|")
            g.point_data["u"] = frame[label]
            shown = g.warp_by_scalar("u", factor=warp * 0.25 / top) if warp and not err else g
            plotter.add_mesh(shown, scalars="u", cmap="magma" if err else "RdBu_r",
                             clim=(0, etop) if err else clim, show_scalar_bar=(j == len(labels) - 1 or
                                                                               (err and i == 0)),
                             scalar_bar_args={"title": "error" if err else "q", "vertical": True,
                                              "position_x": 0.8, "height": 0.6, "fmt": "%.1e",
                                              "label_font_size": 10, "title_font_size": 11})
            if overlay is not None and not (warp and not err):  # on the flat panels
                plotter.add_mesh(pv.lines_from_points(np.column_stack(
                    [overlay[:, 0], overlay[:, 1], np.full(len(overlay), 1e-3)])), color="w",
                    line_width=2)
            text = label if titles is None else f"{label}  {titles[i]}"
            plotter.add_text(text, font_size=8, position="upper_left")
            if title and i == len(frames) - 1 and j == 0:
                plotter.add_text(title, font_size=7, position="lower_left")
            plotter.view_isometric() if warp and not err else plotter.view_xy()
    path = Path(path)
    plotter.screenshot(str(path))
    plotter.close()
    return path
