"""NEMO results as napari layers.

:func:`layer_data` turns a results folder into napari *layer data tuples*
``(data, kwargs, layer_type)`` without importing napari (the reader and the tests use it);
:func:`add_nemo_layers` adds them to a viewer; :func:`field_selector` is a small widget to
choose the field a surface is coloured by; :func:`set_surface_field` does the switch.

Coordinates: NEMO vertices and tables are physical ``(x, y, z)``; napari wants
``(z, y, x)`` (the image's axis order). The conversion happens here and only here
(:func:`to_napari`). The image is shown with ``scale = (dz, dy, dx)``, so image, surface,
vectors and points share napari's world coordinates in µm. Several time points of one channel
are stacked on a leading axis (a time slider appears); frame ``i`` of the slider is the i-th
time point found.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np

from nemo.errors import NemoError, NemoWarning
from nemo.layout import discover_frame, find_frames
from nemo.render import (
    FIELD_CMAPS,
    Frame,
    charge_text,
    glyph_spacing,
    load_frame,
    robust_limits,
    subsample_even,
)

#: Default number of director glyphs per layer and frame.
MAX_VECTORS = 2000

#: Defect markers are lifted off the surface by this fraction of their size (diameter):
#: a little more than the radius, so that no part of the marker is hidden by the surface.
LIFT = 0.6


def to_napari(xyz: np.ndarray, t: int | None = None) -> np.ndarray:
    """Physical ``(x, y, z)`` -> napari ``(z, y, x)`` (with a leading ``t`` when given).

    Parameters
    ----------
    xyz : ndarray, shape (M, 3)
    t : int, optional
        Index on the time axis prepended as the first coordinate.

    Returns
    -------
    ndarray, shape (M, 3) or (M, 4)
    """
    zyx = np.asarray(xyz, dtype=np.float64)[:, ::-1]
    if t is None:
        return zyx
    return np.column_stack([np.full(len(zyx), float(t)), zyx])


def _kind(name: str) -> str:
    return name.split(" ", 1)[0]


def _default_field(names: list[str], layer: str | None) -> str | None:
    if not names:
        return None
    if layer is not None:
        for want in (f"intensity ({layer})", f"S ({layer})"):
            if want in names:
                return want
    for prefix in ("intensity", "S ", "H", "thickness"):
        hit = next((n for n in names if n.startswith(prefix)), None)
        if hit:
            return hit
    return names[0]


def _image_layer(frames: list[Frame], c: int, stacked: bool, spacing) -> tuple | None:
    path = frames[0].files.image
    if path is None:
        warnings.warn("no image found for these results (give it with --image / image=): "
                      "showing the surfaces only", NemoWarning, stacklevel=3)
        return None
    from nemo.io import read_info, read_stack

    try:
        info = read_info(path)
    except NemoError as exc:
        warnings.warn(f"image not shown: {exc}", NemoWarning, stacklevel=3)
        return None
    sp = tuple(float(s) for s in (spacing if spacing is not None else info.spacing))
    shape = (info.shape["Z"], info.shape["Y"], info.shape["X"])
    times = [f.t for f in frames]
    bad = [t for t in times if t >= info.shape["T"]] + ([c] if c >= info.shape["C"] else [])
    if bad:
        warnings.warn(f"image not shown: {path} has T={info.shape['T']}, C={info.shape['C']} but the "
                      f"results have t={times}, c={c}", NemoWarning, stacklevel=3)
        return None
    if stacked:
        try:
            import dask
            import dask.array as da

            parts = [da.from_delayed(dask.delayed(lambda tt: read_stack(path, tt, c)[0])(t),
                                     shape=shape, dtype=info.dtype) for t in times]
            data = da.stack(parts)  # lazy: one (Z, Y, X) stack read per time point shown
        except ImportError:  # dask ships with napari; without it read every frame now
            data = np.stack([read_stack(path, t, c)[0] for t in times])
        scale = (1.0, *sp)
    else:
        data = read_stack(path, times[0], c)[0]
        scale = sp
    lo, hi = float(np.min(data[0] if stacked else data)), float(np.max(data[0] if stacked else data))
    return (data, {"name": f"image c{c}", "scale": scale, "colormap": "gray", "blending": "additive",
                   "rendering": "mip", "opacity": 0.5, "contrast_limits": (lo, hi if hi > lo else lo + 1),
                   "metadata": {"nemo": {"kind": "image", "path": str(path), "spacing": sp}}},
            "image")


def _surface_layers(frames: list[Frame], stacked: bool, layer: str | None, shown: str) -> list[tuple]:
    out = []
    keys = []
    for f in frames:
        keys += [k for k in f.surfaces if k not in keys]
    for key in keys:
        verts, faces, names, offset = [], [], [], 0
        for f in frames:
            if key in f.surfaces:
                names += [n for n in f.surfaces[key].fields if n not in names]
        fields = {n: [] for n in names}
        kinds: dict[str, str] = {}
        labels: dict[str, str] = {}
        for i, f in enumerate(frames):
            s = f.surfaces.get(key)
            if s is None:
                continue
            v = np.asarray(s.mesh.vertices)
            verts.append(to_napari(v, i if stacked else None))
            faces.append(np.asarray(s.mesh.faces) + offset)
            offset += len(v)
            for n in names:
                fields[n].append(s.fields.get(n, np.full(len(v), np.nan)))
                if n in s.fields:
                    kinds[n], labels[n] = s.kinds[n], s.label(n)
        fields = {n: np.concatenate(a) for n, a in fields.items()}
        current = _default_field(names, layer)
        values = fields[current] if current else np.ones(offset)
        kind = kinds.get(current, "")
        meta = {"nemo_fields": fields, "nemo_kinds": kinds, "nemo_labels": labels,
                "nemo_field": current,
                "nemo": {"kind": "surface", "surface": key, "times": [f.t for f in frames]}}
        kwargs = {"name": f"surface {key}", "colormap": FIELD_CMAPS.get(kind, "gray"),
                  "contrast_limits": robust_limits(values, kind), "metadata": meta,
                  "visible": key == shown, "shading": "smooth"}
        out.append(((np.concatenate(verts), np.concatenate(faces), _display(values)), kwargs, "surface"))
    return out


def _display(values: np.ndarray) -> np.ndarray:
    """Values napari can colour: NaN (no data) shown at the bottom of the range."""
    v = np.asarray(values, dtype=np.float64)
    if np.isnan(v).any():
        finite = v[np.isfinite(v)]
        v = np.where(np.isfinite(v), v, finite.min() if finite.size else 0.0)
    return v


def _vector_layers(frames: list[Frame], stacked: bool, max_vectors: int, layer: str | None) -> list[tuple]:
    out = []
    names = []
    for f in frames:
        names += [n for n in f.layers if n not in names]
    for name in names:
        for table, feature, title, colour in (("directors", "coherency", "directors", "magenta"),
                                              ("order", "S", "averaged directors", None)):
            data, feats, length = [], [], None
            for i, f in enumerate(frames):
                lay = f.layers.get(name)
                df = getattr(lay, table, None) if lay is not None else None
                if df is None or not len(df):
                    continue
                mesh = f.surfaces[lay.surface].mesh
                spacing = glyph_spacing(mesh, max_vectors)
                length = 0.8 * spacing
                df = df[np.isfinite(df[["x", "y", "z", "nx", "ny", "nz"]].to_numpy(np.float64)).all(axis=1)]
                pos = df[["x", "y", "z"]].to_numpy(np.float64)
                keep = subsample_even(pos, spacing)
                pos = pos[keep]
                n = df[["nx", "ny", "nz"]].to_numpy(np.float64)[keep]
                n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
                start = to_napari(pos - 0.5 * length * n, i if stacked else None)
                proj = to_napari(length * n, 0 if stacked else None)
                data.append(np.stack([start, proj], axis=1))
                feats.append(df[feature].to_numpy(np.float64)[keep])
            if not data:
                continue
            vals = np.concatenate(feats)
            kwargs = {"name": f"{title} ({name})", "features": {feature: vals}, "edge_width":
                      max(0.08 * length, 1e-3), "vector_style": "line", "length": 1.0,
                      "visible": name == layer,
                      "metadata": {"nemo": {"kind": table, "layer": name, "glyph_length": length}}}
            if colour is None:
                kwargs.update(edge_color=feature, edge_colormap="viridis", edge_contrast_limits=(0.0, 1.0))
            else:
                kwargs.update(edge_color=colour, visible=False)
            out.append((np.concatenate(data), kwargs, "vectors"))
    return out


def lift(mesh, xyz: np.ndarray, height: float) -> np.ndarray:
    """Points moved ``height`` outward, along the surface normal under them.

    napari draws a 3D point as a disc facing the camera, centred on the point: a defect marker
    placed on the surface sinks half into it (and its label with it). Lifted by at least the
    marker radius, the whole disc stays above the tangent plane from any viewing angle.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The surface (outward normals, as NEMO's meshes).
    xyz : ndarray, shape (M, 3)
        Points on the surface, physical ``(x, y, z)``.
    height : float
        Distance to move them, in the mesh's unit.

    Returns
    -------
    ndarray, shape (M, 3)
        The moved points; the normal is the mean vertex normal within ``height`` of the point
        (the nearest vertex's when none is that close), so mesh roughness does not tilt it.
    """
    from scipy.spatial import cKDTree

    from nemo.mesh import vertex_normals

    xyz = np.asarray(xyz, dtype=np.float64)
    if not len(xyz):
        return xyz
    normals = np.nan_to_num(vertex_normals(mesh))
    tree = cKDTree(np.asarray(mesh.vertices, dtype=np.float64))
    _, nearest = tree.query(xyz)
    out = xyz.copy()
    for k, (p, near) in enumerate(zip(xyz, tree.query_ball_point(xyz, height), strict=True)):
        n = normals[near].sum(axis=0) if near else normals[nearest[k]]
        norm = np.linalg.norm(n)
        if norm > 0:
            out[k] = p + height * n / norm
    return out


def _points_layers(frames: list[Frame], stacked: bool, layer: str | None) -> list[tuple]:
    out = []
    names = []
    for f in frames:
        names += [n for n in f.layers if n not in names]
    for name in names:
        pts, where, charge, label, size = [], [], [], [], None
        for i, f in enumerate(frames):
            lay = f.layers.get(name)
            if lay is None or lay.defects is None or not len(lay.defects):
                continue
            d = lay.defects[np.isfinite(lay.defects[["x", "y", "z"]].to_numpy(np.float64)).all(axis=1)]
            if not len(d):
                continue
            mesh = f.surfaces[lay.surface].mesh
            size = 0.05 * float(np.linalg.norm(np.ptp(np.asarray(mesh.vertices), axis=0)))
            xyz = d[["x", "y", "z"]].to_numpy(np.float64)
            where.append(xyz)
            pts.append(to_napari(lift(mesh, xyz, LIFT * size), i if stacked else None))
            q = d["charge"].to_numpy(np.float64)
            charge.append(q)
            rounded = d["charge_rounded"].to_numpy(np.float64) if "charge_rounded" in d else q
            label += [charge_text(x) for x in rounded]
        if not pts:
            continue
        kwargs = {"name": f"defects ({name})",
                  "features": {"charge": np.concatenate(charge), "label": np.asarray(label, dtype=object),
                               **dict(zip("xyz", np.concatenate(where).T, strict=True))},  # on the surface
                  "face_color": "charge", "face_colormap": "bwr", "face_contrast_limits": (-1.0, 1.0),
                  "border_color": "black", "size": size, "visible": name == layer,
                  # in 3D napari centres the text on its point: dark text on the light bwr colours
                  "text": {"string": "{label}", "size": 12, "color": "black", "anchor": "center"},
                  "metadata": {"nemo": {"kind": "defects", "layer": name, "lift": LIFT * size}}}
        out.append((np.concatenate(pts), kwargs, "points"))
    return out


def layer_data(
    results: str | os.PathLike,
    dataset: str | None = None,
    t: int | None = None,
    c: int | None = None,
    layer: str | None = None,
    image: str | os.PathLike | None = None,
    spacing: tuple[float, float, float] | None = None,
    max_vectors: int = MAX_VECTORS,
) -> list[tuple]:
    """napari layer data tuples for a NEMO results folder (napari is not imported).

    Parameters
    ----------
    results : path
        Frame folder, dataset folder (``t*/c*/``) or results root (``*/t*/c*/``).
    dataset : str, optional
        Dataset to show from a results root (default the first).
    t : int, optional
        One time point; default all time points of the channel, stacked (time slider).
    c : int, optional
        Channel (default the first with results).
    layer : str, optional
        Nematic layer to show first (its surface coloured by its intensity, its directors
        and defects visible); default the first layer by name (the others are added hidden).
    image : path, optional
        The hyperstack, when it is not found from the tables' provenance.
    spacing : (dz, dy, dx), optional
        Override the image calibration (as ``--spacing`` did for the analysis).
    max_vectors : int
        About how many director glyphs per layer and frame (thinned evenly on the surface).

    Returns
    -------
    list of (data, kwargs, layer_type)
        Image (``scale = spacing``), one surface per mesh (fields in ``metadata``),
        director vectors, averaged director vectors, defect points -- all in napari
        ``(z, y, x)`` (or ``(t, z, y, x)``) world coordinates in µm. The defect markers are
        lifted off the surface by :data:`LIFT` times their size along the normal (see
        :func:`lift`; the distance in ``metadata['nemo']['lift']``); their features ``x, y, z``
        keep the defect positions on the surface.

    Raises
    ------
    NemoError
        No results, or a ``t``/``c``/``layer`` that is not there.
    """
    tree = find_frames(results, dataset)
    channels = tree.channels
    c = channels[0] if c is None else int(c)
    if c not in channels:
        raise NemoError(f"channel c={c} has no results in {tree.root} (channels: {channels})")
    times = tree.times(c)
    if t is not None:
        if int(t) not in times:
            raise NemoError(f"time point t={t} has no results in {tree.root} for c={c} (found: {times})")
        times = [int(t)]
    frames = [load_frame(discover_frame(tree.frames[(tt, c)], image=image)) for tt in times]
    names = sorted({n for f in frames for n in f.layers})
    if layer is not None and layer not in names:
        raise NemoError(f"layer {layer!r} not found in {tree.root} (layers: {', '.join(names) or 'none'})")
    first = layer if layer is not None else (names[0] if names else None)
    shown = next((f.layers[first].surface for f in frames if first in f.layers),
                 next(iter(frames[0].surfaces)))
    stacked = len(frames) > 1
    out: list[tuple] = []
    img = _image_layer(frames, c, stacked, spacing)
    if img is not None:
        out.append(img)
    out += _surface_layers(frames, stacked, first, shown)
    out += _vector_layers(frames, stacked, max_vectors, first)
    out += _points_layers(frames, stacked, first)
    unit = "um" if next(iter(frames[0].surfaces.values())).unit in ("um", "µm", "micron") else "pixel"
    units = (("pixel",) if stacked else ()) + (unit,) * 3  # the scale bar shows µm
    for _, kwargs, _ in out:
        kwargs.setdefault("units", units)
    return out


def set_surface_field(surface_layer, name: str) -> None:
    """Colour a NEMO surface layer by one of its fields (``surface_layer.metadata['nemo_fields']``)."""
    fields = surface_layer.metadata.get("nemo_fields", {})
    if name not in fields:
        raise NemoError(f"surface {surface_layer.name!r} has no field {name!r} (fields: {', '.join(fields)})")
    kind = surface_layer.metadata["nemo_kinds"].get(name, _kind(name))
    values = fields[name]
    vertices, faces = surface_layer.data[0], surface_layer.data[1]
    surface_layer.data = (vertices, faces, _display(values))
    surface_layer.colormap = FIELD_CMAPS.get(kind, "viridis")
    surface_layer.contrast_limits = robust_limits(values, kind)
    surface_layer.metadata["nemo_field"] = name


def _scale_bar(viewer):
    """The viewer's scale bar overlay (``viewer.canvas.overlays`` since napari 0.9)."""
    canvas = getattr(viewer, "canvas", None)
    overlays = getattr(canvas, "overlays", None)
    return overlays.scale_bar if overlays is not None and hasattr(overlays, "scale_bar") else viewer.scale_bar


def add_nemo_layers(viewer, results: str | os.PathLike, **kwargs) -> dict:
    """Add the layers of a NEMO results folder to an existing napari viewer.

    Parameters
    ----------
    viewer : napari.Viewer
    results : path
    **kwargs
        As :func:`layer_data` (``dataset``, ``t``, ``c``, ``layer``, ``image``, ``spacing``,
        ``max_vectors``).

    Returns
    -------
    dict of str to napari.layers.Layer
        The added layers by name. The viewer switches to 3D with axis labels ``(t,) z, y, x``.
    """
    from napari.layers import Layer as NapariLayer

    added = {}
    for data, meta, kind in layer_data(results, **kwargs):
        lay = viewer.add_layer(NapariLayer.create(data, meta, kind))
        added[lay.name] = lay
    viewer.dims.ndisplay = 3
    ndim = viewer.dims.ndim
    labels = ("t", "z", "y", "x")[-ndim:] if ndim <= 4 else None
    if labels:
        viewer.dims.axis_labels = labels
    _scale_bar(viewer).visible = True
    return added


def field_selector(napari_viewer):
    """A dock widget choosing the field a NEMO surface is coloured by.

    Two combo boxes (surface layer, field) and a line with the field's colour-bar label
    (units) and colour range. Also the npe2 widget contribution ``NEMO field selector``.
    """
    from magicgui.widgets import ComboBox, Container, Label

    def surfaces(*_):
        return [lay.name for lay in napari_viewer.layers if "nemo_fields" in lay.metadata]

    def current_layer():
        name = surf.value if surf is not None else None
        return napari_viewer.layers[name] if name in napari_viewer.layers else None

    def field_names(*_):
        lay = current_layer()
        return list(lay.metadata["nemo_fields"]) if lay is not None else []

    surf = None
    surf = ComboBox(label="surface", choices=surfaces)
    # callable choices: napari calls reset_choices() on docked magicgui widgets
    fld = ComboBox(label="field", choices=field_names)
    info = Label(value="")

    def refresh_fields(*_):
        lay = current_layer()
        fld.reset_choices()
        names = list(fld.choices)
        if lay is not None and lay.metadata.get("nemo_field") in names:
            fld.value = lay.metadata["nemo_field"]
        show_info()

    def show_info():
        lay = current_layer()
        if lay is None or not fld.value:
            info.value = ""
            return
        lo, hi = lay.contrast_limits
        info.value = f"{lay.metadata['nemo_labels'].get(fld.value, fld.value)}: {lo:.3g} … {hi:.3g}"

    def apply(*_):
        lay = current_layer()
        if lay is not None and fld.value and fld.value != lay.metadata.get("nemo_field"):
            set_surface_field(lay, fld.value)
        show_info()

    surf.changed.connect(refresh_fields)
    fld.changed.connect(apply)
    napari_viewer.layers.events.inserted.connect(lambda *_: (surf.reset_choices(), refresh_fields()))
    napari_viewer.layers.events.removed.connect(lambda *_: (surf.reset_choices(), refresh_fields()))
    box = Container(widgets=[surf, fld, info], labels=True)
    surf.reset_choices()
    refresh_fields()
    return box


def open_viewer(results: str | os.PathLike, show: bool = True, **kwargs):
    """A new napari viewer with the NEMO layers and the field selector docked."""
    import napari

    viewer = napari.Viewer(show=show, title=f"NEMO: {Path(results)}")
    try:
        viewer.window.resize(1400, 900)  # room for the canvas beside the dock widgets
    except AttributeError:  # older napari windows have no resize
        pass
    add_nemo_layers(viewer, results, **kwargs)
    viewer.window.add_dock_widget(field_selector(viewer), name="NEMO field", area="right")
    return viewer
