"""The frame data model: one frame's meshes and tables read into surfaces, layers, alignments.

:func:`load_frame` takes the files found by :func:`nemo.layout.discover_frame` and returns a
:class:`Frame`: per mesh a :class:`Surface` with its per-vertex fields (intensity, S, H, K,
thickness, alignment c), per layer a :class:`Layer` with its order, director and defect
tables. Each table is placed on the mesh it was computed on (:func:`_pick_mesh`: the mesh
named in its provenance, else the one whose vertex count fits). Missing tables mean "not
shown", never an error; a table that cannot be read or matched to a mesh is skipped with a
warning. Both the figures and the napari layers draw from this model.

All positions are physical ``x, y, z`` (µm); nothing here converts to napari's ``(z, y, x)``.
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from nemo.errors import NemoError, NemoWarning
from nemo.layout import (
    MESH_PREFERENCE,
    FrameFiles,
    discover_frame,
    provenance_strings,
    table_provenance,
)
from nemo.render.style import field_label


@dataclass
class Surface:
    """A mesh with the per-vertex fields found for it.

    ``fields`` maps a display name (``"intensity (a)"``, ``"S (a)"``, ``"H"``, ``"c (a-b)"``)
    to an ``(N,)`` array; ``kinds`` maps the same names to the field kind (for labels/cmaps).
    """

    key: str
    path: Path
    mesh: object  # trimesh.Trimesh
    fields: dict[str, np.ndarray] = field(default_factory=dict)
    kinds: dict[str, str] = field(default_factory=dict)
    sources: dict[str, Path] = field(default_factory=dict)

    @property
    def unit(self) -> str:
        return getattr(self.mesh, "units", None) or "um"

    def label(self, name: str) -> str:
        return field_label(self.kinds.get(name, name), self.unit)


@dataclass
class Layer:
    """One nematic layer of a frame.

    Attributes
    ----------
    name : str
    surface : str
        Key of the mesh its tables refer to.
    intensity : ndarray, shape (N,) or None
    order : DataFrame or None
        ``x, y, z, S, nx, ny, nz`` (positions filled from the mesh when absent).
    directors : DataFrame or None
        ``x, y, z, nx, ny, nz, coherency``.
    defects : DataFrame or None
        ``x, y, z, charge`` (+ ``charge_rounded``, ``S``...).
    """

    name: str
    surface: str
    intensity: np.ndarray | None = None
    order: pd.DataFrame | None = None
    directors: pd.DataFrame | None = None
    defects: pd.DataFrame | None = None
    sources: dict[str, Path] = field(default_factory=dict)


@dataclass
class Frame:
    """Everything loaded for one frame."""

    files: FrameFiles
    surfaces: dict[str, Surface]
    layers: dict[str, Layer]
    align: dict[tuple[str, str], pd.DataFrame]
    align_surface: dict[tuple[str, str], str]
    align_suffix: dict[tuple[str, str], str] = field(default_factory=dict)

    @property
    def t(self) -> int:
        return self.files.t

    @property
    def c(self) -> int:
        return self.files.c


def _read(path: Path, kind: str) -> pd.DataFrame | None:
    from nemo.tables import read_table

    try:
        return read_table(path, kind)
    except NemoError as exc:
        warnings.warn(f"not shown: {exc}", NemoWarning, stacklevel=4)  # at load_frame's caller
        return None


def _pick_mesh(path: Path, df: pd.DataFrame, meshes: dict[str, object], hint: str = "",
               per_vertex: bool = True) -> str | None:
    """Which mesh a table's ``vertex`` column refers to.

    In order: a mesh file named in the table's provenance; the hint (e.g. ``curvature_inner``);
    for per-vertex tables a mesh with exactly as many vertices as the table has rows; any mesh
    with more vertices than the largest index (preferring inner, mesh, outer).
    """
    prov = table_provenance(path)
    by_file = {getattr(m, "_nemo_file", None): k for k, m in meshes.items()}
    for field_name in ("mesh", "mesh_from", "mesh_a", "surface"):  # the table's own mesh first
        value = prov.get(field_name)
        if isinstance(value, str) and Path(value).name in by_file:
            return by_file[Path(value).name]
    named = {by_file[Path(s).name] for s in provenance_strings(prov) if Path(s).name in by_file}
    if len(named) == 1:
        return named.pop()
    made_on = prov.get("n_vertices")  # a table records the size of the mesh it was made on
    if made_on is not None:
        meshes = {k: m for k, m in meshes.items() if len(m.vertices) == int(made_on)}
        if not meshes:
            warnings.warn(f"not shown: {path} was computed on a mesh of {made_on} vertices, none of the "
                          "meshes given has that many (a table of another mesh)", NemoWarning, stacklevel=4)
            return None
    hint = {"whole": "mesh"}.get(hint, hint)  # workflow: curvature_whole -> mesh.ply
    if hint and hint in meshes:
        return hint
    vmax = int(df["vertex"].max()) if len(df) else -1
    order = [k for k in MESH_PREFERENCE if k in meshes] + [k for k in meshes if k not in MESH_PREFERENCE]
    if per_vertex:
        exact = [k for k in order if len(meshes[k].vertices) == len(df)]
        if exact:
            return exact[0]
    fits = [k for k in order if len(meshes[k].vertices) > vmax]
    if fits:
        return fits[0]
    warnings.warn(f"not shown: {path} refers to vertex {vmax}, beyond every mesh of the frame",
                  NemoWarning, stacklevel=4)
    return None


def _scatter(df: pd.DataFrame, column: str, n: int) -> np.ndarray:
    out = np.full(n, np.nan)
    out[df["vertex"].to_numpy(dtype=np.int64)] = df[column].to_numpy(dtype=np.float64)
    return out


def _fill_nearest(values: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """Fill NaN entries of a sparse per-vertex field from the nearest finite vertex (display)."""
    ok = np.isfinite(values)
    if ok.all() or not ok.any():
        return values
    _, idx = cKDTree(vertices[ok]).query(vertices[~ok])
    out = values.copy()
    out[~ok] = values[ok][idx]
    return out


def _with_positions(df: pd.DataFrame, vertices: np.ndarray) -> pd.DataFrame:
    if not {"x", "y", "z"} <= set(df.columns):
        df = df.copy()
        xyz = vertices[df["vertex"].to_numpy(dtype=np.int64)]
        df["x"], df["y"], df["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    return df


def _load_meshes(ff: FrameFiles) -> dict[str, object]:
    """The frame's readable meshes by key; an unreadable mesh is skipped with a warning."""
    from nemo.mesh import load_mesh

    meshes = {}
    for key, path in ff.meshes.items():
        try:
            mesh = load_mesh(path, manifold=False)  # show what is there
        except NemoError as exc:
            warnings.warn(f"not shown: {exc}", NemoWarning, stacklevel=3)  # at load_frame's caller
            continue
        mesh._nemo_file = path.name
        meshes[key] = mesh
    if not meshes:
        raise NemoError(f"no readable mesh among {', '.join(map(str, ff.meshes.values()))}")
    return meshes


def _add_field(surface: Surface, name: str, kind: str, values: np.ndarray, src: Path) -> None:
    """Put a per-vertex field on a surface, its NaN entries filled from the nearest vertex."""
    surface.fields[name] = _fill_nearest(values, np.asarray(surface.mesh.vertices))
    surface.kinds[name] = kind
    surface.sources[name] = src


def _load_layer(name: str, ff: FrameFiles, meshes: dict[str, object],
                surfaces: dict[str, Surface]) -> Layer:
    """One layer's tables; its intensity and S also become fields of the surface they are on."""
    layer = Layer(name=name, surface="")
    for kind, table in (("layer", ff.layers), ("order", ff.order), ("directors", ff.directors),
                        ("defects", ff.defects)):
        if name not in table:
            continue
        df = _read(table[name], kind)
        if df is None:
            continue
        layer.sources[kind] = table[name]
        if kind == "defects":
            layer.defects = df
            continue
        key = layer.surface or _pick_mesh(table[name], df, meshes, per_vertex=kind != "directors")
        if key is None:
            continue
        layer.surface = key
        verts = np.asarray(meshes[key].vertices)
        suffix = f" ({name})"
        if kind == "layer":
            layer.intensity = _scatter(df, "intensity", len(verts))
            _add_field(surfaces[key], "intensity" + suffix, "intensity", layer.intensity, table[name])
        elif kind == "order":
            layer.order = _with_positions(df, verts)
            _add_field(surfaces[key], "S" + suffix, "S", _scatter(df, "S", len(verts)), table[name])
        else:
            layer.directors = _with_positions(df, verts)
    if not layer.surface:
        layer.surface = next(k for k in (*MESH_PREFERENCE, *meshes) if k in meshes)
    return layer


def _load_morphology(ff: FrameFiles, meshes: dict[str, object], surfaces: dict[str, Surface]) -> None:
    """Curvature (H, K) and thickness tables as fields of the surface each was computed on."""
    for kind, tables in (("curvature", ff.curvature), ("thickness", ff.thickness)):
        for hint, path in tables.items():
            df = _read(path, kind)
            if df is None:
                continue
            key = _pick_mesh(path, df, meshes, hint=hint)
            if key is None:
                continue
            n = len(meshes[key].vertices)
            cols = ("H", "K") if kind == "curvature" else ("thickness",)
            for col in cols:
                values = _scatter(df, col, n)
                if kind == "thickness":  # NaN = no hit: keep it, do not fill
                    s = surfaces[key]
                    s.fields[col], s.kinds[col], s.sources[col] = values, col, path
                else:
                    _add_field(surfaces[key], col, col, values, path)


def _load_alignments(ff: FrameFiles, meshes: dict[str, object], layers: dict[str, Layer],
                     surfaces: dict[str, Surface]) -> tuple[dict, dict, dict]:
    """Alignment tables by layer pair (a, b): (tables, surface keys, file suffixes).

    Each table lies on the mesh of layer a; its c becomes the field ``c (a-b)`` there.
    """
    align, align_surface, align_suffix = {}, {}, {}
    for suffix, path in ff.align.items():
        df = _read(path, "align")
        if df is None:
            continue
        a, b = _split_pair(suffix, list(layers))
        key = layers[a].surface if a in layers else _pick_mesh(path, df, meshes, per_vertex=False)
        if key is None or (len(df) and int(df["vertex"].max()) >= len(meshes[key].vertices)):
            warnings.warn(f"not shown: {path} does not fit the mesh of layer {a}", NemoWarning,
                          stacklevel=3)  # at load_frame's caller
            continue
        verts = np.asarray(meshes[key].vertices)
        align[(a, b)] = _with_positions(df, verts)
        align_surface[(a, b)] = key
        align_suffix[(a, b)] = suffix
        _add_field(surfaces[key], f"c ({a}-{b})", "c", _scatter(df, "c", len(verts)), path)
    return align, align_surface, align_suffix


def load_frame(files: FrameFiles | str | os.PathLike | list) -> Frame:
    """Read a frame's meshes and tables into surfaces with fields, layers, alignments.

    Parameters
    ----------
    files : FrameFiles or anything :func:`discover_frame` accepts

    Returns
    -------
    Frame
        Per-vertex fields are placed on the mesh each table refers to (see
        :func:`_pick_mesh`). Sparse per-vertex fields (S on director vertices, alignment c) are
        filled from the nearest vertex *for display*.
    """
    # The helpers are called from here directly: their warnings use stacklevel 3 (_read and
    # _pick_mesh, one call deeper: 4) so that they point at the caller of load_frame.
    ff = files if isinstance(files, FrameFiles) else discover_frame(files)
    meshes = _load_meshes(ff)
    surfaces = {k: Surface(k, ff.meshes[k], m) for k, m in meshes.items()}
    layers: dict[str, Layer] = {}
    for name in ff.layer_names():
        layers[name] = _load_layer(name, ff, meshes, surfaces)
    _load_morphology(ff, meshes, surfaces)
    align, align_surface, align_suffix = _load_alignments(ff, meshes, layers, surfaces)
    return Frame(ff, surfaces, layers, align, align_surface, align_suffix)


def _split_pair(suffix: str, layer_names: list[str]) -> tuple[str, str]:
    """Split ``"<a>_<b>"`` using the known layer names (names may contain underscores)."""
    for a in sorted(layer_names, key=len, reverse=True):
        if suffix.startswith(a + "_") and suffix[len(a) + 1:]:
            return a, suffix[len(a) + 1:]
    a, _, b = suffix.partition("_")
    return a, b or "?"
