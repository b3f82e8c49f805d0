"""Figures of NEMO results: pyvista surface renders and matplotlib figures (``nemo render``).

One module per responsibility, in the order data flows through them:

* :mod:`nemo.layout` (not in this package) -- **discovery**: :func:`discover_frame`
  classifies the files of one frame folder by name, :func:`find_frames` the frames of a
  results tree ``results/{dataset}/t{t}/c{c}/``;
* :mod:`nemo.render.data` -- the **frame model**: :func:`load_frame` reads a frame's meshes
  and tables into a :class:`Frame` of :class:`Surface` (per-vertex fields) and :class:`Layer`
  (order, directors, defects). Missing tables mean "not shown", never an error;
* :mod:`nemo.render.style` -- field labels with units, colour maps, colour limits
  (:func:`robust_limits`), :data:`CAPTIONS` of every figure kind;
* :mod:`nemo.render.charts` -- spherical-chart geometry around the surface centroid;
* :mod:`nemo.render.surfaces` -- pyvista off-screen renders (:func:`render_surface`; EGL or
  OSMesa, no X server needed);
* :mod:`nemo.render.figures` -- matplotlib figures of one frame (distributions, spherical
  map, morphology, alignment; paper Fig. 2C/D);
* :mod:`nemo.render.timeseries` -- matplotlib figures of a time-lapse (defect tracks, defect
  map, per-frame summary with quality control);
* :mod:`nemo.render.manifest` -- what ``nemo render`` writes: :func:`planned_figures`,
  :func:`render_frame`, :func:`render_summary` and ``figures.json`` (file -> kind, caption,
  sources, parameters) for the workflow report.

Every public name is re-exported here, so ``from nemo.render import render_frame`` works.
pyvista and matplotlib are imported only inside the functions that draw. All positions are
physical ``x, y, z`` (µm); nothing here converts to napari's ``(z, y, x)``.
"""

from __future__ import annotations

from nemo.layout import (
    DEFAULT_LAYER,
    FrameFiles,
    ResultsTree,
    discover_frame,
    find_frames,
)
from nemo.render.charts import (
    chart_directions,
    glyph_spacing,
    spherical_angles,
    spherical_grid,
    subsample_even,
    surface_centre,
)
from nemo.render.data import Frame, Layer, Surface, load_frame
from nemo.render.figures import (
    alignment_figure,
    distributions_figure,
    morphology_figure,
    save_figure,
    spherical_figure,
)
from nemo.render.manifest import Figure, planned_figures, render_frame, render_summary
from nemo.render.style import (
    CAPTIONS,
    FIELD_CMAPS,
    FIELD_LABELS,
    LAYER_COLOURS,
    SIGNED_KINDS,
    SURFACE_COLOURS,
    caption,
    charge_text,
    field_label,
    robust_limits,
)
from nemo.render.surfaces import render_surface, surface_plotter
from nemo.render.timeseries import (
    FRAME_PANELS,
    QC_CHARGE_TOLERANCE,
    RELATIVE_SPAN,
    defect_lonlat,
    defect_map_figure,
    frame_qc,
    frames_figure,
    tracks_figure,
)

__all__ = [
    "CAPTIONS",
    "DEFAULT_LAYER",
    "FIELD_CMAPS",
    "FIELD_LABELS",
    "FRAME_PANELS",
    "LAYER_COLOURS",
    "QC_CHARGE_TOLERANCE",
    "RELATIVE_SPAN",
    "SIGNED_KINDS",
    "SURFACE_COLOURS",
    "Figure",
    "Frame",
    "FrameFiles",
    "Layer",
    "ResultsTree",
    "Surface",
    "alignment_figure",
    "caption",
    "charge_text",
    "chart_directions",
    "defect_lonlat",
    "defect_map_figure",
    "discover_frame",
    "distributions_figure",
    "field_label",
    "find_frames",
    "frame_qc",
    "frames_figure",
    "glyph_spacing",
    "load_frame",
    "morphology_figure",
    "planned_figures",
    "render_frame",
    "render_summary",
    "render_surface",
    "robust_limits",
    "save_figure",
    "spherical_angles",
    "spherical_figure",
    "spherical_grid",
    "subsample_even",
    "surface_centre",
    "surface_plotter",
    "tracks_figure",
]
