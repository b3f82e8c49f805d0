"""What ``nemo render`` writes: the figure names, the figures of a frame or summary, figures.json.

:func:`planned_figures` names the PNG files a frame's inputs give (so that a workflow can
declare them as outputs); :func:`render_frame` writes them -- pyvista renders
(:mod:`nemo.render.surfaces`) and matplotlib figures (:mod:`nemo.render.figures`) -- and
:func:`render_summary` writes the time-series figures of a dataset
(:mod:`nemo.render.timeseries`). Both record each file's kind, caption, sources and the
sources' provenance parameters as a :class:`Figure` in ``OUTDIR/figures.json``, from which
the workflow report takes its captions.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from nemo import atomic
from nemo._log import logger, step
from nemo.errors import NemoError
from nemo.layout import (
    MESH_PREFERENCE,
    FrameFiles,
    discover_frame,
    find_frames,
    table_provenance,
)
from nemo.render.charts import glyph_spacing, subsample_even, surface_centre
from nemo.render.data import Frame, Surface, load_frame
from nemo.render.figures import (
    alignment_figure,
    distributions_figure,
    morphology_figure,
    save_figure,
    spherical_figure,
)
from nemo.render.style import FIELD_CMAPS, caption, field_label, robust_limits
from nemo.render.surfaces import render_surface
from nemo.render.timeseries import defect_map_figure, frames_figure, tracks_figure


@dataclass
class Figure:
    """One written figure: file name, kind (a :data:`CAPTIONS` key), caption, sources."""

    path: Path
    kind: str
    caption: str
    sources: list[str] = field(default_factory=list)
    names: dict = field(default_factory=dict)


def planned_figures(frame: FrameFiles, layers: list[str] | None = None) -> dict[str, str]:
    """The PNG names :func:`render_frame` writes for these inputs -> figure kind.

    Naming (so that a workflow can declare outputs): per layer L with a mesh,
    ``surface_intensity_L.png`` (layer table), ``surface_order_L.png`` (order table),
    ``surface_defects_L.png`` (defects table), ``distributions_L.png`` (order or defects),
    ``spherical_L.png`` (always); per curvature/thickness table ``curvature[_X]``/``thickness[_X]``
    ``surface_H[_X].png``, ``surface_K[_X].png``, ``surface_thickness[_X].png`` and one
    ``morphology_map[_X].png``; per alignment table ``align_A_B``: ``alignment_A_B.png``.
    """
    names = layers if layers is not None else frame.layer_names()
    out: dict[str, str] = {}
    for L in names:
        if L in frame.layers:
            out[f"surface_intensity_{L}.png"] = "surface_intensity"
        if L in frame.order:
            out[f"surface_order_{L}.png"] = "surface_order"
        if L in frame.defects:
            out[f"surface_defects_{L}.png"] = "surface_defects"
        if L in frame.order or L in frame.defects:
            out[f"distributions_{L}.png"] = "distributions"
        out[f"spherical_{L}.png"] = "spherical"
    morph = set()
    for key in frame.curvature:
        sfx = f"_{key}" if key else ""
        out[f"surface_H{sfx}.png"] = "surface_H"
        out[f"surface_K{sfx}.png"] = "surface_K"
        morph.add(sfx)
    for key in frame.thickness:
        sfx = f"_{key}" if key else ""
        out[f"surface_thickness{sfx}.png"] = "surface_thickness"
        morph.add(sfx)
    for sfx in sorted(morph):
        out[f"morphology_map{sfx}.png"] = "morphology_map"
    for suffix in frame.align:
        out[f"alignment_{suffix}.png"] = "alignment"
    return out


def _params(paths: list[Path]) -> dict:
    out = {}
    for p in paths:
        prov = table_provenance(p)
        prov.pop("version", None)
        if prov:
            out[p.name] = prov
    return out


def _write_manifest(outdir: Path, figures: list[Figure]) -> Path:
    path = outdir / "figures.json"
    old = {}
    if path.exists():
        try:
            old = json.loads(path.read_text())
        except ValueError:
            old = {}
    for f in figures:
        old[f.path.name] = {"kind": f.kind, "caption": f.caption, "sources": f.sources,
                            "names": f.names, "parameters": _params([Path(s) for s in f.sources])}
    atomic.write_json(path, old, default=str, indent=1)
    return path


def _record(path: Path, kind: str, sources, **names) -> Figure:
    """The :class:`Figure` of a written file, with its caption filled in from ``names``."""
    return Figure(path, kind, caption(kind, **names), [str(s) for s in sources], names)


def _layer_renders(frame: Frame, L: str, outdir: Path, src: list, nm: dict) -> list[Figure]:
    """The pyvista renders of one layer: intensity, S with the directors, defects."""
    ff = frame.files
    lay = frame.layers[L]
    surf = frame.surfaces[lay.surface]
    mesh = surf.mesh
    figs: list[Figure] = []
    if lay.intensity is not None:
        path = render_surface(outdir / f"surface_intensity_{L}.png", mesh, scalars=lay.intensity,
                              label=field_label("intensity"), cmap="gray", clim=robust_limits(lay.intensity),
                              title=f"t={ff.t} c={ff.c} layer {L}: intensity")
        figs.append(_record(path, "surface_intensity", src, **nm))
    if lay.order is not None:
        od = lay.order
        pos = od[["x", "y", "z"]].to_numpy(float)
        keep = subsample_even(pos, glyph_spacing(mesh))
        path = render_surface(outdir / f"surface_order_{L}.png", mesh,
                              scalars=surf.fields.get(f"S ({L})"), label=field_label("S"),
                              cmap="viridis", clim=(0, 1),
                              segments=(pos[keep], od[["nx", "ny", "nz"]].to_numpy(float)[keep],
                                        od["S"].to_numpy(float)[keep]),
                              title=f"t={ff.t} c={ff.c} layer {L}: S and n_avg")
        figs.append(_record(path, "surface_order", src, **nm))
    if lay.defects is not None:
        d = lay.defects
        path = render_surface(outdir / f"surface_defects_{L}.png", mesh, scalars=lay.intensity,
                              label=field_label("intensity") if lay.intensity is not None else "",
                              cmap="gray", clim=robust_limits(lay.intensity)
                              if lay.intensity is not None else None,
                              defects=(d[["x", "y", "z"]].to_numpy(float), d["charge"].to_numpy(float)),
                              title=f"t={ff.t} c={ff.c} layer {L}: {len(d)} defects")
        figs.append(_record(path, "surface_defects", src, **nm))
    return figs


def _layer_figures(frame: Frame, L: str, outdir: Path, surface_renders: bool) -> list[Figure]:
    """Every figure of one layer: the renders, the distributions of S and charge, the map."""
    ff = frame.files
    lay = frame.layers[L]
    surf = frame.surfaces[lay.surface]
    src = list(lay.sources.values()) + [surf.path]
    nm = {"layer": L, "surface": lay.surface}
    figs = _layer_renders(frame, L, outdir, src, nm) if surface_renders else []
    if lay.order is not None or lay.defects is not None:
        S = surf.fields.get(f"S ({L})", np.zeros(0)) if lay.order is not None else np.zeros(0)
        q = lay.defects["charge"].to_numpy(float) if lay.defects is not None else np.zeros(0)
        path = save_figure(distributions_figure(S, q, f"t={ff.t} c={ff.c} layer {L}"),
                           outdir / f"distributions_{L}.png")
        figs.append(_record(path, "distributions", src, **nm))
    path = save_figure(spherical_figure(frame, L), outdir / f"spherical_{L}.png")
    figs.append(_record(path, "spherical", src, **nm))
    return figs


def _morphology_figures(frame: Frame, outdir: Path, surface_renders: bool) -> list[Figure]:
    """Per curvature/thickness table the renders of H, K, thickness; per surface one map."""
    ff = frame.files
    figs: list[Figure] = []
    morph: dict[str, tuple[Surface, list]] = {}
    for kind, tables in (("curvature", ff.curvature), ("thickness", ff.thickness)):
        for key, path in tables.items():
            surf = next((s for s in frame.surfaces.values()
                         if s.sources.get("H" if kind == "curvature" else "thickness") == path), None)
            if surf is None:
                continue
            sfx = f"_{key}" if key else ""
            morph.setdefault(sfx, (surf, []))[1].extend([path, surf.path])
            if not surface_renders:
                continue
            for col in (("H", "K") if kind == "curvature" else ("thickness",)):
                vals = surf.fields[col]
                out = render_surface(outdir / f"surface_{col}{sfx}.png", surf.mesh, scalars=vals,
                                     label=surf.label(col), cmap=FIELD_CMAPS[col], clim=robust_limits(vals, col),
                                     title=f"t={ff.t} c={ff.c} {col} ({surf.key})")
                figs.append(_record(out, f"surface_{col}", [path, surf.path], surface=surf.key))
    for sfx, (surf, src) in sorted(morph.items()):
        fig = morphology_figure(surf)
        if fig is not None:
            out = save_figure(fig, outdir / f"morphology_map{sfx}.png")
            figs.append(_record(out, "morphology_map", sorted(set(src)), surface=surf.key))
    return figs


def _alignment_figures(frame: Frame, outdir: Path) -> list[Figure]:
    """One map and histogram of c per pair of aligned layers."""
    figs: list[Figure] = []
    for pair, suffix in frame.align_suffix.items():
        path = frame.files.align[suffix]
        out = save_figure(alignment_figure(frame, pair), outdir / f"alignment_{suffix}.png")
        figs.append(_record(out, "alignment", [path], a=pair[0], b=pair[1]))
    return figs


def render_frame(inputs, outdir: str | os.PathLike, layers: list[str] | None = None,
                 surface_renders: bool = True, image: str | os.PathLike | None = None) -> list[Figure]:
    """Write every figure of one frame into ``outdir`` (names: :func:`planned_figures`).

    Parameters
    ----------
    inputs : frame folder, list of files, FrameFiles or Frame
    outdir : path
    layers : list of str, optional
        Only these layers (default all found).
    surface_renders : bool
        False skips the pyvista renders (matplotlib figures only).

    Returns
    -------
    list of Figure
        Also recorded in ``outdir/figures.json``.

    Raises
    ------
    NemoError
        No mesh, or a requested layer that has no tables.
    """
    frame = inputs if isinstance(inputs, Frame) else load_frame(
        inputs if isinstance(inputs, FrameFiles) else discover_frame(inputs, image=image))
    ff = frame.files
    names = list(frame.layers) if not layers else list(layers)
    unknown = [n for n in names if n not in frame.layers]
    if unknown:
        raise NemoError(f"layer(s) {', '.join(unknown)} have no tables in the inputs "
                        f"(found: {', '.join(frame.layers) or 'none'})")
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    figs: list[Figure] = []
    with step(f"rendering figures of t={ff.t} c={ff.c} into {outdir}"):
        for L in names:
            figs.extend(_layer_figures(frame, L, outdir, surface_renders))
        figs.extend(_morphology_figures(frame, outdir, surface_renders))
        figs.extend(_alignment_figures(frame, outdir))
    _write_manifest(outdir, figs)
    for f in figs:
        logger.info("wrote %s", f.path)
    return figs


def _summary_files(inputs) -> dict[str, Path]:
    items = [inputs] if isinstance(inputs, (str, os.PathLike)) else list(inputs)
    out: dict[str, Path] = {}
    for item in items:
        p = Path(item)
        if not p.exists():
            raise NemoError(f"{p} does not exist; give results/DATASET/summary or its tables")
        files = sorted(p.glob("*.parquet")) if p.is_dir() else [p]
        for f in files:
            stem = f.name[: -len(".parquet")] if f.name.endswith(".parquet") else f.stem
            if stem in ("defects", "frames", "tracks", "alignment"):
                out[stem] = f
    return out


def _frame_centres(dataset_dir: Path) -> dict[tuple, np.ndarray]:
    """Surface centroid per frame ``(t, c)``; with several objects also per ``(t, c, object)``."""
    from nemo import objects
    from nemo.mesh import load_mesh

    centres = {}
    try:
        tree = find_frames(dataset_dir)
    except NemoError:
        return centres
    for key, d in tree.frames.items():
        ff = discover_frame(d)
        mkey = next((k for k in (*MESH_PREFERENCE, *ff.meshes) if k in ff.meshes), None)
        try:
            mesh = load_mesh(ff.meshes[mkey], manifold=False)
            centres[key] = surface_centre(mesh)
            for part in objects.parts(mesh) or []:  # a handful of objects
                centres[(*key, part.label)] = surface_centre(part.mesh)
        except NemoError:
            continue
    return centres


def _table_unit(*paths: Path) -> str:
    """The length unit recorded in the provenance of the first table that has one (else µm)."""
    for path in paths:
        unit = table_provenance(path).get("unit")
        if isinstance(unit, str) and unit:
            return unit
    return "um"


def render_summary(inputs, outdir: str | os.PathLike, layers: list[str] | None = None,
                   centres: bool = True) -> list[Figure]:
    """Write the time-series figures of a dataset's summary tables.

    Parameters
    ----------
    inputs : path or list of paths
        The summary folder or its tables (``defects.parquet``, ``frames.parquet``).
    outdir : path
    layers : list of str, optional
        Only these layers of ``defects.parquet`` (default all).
    centres : bool
        Use the frame meshes beside the summary folder as the spherical-map centres.

    Returns
    -------
    list of Figure
        Per layer of ``defects.parquet`` (needs ``track_id``): ``tracks_<layer>.png`` and
        ``defect_map_<layer>.png`` (``tracks.png``, ``defect_map.png`` without a ``layer``
        column); ``frames.png`` from ``frames.parquet``. Also recorded in
        ``outdir/figures.json``.

    Raises
    ------
    NemoError
        No summary tables among the inputs.
    """
    from nemo.tables import read_table

    tables = _summary_files(inputs)
    if not tables:
        raise NemoError(f"no summary tables (defects.parquet, frames.parquet) in {inputs}")
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    figs: list[Figure] = []
    unit = _table_unit(*(tables[k] for k in ("frames", "defects") if k in tables))
    with step(f"rendering summary figures into {outdir}"):
        if "defects" in tables:
            src = [str(tables["defects"])]
            df = read_table(tables["defects"], columns=("t", "x", "y", "z", "charge", "track_id"))
            ctr = _frame_centres(tables["defects"].parent.parent) if centres else {}
            names = layers or (sorted(df["layer"].astype(str).unique()) if "layer" in df.columns else [None])
            for L in names:
                sfx = f"_{L}" if L is not None else ""
                path = save_figure(tracks_figure(df, L, ctr or None), outdir / f"tracks{sfx}.png")
                figs.append(Figure(path, "tracks", caption("tracks", layer=L or ""), src, {"layer": L}))
                path = save_figure(defect_map_figure(df, L, ctr or None), outdir / f"defect_map{sfx}.png")
                figs.append(Figure(path, "defect_map", caption("defect_map", layer=L or ""), src, {"layer": L}))
        if "frames" in tables:
            dataset = tables["frames"].parent.parent.name
            fig = frames_figure(read_table(tables["frames"], columns=("t",)), unit=unit,
                                title=f"dataset {dataset}: per-frame summary")
            if fig is not None:
                path = save_figure(fig, outdir / "frames.png")
                figs.append(Figure(path, "frames", caption("frames"), [str(tables["frames"])], {}))
    _write_manifest(outdir, figs)
    return figs
