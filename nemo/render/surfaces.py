"""Pyvista surface renders: a surface coloured by a field, seen from two opposite sides.

:func:`surface_plotter` builds an off-screen two-view plotter (front and back) with an
optional colour field, nematic glyphs (headless segments), defect markers labelled by
charge and, on an open surface (cut by the image border), its rim as a magenta line;
:func:`render_surface` writes it to a PNG. Rendering is off-screen through EGL/OSMesa,
so no X server is needed. pyvista (and VTK) is imported only when a render is made, so that
importing :mod:`nemo.render` stays light.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from nemo import atomic
from nemo.render.charts import glyph_spacing, surface_centre
from nemo.render.style import charge_text, field_label


def _pyvista():
    if not os.environ.get("DISPLAY") and "VTK_DEFAULT_OPENGL_WINDOW" not in os.environ:
        os.environ["VTK_DEFAULT_OPENGL_WINDOW"] = "vtkEGLRenderWindow"  # no X: skip the X probe
    import pyvista as pv

    pv.OFF_SCREEN = True
    return pv


def _polydata(mesh):
    pv = _pyvista()
    return pv.PolyData.from_regular_faces(np.asarray(mesh.vertices, dtype=np.float64),
                                          np.asarray(mesh.faces, dtype=np.int64))


#: Colour of the open rim of a surface cut by the image border (distinct from the colour maps,
#: the black glyphs and the blue-white-red defect markers).
RIM_COLOUR = "magenta"


def _rim_lines(mesh):
    """The open rim (boundary edges) of ``mesh`` as pyvista lines, or None for a closed surface."""
    from nemo.geometry import boundary_edges

    edges = boundary_edges(np.asarray(mesh.faces))
    if not len(edges):
        return None
    pv = _pyvista()
    lines = np.column_stack([np.full(len(edges), 2), edges]).ravel()
    return pv.PolyData(np.asarray(mesh.vertices, dtype=np.float64), lines=lines)


def surface_plotter(
    mesh,
    scalars: np.ndarray | None = None,
    label: str = "",
    cmap: str = "viridis",
    clim: tuple[float, float] | None = None,
    segments: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    segment_label: str = "S",
    segment_cmap: str | None = None,
    segment_clim: tuple[float, float] = (0.0, 1.0),
    segment_colour: str = "black",
    defects: tuple[np.ndarray, np.ndarray] | None = None,
    title: str = "",
    window_size: tuple[int, int] = (1400, 700),
    view: np.ndarray | None = None,
    rim_colour: str | None = RIM_COLOUR,
):
    """A two-view off-screen pyvista plotter of a surface (front and back).

    An open surface (cut by the image border, ``mesh.border: open``) has its rim (the edges of
    one face) drawn as a thick line in ``rim_colour``: where the surface ends is visible, and
    not mistaken for a hole or a shading artefact.

    Parameters
    ----------
    mesh : trimesh.Trimesh
    scalars : ndarray, shape (N,), optional
        Per-vertex field; NaN drawn grey.
    label : str
        Colour-bar title (with units).
    segments : (centres (M, 3), directions (M, 3), values (M,)), optional
        Nematic glyphs: headless segments of length 0.8 × glyph spacing, in
        ``segment_colour``, or coloured by values when ``segment_cmap`` is given.
    defects : (positions (D, 3), charges (D,)), optional
        Spheres coloured by charge (bwr, [−1, 1]) labelled with the rounded charge.
    view : ndarray, shape (3,), optional
        Direction from the centre to the first camera (default (1, 0.6, 0.5)).
    rim_colour : str or None
        Colour of the open rim (default :data:`RIM_COLOUR`); None draws no rim.

    Returns
    -------
    pyvista.Plotter
        Not yet rendered: call ``screenshot``; ``plotter.scalar_bars`` holds the colour bars.
    """
    pv = _pyvista()
    poly = _polydata(mesh)
    centre = surface_centre(mesh)
    size = float(np.linalg.norm(np.ptp(np.asarray(mesh.vertices), axis=0)))
    spacing = glyph_spacing(mesh)
    view = np.asarray(view if view is not None else (1.0, 0.6, 0.5), dtype=np.float64)
    view /= np.linalg.norm(view)
    p = pv.Plotter(off_screen=True, shape=(1, 2), window_size=list(window_size), border=False)
    from nemo.mesh import vertex_normals

    normals = np.nan_to_num(vertex_normals(mesh))
    rim_lines = _rim_lines(mesh) if rim_colour else None
    for col, sign in enumerate((1.0, -1.0)):
        p.subplot(0, col)
        p.set_background("white")
        bar = {"title": label, "color": "black", "vertical": False, "position_x": 0.2,
               "position_y": 0.02, "width": 0.6, "height": 0.08, "title_font_size": 22,
               "label_font_size": 18, "n_labels": 5, "fmt": "%.3g"}
        show_bar = col == 1
        if scalars is not None:
            poly.point_data["field"] = np.asarray(scalars, dtype=np.float64)
            p.add_mesh(poly.copy(), scalars="field", cmap=cmap, clim=clim, nan_color="lightgrey",
                       smooth_shading=True, show_scalar_bar=show_bar and bool(label),
                       scalar_bar_args=bar if label else None)
        else:
            p.add_mesh(poly.copy(), color="lightgrey", smooth_shading=True)
        if rim_lines is not None:
            p.add_mesh(rim_lines, color=rim_colour, line_width=5, render_lines_as_tubes=True)
        if segments is not None and len(segments[0]):
            pos, vec, val = (np.asarray(a, dtype=np.float64) for a in segments)
            _, vidx = cKDTree(np.asarray(mesh.vertices)).query(pos)
            pos = pos + 0.004 * size * normals[vidx]  # lift above the surface so it is not hidden
            half = 0.4 * spacing * vec / np.maximum(np.linalg.norm(vec, axis=1, keepdims=True), 1e-12)
            pts = np.concatenate([pos - half, pos + half])
            m = len(pos)
            lines = np.column_stack([np.full(m, 2), np.arange(m), np.arange(m) + m]).ravel()
            seg = pv.PolyData(pts, lines=lines)
            if segment_cmap is None:  # one colour: readable on any surface colouring
                p.add_mesh(seg, color=segment_colour, line_width=2.5, render_lines_as_tubes=True)
            else:
                seg.point_data["glyph"] = np.concatenate([val, val])
                p.add_mesh(seg, scalars="glyph", cmap=segment_cmap, clim=segment_clim, line_width=3,
                           render_lines_as_tubes=True, show_scalar_bar=show_bar,
                           scalar_bar_args=dict(bar, title=segment_label, position_y=0.88))
        if defects is not None and len(defects[0]):
            pos, q = (np.asarray(a, dtype=np.float64) for a in defects)
            cloud = pv.PolyData(pos)
            cloud.point_data["charge"] = q
            glyphs = cloud.glyph(geom=pv.Sphere(radius=0.025 * size), scale=False, orient=False)
            p.add_mesh(glyphs, scalars="charge", cmap="bwr", clim=(-1, 1), show_scalar_bar=show_bar,
                       scalar_bar_args=dict(bar, title=field_label("charge"), position_y=0.88))
            p.add_point_labels(pos + 0.05 * size * (pos - centre) / np.maximum(
                np.linalg.norm(pos - centre, axis=1, keepdims=True), 1e-12),
                [charge_text(x) for x in q], font_size=24, text_color="black", shape_opacity=0.6,
                show_points=False, always_visible=False)
        p.camera.position = tuple(centre + sign * view * 3.0 * size)
        p.camera.focal_point = tuple(centre)
        p.camera.up = (0.0, 0.0, 1.0)
        p.reset_camera()  # keeps the direction, fits the surface
        p.camera.zoom(1.25)
        p.add_text(f"{title}  ({'front' if col == 0 else 'back'})" if title else
                   ("front" if col == 0 else "back"), font_size=12, color="black")
    return p


def render_surface(out: str | os.PathLike, mesh, **kwargs) -> Path:
    """Render :func:`surface_plotter` to a PNG (atomically) and return its path."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    p = surface_plotter(mesh, **kwargs)
    try:
        with atomic.atomic_path(out, keep_suffix=True) as tmp:
            p.screenshot(str(tmp))
    finally:
        p.close()
    return out
