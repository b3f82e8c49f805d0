"""Matplotlib figures of one frame: distributions, spherical maps, morphology, alignment.

* :func:`distributions_figure` -- densities of S and of the defect charges (paper Fig. 2C);
* :func:`spherical_figure` -- intensity, averaged directors and defects in spherical
  coordinates around the surface centroid (paper Fig. 2D);
* :func:`morphology_figure` -- spherical maps of H, K and thickness;
* :func:`alignment_figure` -- inter-layer alignment map and histogram.

Also the shared plumbing of every matplotlib figure (:func:`save_figure`, the (φ, θ) map axes),
used by :mod:`nemo.render.timeseries`. Figures are object-oriented on an Agg canvas (no pyplot
state); matplotlib is imported inside the functions, so importing :mod:`nemo.render` does
not load it.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pandas as pd

from nemo import atomic, objects
from nemo.render.charts import (
    chart_directions,
    glyph_spacing,
    spherical_angles,
    spherical_grid,
    subsample_even,
    surface_centre,
)
from nemo.render.data import Frame, Surface, _fill_nearest, _scatter
from nemo.render.style import (
    FIELD_CMAPS,
    charge_text,
    field_label,
    robust_limits,
    unit_text,
)
from nemo.summary import c_avg_means


def _figure(ncols: int = 1, width: float = 6.0, height: float = 4.2):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width * ncols, height), layout="constrained")
    axes = fig.subplots(1, ncols, squeeze=False)[0]
    return fig, axes


def save_figure(fig, out: str | os.PathLike, dpi: int = 130) -> Path:
    """Save a matplotlib figure to PNG atomically (Agg canvas)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    FigureCanvasAgg(fig)
    with atomic.atomic_path(out, keep_suffix=True) as tmp:
        fig.savefig(tmp, dpi=dpi, facecolor="white")
    return out


def distributions_figure(S: np.ndarray, charges: np.ndarray, title: str = ""):
    """Probability densities of S (left) and defect charges (right) -- paper Fig. 2C.

    Parameters
    ----------
    S : ndarray, shape (N,)
        Order parameter at the surface vertices (NaN ignored).
    charges : ndarray, shape (D,)
        Raw (unrounded) defect charges.
    """
    fig, (ax_s, ax_q) = _figure(2, 4.5, 3.6)
    S = np.asarray(S, dtype=np.float64)
    S = S[np.isfinite(S)]
    ax_s.hist(S, bins=np.linspace(0, 1, 41), density=True, color="tab:green", alpha=0.85)
    ax_s.set_xlabel(field_label("S"))
    ax_s.set_ylabel("probability density")
    ax_s.set_xlim(0, 1)
    if S.size:
        ax_s.axvline(float(np.mean(S)), color="k", ls=":", lw=1)
        ax_s.set_title(f"S  (mean {np.mean(S):.2f}, n = {S.size})", fontsize=10)
    q = np.asarray(charges, dtype=np.float64)
    q = q[np.isfinite(q)]
    lim = max(1.25, float(np.abs(q).max()) + 0.25) if q.size else 1.25
    ax_q.hist(q, bins=np.arange(-lim - 0.025, lim + 0.03, 0.05), density=True, color="tab:red", alpha=0.85)
    for x in (-0.5, 0.5):
        ax_q.axvline(x, color="k", ls="--", lw=0.8)
    ax_q.set_xlim(-lim, lim)
    ax_q.set_xlabel(field_label("charge"))
    ax_q.set_ylabel("probability density")
    ax_q.set_title(f"charge  (n = {q.size}, Σ = {q.sum():+.2f})" if q.size else "no defects", fontsize=10)
    if title:
        fig.suptitle(title)
    return fig


def _map_axes(ax) -> None:
    ax.set_xlim(-180, 180)
    ax.set_ylim(180, 0)
    ax.set_xticks(np.arange(-180, 181, 60))
    ax.set_yticks(np.arange(0, 181, 30))
    ax.set_xlabel("azimuth φ [°]")
    ax.set_ylabel("polar angle θ [°]")
    ax.set_aspect("equal")


def _map_image(ax, vertices, values, centre, cmap, clim, label, fig, n_polar=180):
    grid = spherical_grid(vertices, values, centre, n_polar=n_polar)
    cm = _cmap_with_nan(cmap)
    im = ax.imshow(grid, extent=(-180, 180, 180, 0), cmap=cm, vmin=clim[0], vmax=clim[1],
                   interpolation="nearest", aspect="equal")
    cb = fig.colorbar(im, ax=ax, shrink=0.8, pad=0.01)
    cb.set_label(label)
    _map_axes(ax)
    return im, cb


def _cmap_with_nan(name: str):
    import matplotlib

    return matplotlib.colormaps[name].with_extremes(bad="lightgrey")  # a copy (set_bad is being deprecated)


def _chart_segments(ax, pos, vec, values, centre, fig, length_deg: float, label="S",
                    cmap="viridis", clim=(0.0, 1.0)):
    az, pol = spherical_angles(pos, centre)
    uv = chart_directions(pos, vec, centre)
    q = ax.quiver(az, pol, uv[:, 0], uv[:, 1], values, cmap=cmap, clim=clim, angles="xy",
                  scale_units="xy", scale=1.0 / length_deg, pivot="middle", headwidth=0,
                  headlength=0, headaxislength=0, width=0.0025)
    q.set_gid("directors")
    cb = fig.colorbar(q, ax=ax, shrink=0.8, pad=0.01)
    cb.set_label(field_label(label))
    return q, cb


def _chart_defects(ax, pos, charges, centre, fig, colorbar=True):
    az, pol = spherical_angles(pos, centre)
    sc = ax.scatter(az, pol, c=charges, cmap="bwr", vmin=-1, vmax=1, s=90, edgecolors="k",
                    linewidths=1.2, zorder=5)
    sc.set_gid("defects")
    for a, p_, q in zip(az, pol, charges):
        ax.annotate(charge_text(q), (a, p_), xytext=(6, -6), textcoords="offset points",
                    fontsize=9, fontweight="bold", zorder=6,
                    bbox={"boxstyle": "round,pad=0.15", "fc": "white", "alpha": 0.7, "lw": 0})
    if colorbar:
        cb = fig.colorbar(sc, ax=ax, shrink=0.8, pad=0.01)
        cb.set_label(field_label("charge"))
    return sc


#: Largest number of objects drawn, one panel each, in a frame's spherical map (the largest first).
MAX_MAP_OBJECTS = 6


def spherical_figure(frame: Frame, layer: str, n_polar: int = 180, max_glyphs: int = 900):
    """Intensity + averaged directors + defects in spherical coordinates -- paper Fig. 2D.

    The chart is centred on the area-weighted centroid of the layer's surface. Directors are
    thinned evenly on the surface (about ``max_glyphs``) and coloured by S; defects are circles
    coloured by charge with the rounded charge as text. A surface of several objects
    (``mesh.keep: all``) gets one panel per object, each about its own centroid (at most
    :data:`MAX_MAP_OBJECTS`, the largest first): about one centroid of them all, their maps
    overlaid each other.
    """
    lay = frame.layers[layer]
    surf = frame.surfaces[lay.surface]
    pieces = _map_parts(surf.mesh)
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10.5, 5.0 * len(pieces)), layout="constrained")
    for ax, part in zip(fig.subplots(len(pieces), 1, squeeze=False)[:, 0], pieces):
        _spherical_panel(ax, fig, lay, part, surf.unit, len(pieces) > 1, n_polar, max_glyphs)
    return fig


def _map_parts(mesh) -> list:
    """The objects a frame's maps draw, largest first (:func:`nemo.objects.parts`; the whole mesh
    as one part when it has no object labels), at most :data:`MAX_MAP_OBJECTS`."""
    return (objects.parts(mesh) or [objects.Part(0, mesh, np.arange(len(mesh.vertices)))])[:MAX_MAP_OBJECTS]


def _spherical_panel(ax, fig, lay, part, unit: str, several: bool, n_polar: int, max_glyphs: int) -> None:
    """One object's map in :func:`spherical_figure` (``part``: a :class:`nemo.objects.Part`)."""
    verts = np.asarray(part.mesh.vertices)
    centre = surface_centre(part.mesh)
    if lay.intensity is not None:
        vals = _fill_nearest(np.asarray(lay.intensity)[part.vertices], verts)
        _map_image(ax, verts, vals, centre, "gray", robust_limits(vals), field_label("intensity"),
                   fig, n_polar)
    else:
        _map_axes(ax)
    od = _of_part(lay.order, part, several)
    if od is not None and len(od):
        keep = subsample_even(od[["x", "y", "z"]].to_numpy(np.float64), glyph_spacing(part.mesh, max_glyphs))
        od = od.iloc[keep]
        _chart_segments(ax, od[["x", "y", "z"]].to_numpy(float), od[["nx", "ny", "nz"]].to_numpy(float),
                        od["S"].to_numpy(float), centre, fig, length_deg=0.8 * 180 / np.sqrt(max_glyphs / 2))
    dd = _of_part(lay.defects, part, several)
    if dd is not None and len(dd):
        _chart_defects(ax, dd[["x", "y", "z"]].to_numpy(float), dd["charge"].to_numpy(float), centre, fig)
    what = f"layer {lay.name}" + (f", object {part.label}" if several else "")
    ax.set_title(f"{what}: spherical coordinates around the centroid "
                 f"({centre[0]:.1f}, {centre[1]:.1f}, {centre[2]:.1f}) {unit_text(unit)}", fontsize=10)


def _of_part(df: pd.DataFrame | None, part, several: bool) -> pd.DataFrame | None:
    """The rows of a vertex-keyed table (order) or an object-keyed one (defects) on ``part``."""
    if df is None or not several:
        return df
    if "object" in df.columns:
        return df[df["object"].to_numpy() == part.label]
    if "vertex" in df.columns:
        return df[np.isin(df["vertex"].to_numpy(), part.vertices)]
    return df


def morphology_figure(surf: Surface, n_polar: int = 120):
    """Spherical maps of H, K and thickness (those present) on one surface, or None; a row per
    object about its own centroid on a surface of several (at most :data:`MAX_MAP_OBJECTS`)."""
    names = [n for n in ("H", "K", "thickness") if n in surf.fields]
    if not names:
        return None
    pieces = _map_parts(surf.mesh)
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.2 * len(names), 3.6 * len(pieces)), layout="constrained")
    grid = fig.subplots(len(pieces), len(names), squeeze=False)
    for row, part in zip(grid, pieces):
        verts = np.asarray(part.mesh.vertices)
        centre = surface_centre(part.mesh)
        for ax, name in zip(row, names):
            vals = np.asarray(surf.fields[name])[part.vertices]
            _map_image(ax, verts, vals, centre, FIELD_CMAPS[name], robust_limits(vals, name),
                       surf.label(name), fig, n_polar)
            ax.set_title(f"{name} ({surf.key} surface" + (f", object {part.label})" if len(pieces) > 1 else ")"),
                         fontsize=10)
    return fig


def alignment_figure(frame: Frame, pair: tuple[str, str], n_polar: int = 120):
    """Alignment c between two layers: spherical map (left) and histogram (right)."""
    df = frame.align[pair]
    surf = frame.surfaces[frame.align_surface[pair]]
    verts = np.asarray(surf.mesh.vertices)
    centre = surface_centre(surf.mesh)
    c_vertex = _fill_nearest(_scatter(df, "c", len(verts)), verts)
    fig, (ax_m, ax_h) = _figure(2, 6.0, 3.6)
    fig.set_size_inches(13, 3.8)
    _map_image(ax_m, verts, c_vertex, centre, "coolwarm", (-1, 1), field_label("c"), fig, n_polar)
    ax_m.set_title(f"alignment {pair[0]} vs {pair[1]}", fontsize=10)
    c = df["c"].to_numpy(float)
    c = c[np.isfinite(c)]
    bins = np.linspace(-1, 1, 41)
    ax_h.hist(c, bins=bins, density=True, color="tab:purple", alpha=0.85, label="c per director")
    if c.size:
        ax_h.axvline(float(c.mean()), color="k", ls="--", lw=1)
    averaged = c_avg_means(df)["c_avg_mean"]
    if np.isfinite(averaged):  # with the order tables: c between the averaged directors, S_A·S_B-weighted
        ok = np.isfinite(df["c_avg"].to_numpy(float)) & (df["weight"].to_numpy(float) > 0)
        ax_h.hist(df["c_avg"].to_numpy(float)[ok], bins=bins, weights=df["weight"].to_numpy(float)[ok],
                  density=True, histtype="step", color="tab:orange", lw=1.5, label="c_avg (S-weighted)")
        ax_h.axvline(averaged, color="tab:orange", ls="--", lw=1)
        ax_h.legend(fontsize=8, loc="upper center")
    ax_h.set_xlim(-1, 1)
    ax_h.set_xlabel(field_label("c"))
    ax_h.set_ylabel("probability density")
    title = f"mean c = {c.mean():+.2f} (n = {c.size})" if c.size else "no values"
    ax_h.set_title(title + (f", c_avg = {averaged:+.2f}" if np.isfinite(averaged) else ""), fontsize=10)
    return fig
