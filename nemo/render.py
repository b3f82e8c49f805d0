"""Figures of NEMO results: result discovery, pyvista surface renders, matplotlib figures.

Three parts, used by ``nemo render`` (figures for a report), ``nemo view`` and the napari
plugin (:mod:`nemo.napari`):

* **Discovery** -- :func:`discover_frame` classifies the files of one frame folder (or an
  explicit list of files) by name pattern; :func:`find_frames` finds the frames of a results
  tree ``results/{dataset}/t{t}/c{c}/``; :func:`load_frame` reads meshes and tables into
  per-surface fields, per-layer directors and defects. Missing tables mean "not shown", never
  an error; a table that cannot be matched to a mesh is skipped with a warning.
* **Surface renders** (pyvista, off-screen through EGL/OSMesa, no X server needed):
  :func:`render_surface` -- two opposite views of the surface coloured by a field, with
  optional nematic glyphs (headless segments) and defect markers labelled by charge.
* **Matplotlib figures** (object-oriented, Agg canvas, no pyplot state): distributions of S
  and charge (paper Fig. 2C), spherical-coordinate maps around the surface centroid (paper
  Fig. 2D), morphology maps, alignment map and histogram, defect tracks over time.

:data:`CAPTIONS` holds a caption for each figure kind; :func:`render_frame` and
:func:`render_summary` also write ``figures.json`` (file -> kind, caption, sources, parameters)
into the output folder so that a workflow can attach captions to report items.

All positions are physical ``x, y, z`` (µm); nothing here converts to napari's ``(z, y, x)``.
"""

from __future__ import annotations

import json
import os
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from nemo import atomic, layout
from nemo._log import logger, step
from nemo.errors import NemoError, NemoWarning

# --------------------------------------------------------------------------------------------
# labels, captions

#: Colour-bar label of each field kind (``{unit}`` is the mesh's unit, normally µm).
FIELD_LABELS: dict[str, str] = {
    "intensity": "intensity [a.u.]",
    "S": "S",
    "coherency": "coherency",
    "H": "H [1/{unit}]",
    "K": "K [1/{unit}²]",
    "k1": "k1 [1/{unit}]",
    "k2": "k2 [1/{unit}]",
    "thickness": "thickness [{unit}]",
    "c": "alignment c = cos 2Δθ",
    "charge": "charge m",
    "t": "time point t",
}

#: Default colour map of each field kind.
FIELD_CMAPS: dict[str, str] = {
    "intensity": "gray", "S": "viridis", "coherency": "viridis", "H": "RdBu_r", "K": "RdBu_r",
    "k1": "RdBu_r", "k2": "RdBu_r", "thickness": "magma", "c": "coolwarm", "charge": "bwr",
}

#: Caption of each figure kind; ``{layer}``, ``{surface}``, ``{a}``, ``{b}`` are filled in.
CAPTIONS: dict[str, str] = {
    "surface_intensity": (
        "Layer {layer}: peeled intensity [a.u.] on the {surface} surface, two opposite views. "
        "Each vertex carries the image sampled along its outward normal over the layer's depth "
        "range and reduced to one value (the 'projection of an intensity layer')."
    ),
    "surface_order": (
        "Layer {layer}: nematic order S of the tangential Q-tensor average on the {surface} "
        "surface, with the averaged directors n_avg drawn as headless segments coloured by S "
        "(one per surface cell of the glyph spacing). Low S marks disorder and defect cores."
    ),
    "surface_defects": (
        "Layer {layer}: topological defects on the {surface} surface (grey: peeled intensity). "
        "Markers are coloured by the curvature-corrected charge m (blue negative, red positive) "
        "and labelled with the charge rounded to the nearest half."
    ),
    "distributions": (
        "Layer {layer}: probability density of the nematic order S over all surface vertices "
        "(left) and of the defect charges m (right; dashed lines at ±1/2), as in the paper's "
        "Fig. 2C."
    ),
    "spherical": (
        "Layer {layer}: the surface in spherical coordinates around its centroid (azimuth φ "
        "from +x towards +y, polar angle θ from +z), as in the paper's Fig. 2D. Background: "
        "peeled intensity; segments: averaged directors coloured by S; circles: defects coloured "
        "by charge. Near the poles the map stretches in φ."
    ),
    "surface_H": "Mean curvature H [1/µm] on the {surface} surface (outward normals: a sphere "
                 "of radius R has H = +1/R), two opposite views.",
    "surface_K": "Gaussian curvature K [1/µm²] on the {surface} surface (sphere: K = 1/R²; "
                 "saddles negative), two opposite views.",
    "surface_thickness": "Thickness [µm] from the {surface} surface to the opposite surface "
                         "along the vertex normals; grey where the ray found no surface (NaN).",
    "morphology_map": "Morphology of the {surface} surface in spherical coordinates around "
                      "its centroid: mean curvature H [1/µm], Gaussian curvature K [1/µm²] and "
                      "thickness [µm] (where computed).",
    "alignment": (
        "Inter-layer alignment between layers {a} and {b}: c = cos 2(θ_b − θ_a) at each "
        "director of {a} with the nearest director of {b} (1 parallel, −1 orthogonal), in "
        "spherical coordinates (left) and as a histogram with its mean (right)."
    ),
    "tracks": (
        "Layer {layer}: defect tracks over time in spherical coordinates around the surface "
        "centroid (left; one colour per track, label = track id and charge) and the distance "
        "travelled from each track's first position along the surface (right)."
    ),
    "defect_map": (
        "Layer {layer}: the defects of every frame on an equal-area (Mollweide) map around the "
        "surface centroid (longitude = azimuth φ from +x towards +y, latitude = 90° − θ, north "
        "= +z). Colour: charge m on a diverging scale centred on 0 (red positive, blue "
        "negative); shape: circle m > 0, triangle m < 0; earlier frames fainter, the last frame "
        "with bold edges; grey lines join the positions of one track."
    ),
    "frames": (
        "Per-frame summary over time t. Top row, per layer (one colour per channel and layer): "
        "nematic order S (mean solid, median dashed; 0–1), number of defects, and their total "
        "charge Σm with the surface's Euler characteristic χ as dashed reference (Poincaré–Hopf: "
        "Σm = χ on a closed surface; grey band ±0.25). Second row, per surface: wall thickness "
        "(mean, median), mean curvature H (mesh and fit), area and enclosed volume. Morphology "
        "axes span at least ±5 % of the mean, so numerical noise looks flat. Bottom: quality "
        "control per frame (green pass, red ✕ flagged; flagged t shaded red in every panel) "
        "with the reasons."
    ),
}


def caption(kind: str, **names) -> str:
    """The caption of a figure kind with its names filled in (missing names stay readable)."""

    class _Keep(dict):
        def __missing__(self, key):
            return key

    return CAPTIONS[kind].format_map(_Keep(**{k: v for k, v in names.items() if v is not None}))


def field_label(kind: str, unit: str = "um") -> str:
    """Colour-bar label of a field kind with its physical unit (``"um"`` shown as µm)."""
    u = "µm" if unit in ("um", "µm", "micron") else unit
    return FIELD_LABELS.get(kind, kind).replace("{unit}", u)


def charge_text(q: float) -> str:
    """A charge rounded to the nearest half as text: ``+1/2``, ``-1/2``, ``+1``, ``0``."""
    if not np.isfinite(q):
        return "?"
    half = round(2 * float(q))
    if half == 0:
        return "0"
    sign = "+" if half > 0 else "-"
    return f"{sign}{abs(half)}/2" if half % 2 else f"{sign}{abs(half) // 2}"


# --------------------------------------------------------------------------------------------
# discovery

_MESH_PREFIX = re.compile(r"^mesh[._-]?")
_TABLE = re.compile(  # the per-frame tables of nemo.layout (named, or unnamed single files)
    rf"^(?P<kind>{'|'.join((*layout.LAYER_KINDS, 'curvature', 'thickness', 'align'))})(?:[._-](?P<name>.+))?$"
)
_FRAME_DIR = re.compile(r"^t(\d+)$")
_CHANNEL_DIR = re.compile(r"^c(\d+)$")
#: Name given to the layer of the single-frame ``nemo run`` files (``layer.parquet`` ...).
DEFAULT_LAYER = "layer"
#: Preference when a table fits several meshes (paper: layers live on the inner mesh).
_MESH_PREFERENCE = ("inner", "mesh", "outer")


@dataclass
class FrameFiles:
    """The result files of one frame, classified by name.

    Attributes
    ----------
    path : Path or None
        The frame folder (None for an explicit file list spread over folders).
    t, c : int
        Time point and channel (from ``t{t}/c{c}`` folder names; 0 otherwise).
    meshes : dict
        Mesh key -> PLY/OBJ file; ``mesh.ply`` -> ``"mesh"``, ``mesh.inner.ply`` -> ``"inner"``.
    layers, directors, order, defects : dict
        Layer name -> table (``layer_<name>.parquet`` ...; unnamed files -> ``"layer"``).
    curvature, thickness : dict
        Surface key (``""`` for the unnamed file, else e.g. ``"inner"``) -> table.
    align : dict
        Suffix ``"<a>_<b>"`` -> table.
    image : Path or None
        The hyperstack the frame came from, when it can be found.
    """

    path: Path | None = None
    t: int = 0
    c: int = 0
    meshes: dict[str, Path] = field(default_factory=dict)
    layers: dict[str, Path] = field(default_factory=dict)
    directors: dict[str, Path] = field(default_factory=dict)
    order: dict[str, Path] = field(default_factory=dict)
    defects: dict[str, Path] = field(default_factory=dict)
    curvature: dict[str, Path] = field(default_factory=dict)
    thickness: dict[str, Path] = field(default_factory=dict)
    align: dict[str, Path] = field(default_factory=dict)
    image: Path | None = None

    def layer_names(self) -> list[str]:
        """Every layer name that has at least one table, sorted."""
        names = set(self.layers) | set(self.directors) | set(self.order) | set(self.defects)
        return sorted(names)

    def tables(self) -> list[Path]:
        out: list[Path] = []
        for d in (self.layers, self.directors, self.order, self.defects, self.curvature,
                  self.thickness, self.align):
            out.extend(d.values())
        return out


def _mesh_key(path: Path) -> str:
    stem = path.name[: -len(path.suffix)]
    key = _MESH_PREFIX.sub("", stem)
    return key or "mesh"


def _int_from(pattern: re.Pattern, name: str) -> int | None:
    m = pattern.match(name)
    return int(m.group(1)) if m else None


def discover_frame(paths: str | os.PathLike | list, image: str | os.PathLike | None = None) -> FrameFiles:
    """Classify the result files of one frame.

    Parameters
    ----------
    paths : path or list of paths
        A frame folder (its files are globbed) or explicit files (meshes ``*.ply``/``*.obj``,
        tables ``*.parquet``). Names follow ``docs/viewing.md``; unknown files are ignored.
    image : path, optional
        The hyperstack; otherwise searched in the tables' provenance and beside the results.

    Returns
    -------
    FrameFiles

    Raises
    ------
    NemoError
        A path that does not exist, or no mesh among the inputs.
    """
    items = [paths] if isinstance(paths, (str, os.PathLike)) else list(paths)
    files: list[Path] = []
    folder: Path | None = None
    for item in items:
        p = Path(item)
        if not p.exists():
            raise NemoError(f"{p} does not exist; give a frame folder or its result files")
        if p.is_dir():
            folder = p
            files.extend(sorted(q for q in p.iterdir() if q.is_file()))
        else:
            files.append(p)
    if folder is None and files:
        parents = {f.parent for f in files}
        folder = parents.pop() if len(parents) == 1 else None
    ff = FrameFiles(path=folder)
    # t and c from the folder names t{t}/c{c} (the tables' folder when files are spread out)
    for d in ([folder] if folder is not None else []) + [f.parent for f in files if f.suffix == ".parquet"]:
        c = _int_from(_CHANNEL_DIR, d.name)
        t = _int_from(_FRAME_DIR, d.parent.name)
        if c is not None and t is not None:
            ff.t, ff.c = t, c
            break
    for f in files:
        if f.name.startswith("."):
            continue  # temporary files of atomic writes
        suffix = f.suffix.lower()
        if suffix in (".ply", ".obj"):
            ff.meshes[_mesh_key(f)] = f
            continue
        if suffix != ".parquet" or f.name.endswith(".profile.parquet"):
            continue
        m = _TABLE.match(f.name[: -len(".parquet")])
        if not m:
            continue
        kind, name = m.group("kind"), m.group("name")
        if kind in ("curvature", "thickness"):
            getattr(ff, kind)[name or ""] = f
        elif kind == "align":
            ff.align[name or "a_b"] = f
        else:
            getattr(ff, {"layer": "layers"}.get(kind, kind))[name or DEFAULT_LAYER] = f
    if not ff.meshes:
        where = folder if folder is not None else ", ".join(map(str, items))
        raise NemoError(
            f"no mesh (*.ply or *.obj) found in {where}: give a NEMO frame folder "
            "(results/DATASET/tT/cC) or list the mesh with the tables"
        )
    ff.image = Path(image) if image is not None else _find_image(ff)
    return ff


def _strings(obj) -> list[str]:
    if isinstance(obj, str):
        return [obj]
    if isinstance(obj, dict):
        return [s for v in obj.values() for s in _strings(v)]
    if isinstance(obj, (list, tuple)):
        return [s for v in obj for s in _strings(v)]
    return []


def _provenance(path: Path) -> dict:
    from nemo.tables import read_provenance

    try:
        return read_provenance(path)
    except (OSError, ValueError):  # a convenience: a foreign or broken Parquet file has none
        return {}


def _find_image(ff: FrameFiles) -> Path | None:
    """The frame's hyperstack: a TIFF named in a table's provenance, else one beside it."""
    roots = [Path.cwd()]
    if ff.path is not None:
        roots += [ff.path, *ff.path.resolve().parents]
    for table in list(ff.layers.values()) + ff.tables():
        for s in _strings(_provenance(table)):
            if not s.lower().endswith((".tif", ".tiff")):
                continue
            p = Path(s)
            for cand in ([p] if p.is_absolute() else [r / p for r in roots]):
                if cand.is_file():
                    return cand
    if ff.path is not None:
        for d in (ff.path, *ff.path.parents[:3]):
            tifs = sorted(d.glob("*.tif")) + sorted(d.glob("*.tiff"))
            if len(tifs) == 1:
                return tifs[0]
    return None


@dataclass
class ResultsTree:
    """Frames of one dataset: ``frames[(t, c)]`` is a frame folder."""

    root: Path
    dataset: str | None
    frames: dict[tuple[int, int], Path]
    summary: Path | None

    @property
    def channels(self) -> list[int]:
        return sorted({c for _, c in self.frames})

    def times(self, c: int) -> list[int]:
        return sorted(t for t, cc in self.frames if cc == c)


def _has_mesh(d: Path) -> bool:
    return any(p.suffix.lower() in (".ply", ".obj") for p in d.iterdir() if p.is_file())


def find_frames(path: str | os.PathLike, dataset: str | None = None) -> ResultsTree:
    """Find the frames under a results folder.

    ``path`` may be a frame folder (holding a mesh), a dataset folder (``t*/c*/`` below it),
    or the results root (``*/t*/c*/``; pick one with ``dataset``, default the first).

    Raises
    ------
    NemoError
        No NEMO results under ``path``, or an unknown ``dataset``.
    """
    root = Path(path)
    if not root.is_dir():
        raise NemoError(f"{root} is not a folder; give a NEMO results folder (e.g. results/demo)")

    def frames_of(d: Path) -> dict[tuple[int, int], Path]:
        out = {}
        for tdir in d.glob("t*"):
            t = _int_from(_FRAME_DIR, tdir.name)
            if t is None or not tdir.is_dir():
                continue
            for cdir in tdir.glob("c*"):
                c = _int_from(_CHANNEL_DIR, cdir.name)
                if c is not None and cdir.is_dir() and _has_mesh(cdir):
                    out[(t, c)] = cdir
        return out

    if _has_mesh(root):
        c = _int_from(_CHANNEL_DIR, root.name)
        t = _int_from(_FRAME_DIR, root.parent.name)
        key = (t or 0, c or 0)
        summary = root.parent.parent / "summary" if c is not None and t is not None else None
        return ResultsTree(root, None, {key: root},
                           summary if summary is not None and summary.is_dir() else None)
    frames = frames_of(root)
    if frames:
        summary = root / "summary"
        return ResultsTree(root, root.name, frames, summary if summary.is_dir() else None)
    datasets = {d.name: d for d in sorted(root.iterdir()) if d.is_dir() and frames_of(d)}
    if not datasets:
        raise NemoError(
            f"no NEMO results under {root}: expected meshes in {root}/, {root}/tT/cC/ or "
            f"{root}/DATASET/tT/cC/ (see docs/viewing.md)"
        )
    if dataset is None:
        dataset = next(iter(datasets))
        if len(datasets) > 1:
            logger.info("several datasets in %s (%s); showing %s (choose with --dataset)",
                        root, ", ".join(datasets), dataset)
    if dataset not in datasets:
        raise NemoError(f"dataset {dataset!r} not found in {root} (found: {', '.join(datasets)})")
    return find_frames(datasets[dataset])


# --------------------------------------------------------------------------------------------
# loading


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
        warnings.warn(f"not shown: {exc}", NemoWarning, stacklevel=3)
        return None


def _pick_mesh(path: Path, df: pd.DataFrame, meshes: dict[str, object], hint: str = "",
               per_vertex: bool = True) -> str | None:
    """Which mesh a table's ``vertex`` column refers to.

    In order: a mesh file named in the table's provenance; the hint (e.g. ``curvature_inner``);
    for per-vertex tables a mesh with exactly as many vertices as the table has rows; any mesh
    with more vertices than the largest index (preferring inner, mesh, outer).
    """
    prov = _provenance(path)
    by_file = {getattr(m, "_nemo_file", None): k for k, m in meshes.items()}
    for field_name in ("mesh", "mesh_from", "mesh_a", "surface"):  # the table's own mesh first
        value = prov.get(field_name)
        if isinstance(value, str) and Path(value).name in by_file:
            return by_file[Path(value).name]
    named = {by_file[Path(s).name] for s in _strings(prov) if Path(s).name in by_file}
    if len(named) == 1:
        return named.pop()
    made_on = prov.get("n_vertices")  # a table records the size of the mesh it was made on
    if made_on is not None:
        meshes = {k: m for k, m in meshes.items() if len(m.vertices) == int(made_on)}
        if not meshes:
            warnings.warn(f"not shown: {path} was computed on a mesh of {made_on} vertices, none of the "
                          "meshes given has that many (a table of another mesh)", NemoWarning, stacklevel=3)
            return None
    hint = {"whole": "mesh"}.get(hint, hint)  # workflow: curvature_whole -> mesh.ply
    if hint and hint in meshes:
        return hint
    vmax = int(df["vertex"].max()) if len(df) else -1
    order = [k for k in _MESH_PREFERENCE if k in meshes] + [k for k in meshes if k not in _MESH_PREFERENCE]
    if per_vertex:
        exact = [k for k in order if len(meshes[k].vertices) == len(df)]
        if exact:
            return exact[0]
    fits = [k for k in order if len(meshes[k].vertices) > vmax]
    if fits:
        return fits[0]
    warnings.warn(f"not shown: {path} refers to vertex {vmax}, beyond every mesh of the frame",
                  NemoWarning, stacklevel=3)
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
    from nemo.mesh import load_mesh

    ff = files if isinstance(files, FrameFiles) else discover_frame(files)
    meshes = {}
    for key, path in ff.meshes.items():
        try:
            mesh = load_mesh(path, manifold=False)  # show what is there
        except NemoError as exc:
            warnings.warn(f"not shown: {exc}", NemoWarning, stacklevel=2)
            continue
        mesh._nemo_file = path.name
        meshes[key] = mesh
    if not meshes:
        raise NemoError(f"no readable mesh among {', '.join(map(str, ff.meshes.values()))}")
    surfaces = {k: Surface(k, ff.meshes[k], m) for k, m in meshes.items()}

    def add(surface: str, name: str, kind: str, values: np.ndarray, src: Path) -> None:
        s = surfaces[surface]
        s.fields[name] = _fill_nearest(values, np.asarray(s.mesh.vertices))
        s.kinds[name] = kind
        s.sources[name] = src

    layers: dict[str, Layer] = {}
    for name in ff.layer_names():
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
                add(key, "intensity" + suffix, "intensity", layer.intensity, table[name])
            elif kind == "order":
                layer.order = _with_positions(df, verts)
                add(key, "S" + suffix, "S", _scatter(df, "S", len(verts)), table[name])
            else:
                layer.directors = _with_positions(df, verts)
        if not layer.surface:
            layer.surface = next(k for k in (*_MESH_PREFERENCE, *meshes) if k in meshes)
        layers[name] = layer

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
                    add(key, col, col, values, path)

    align, align_surface, align_suffix = {}, {}, {}
    for suffix, path in ff.align.items():
        df = _read(path, "align")
        if df is None:
            continue
        a, b = _split_pair(suffix, list(layers))
        key = layers[a].surface if a in layers else _pick_mesh(path, df, meshes, per_vertex=False)
        if key is None or (len(df) and int(df["vertex"].max()) >= len(meshes[key].vertices)):
            warnings.warn(f"not shown: {path} does not fit the mesh of layer {a}", NemoWarning,
                          stacklevel=2)
            continue
        verts = np.asarray(meshes[key].vertices)
        align[(a, b)] = _with_positions(df, verts)
        align_surface[(a, b)] = key
        align_suffix[(a, b)] = suffix
        add(key, f"c ({a}-{b})", "c", _scatter(df, "c", len(verts)), path)
    return Frame(ff, surfaces, layers, align, align_surface, align_suffix)


def _split_pair(suffix: str, layer_names: list[str]) -> tuple[str, str]:
    """Split ``"<a>_<b>"`` using the known layer names (names may contain underscores)."""
    for a in sorted(layer_names, key=len, reverse=True):
        if suffix.startswith(a + "_") and suffix[len(a) + 1:]:
            return a, suffix[len(a) + 1:]
    a, _, b = suffix.partition("_")
    return a, b or "?"


# --------------------------------------------------------------------------------------------
# geometry helpers


def surface_centre(mesh) -> np.ndarray:
    """Area-weighted centroid of a surface (the origin of the spherical maps), shape (3,)."""
    tri = np.asarray(mesh.vertices)[np.asarray(mesh.faces)]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    if area.sum() <= 0:
        return np.asarray(mesh.vertices).mean(axis=0)
    return (tri.mean(axis=1) * area[:, None]).sum(axis=0) / area.sum()


def spherical_angles(points: np.ndarray, centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Azimuth and polar angle of points around a centre, in degrees.

    Parameters
    ----------
    points : ndarray, shape (M, 3)
        Physical x, y, z.
    centre : ndarray, shape (3,)

    Returns
    -------
    azimuth : ndarray, shape (M,)
        atan2(y, x) in (-180, 180]: 0 along +x, 90 along +y.
    polar : ndarray, shape (M,)
        Angle from +z in [0, 180].
    """
    d = np.asarray(points, dtype=np.float64).reshape(-1, 3) - np.asarray(centre, dtype=np.float64)
    r = np.linalg.norm(d, axis=1)
    az = np.degrees(np.arctan2(d[:, 1], d[:, 0]))
    pol = np.degrees(np.arccos(np.clip(d[:, 2] / np.where(r > 0, r, 1.0), -1.0, 1.0)))
    return az, pol


def chart_directions(points: np.ndarray, vectors: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Tangent vectors as directions in the (azimuth, polar) chart, in degrees per unit.

    A tangent vector with components a along e_φ and b along e_θ moves the chart point by
    (a / (r sin θ), b / r) radians; returned normalised, shape (M, 2) (d azimuth, d polar).
    """
    d = np.asarray(points, dtype=np.float64) - centre
    r = np.linalg.norm(d, axis=1)
    phi = np.arctan2(d[:, 1], d[:, 0])
    theta = np.arccos(np.clip(d[:, 2] / np.where(r > 0, r, 1), -1, 1))
    e_phi = np.stack([-np.sin(phi), np.cos(phi), np.zeros_like(phi)], axis=1)
    e_theta = np.stack([np.cos(theta) * np.cos(phi), np.cos(theta) * np.sin(phi), -np.sin(theta)], axis=1)
    a = np.einsum("ij,ij->i", vectors, e_phi) / np.maximum(np.sin(theta), 1e-3)
    b = np.einsum("ij,ij->i", vectors, e_theta)
    uv = np.stack([a, b], axis=1)
    return uv / np.maximum(np.linalg.norm(uv, axis=1, keepdims=True), 1e-12)


def spherical_grid(vertices: np.ndarray, values: np.ndarray, centre: np.ndarray,
                   n_polar: int = 180) -> np.ndarray:
    """Resample a per-vertex field on a regular (polar, azimuth) grid.

    Each grid direction takes the value of the vertex whose direction from ``centre`` is
    nearest (exact for star-shaped surfaces; otherwise the first sheet hit is not guaranteed).

    Returns
    -------
    ndarray, shape (n_polar, 2 n_polar)
        Row i: polar angle (i + ½)·180/n_polar; column j: azimuth −180 + (j + ½)·180/n_polar.
    """
    n_az = 2 * n_polar
    pol = np.radians((np.arange(n_polar) + 0.5) * 180.0 / n_polar)
    az = np.radians(-180.0 + (np.arange(n_az) + 0.5) * 360.0 / n_az)
    P, A = np.meshgrid(pol, az, indexing="ij")
    grid = np.stack([np.sin(P) * np.cos(A), np.sin(P) * np.sin(A), np.cos(P)], axis=-1).reshape(-1, 3)
    d = np.asarray(vertices, dtype=np.float64) - centre
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    _, idx = cKDTree(d).query(grid)
    return np.asarray(values, dtype=np.float64)[idx].reshape(n_polar, n_az)


def subsample_even(points: np.ndarray, spacing: float) -> np.ndarray:
    """Indices of finite points thinned to about one per cube of side ``spacing`` (vectorised)."""
    ok = np.flatnonzero(np.isfinite(points).all(axis=1))
    if len(ok) == 0:
        return np.zeros(0, dtype=np.int64)
    p = points[ok]
    cells = np.floor((p - p.min(axis=0)) / spacing).astype(np.int64)
    _, idx = np.unique(cells, axis=0, return_index=True)
    return ok[np.sort(idx)]


def glyph_spacing(mesh, target: int = 1500) -> float:
    """Spacing of about ``target`` evenly spread glyphs on a surface: sqrt(area / target)."""
    return float(np.sqrt(max(float(mesh.area), 1e-12) / max(target, 1)))


#: Field kinds whose sign matters: diverging colour maps with limits symmetric about 0.
SIGNED_KINDS = ("H", "K", "k1", "k2")


def robust_limits(values: np.ndarray, kind: str = "") -> tuple[float, float]:
    """Colour limits of a field kind.

    Parameters
    ----------
    values : ndarray
        The field (NaN ignored).
    kind : str
        Field kind (:data:`FIELD_LABELS` key).

    Returns
    -------
    (lo, hi) : tuple of float
        Fixed for S [0, 1], alignment c and charge [−1, 1]. Curvatures (:data:`SIGNED_KINDS`,
        diverging maps) are symmetric about 0, ±(99th percentile of |value|) rounded up to a
        round number (so the colour-bar ticks ±m, ±m/2 read well), whatever the data: white is always 0, red always positive (convex with outward normals), blue always
        negative -- an all-positive sphere is uniformly red, never half blue. Other fields: the
        1--99 % range.
    """
    if kind == "S":
        return 0.0, 1.0
    if kind in ("c", "charge"):
        return -1.0, 1.0
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return (-1.0, 1.0) if kind in SIGNED_KINDS else (0.0, 1.0)
    if kind in SIGNED_KINDS:
        m = _nice_ceil(float(np.percentile(np.abs(v), 99)))
        return -m, m
    lo, hi = (float(x) for x in np.percentile(v, [1, 99]))
    if hi <= lo:
        pad = abs(lo) * 0.05 or 1.0
        lo, hi = lo - pad, hi + pad
    return lo, hi


def _nice_ceil(x: float) -> float:
    """The smallest of 1, 1.2, 1.5, 2, 2.5, 3, 4, 5, 6, 8 × 10^k that is ≥ x (1.0 for x ≤ 0)."""
    if not np.isfinite(x) or x <= 0:
        return 1.0
    k = np.floor(np.log10(x))
    for step_ in (1.0, 1.2, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0):
        if step_ * 10.0**k >= x * (1 - 1e-9):
            return float(step_ * 10.0**k)
    return float(10.0 ** (k + 1))


# --------------------------------------------------------------------------------------------
# pyvista renders


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
):
    """A two-view off-screen pyvista plotter of a surface (front and back).

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


# --------------------------------------------------------------------------------------------
# matplotlib figures


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

    cm = matplotlib.colormaps[name].copy()
    cm.set_bad("lightgrey")
    return cm


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


def spherical_figure(frame: Frame, layer: str, n_polar: int = 180, max_glyphs: int = 900):
    """Intensity + averaged directors + defects in spherical coordinates -- paper Fig. 2D.

    The chart is centred on the area-weighted centroid of the layer's surface. Directors are
    thinned evenly on the surface (about ``max_glyphs``) and coloured by S; defects are circles
    coloured by charge with the rounded charge as text.
    """
    lay = frame.layers[layer]
    surf = frame.surfaces[lay.surface]
    verts = np.asarray(surf.mesh.vertices)
    centre = surface_centre(surf.mesh)
    fig, (ax,) = _figure(1, 10.5, 5.0)
    if lay.intensity is not None:
        vals = _fill_nearest(lay.intensity, verts)
        _map_image(ax, verts, vals, centre, "gray", robust_limits(vals), field_label("intensity"),
                   fig, n_polar)
    else:
        _map_axes(ax)
    if lay.order is not None and len(lay.order):
        od = lay.order
        pos = od[["x", "y", "z"]].to_numpy(dtype=np.float64)
        keep = subsample_even(pos, glyph_spacing(surf.mesh, max_glyphs))
        od = od.iloc[keep]
        _chart_segments(ax, od[["x", "y", "z"]].to_numpy(float), od[["nx", "ny", "nz"]].to_numpy(float),
                        od["S"].to_numpy(float), centre, fig, length_deg=0.8 * 180 / np.sqrt(max_glyphs / 2))
    if lay.defects is not None and len(lay.defects):
        _chart_defects(ax, lay.defects[["x", "y", "z"]].to_numpy(float),
                       lay.defects["charge"].to_numpy(float), centre, fig)
    ax.set_title(f"layer {layer}: spherical coordinates around the centroid "
                 f"({centre[0]:.1f}, {centre[1]:.1f}, {centre[2]:.1f}) {_u(surf.unit)}", fontsize=10)
    return fig


def _u(unit: str) -> str:
    return "µm" if unit in ("um", "µm", "micron") else unit


def morphology_figure(surf: Surface, n_polar: int = 120):
    """Spherical maps of H, K and thickness (those present) on one surface, or None."""
    names = [n for n in ("H", "K", "thickness") if n in surf.fields]
    if not names:
        return None
    fig, axes = _figure(len(names), 6.2, 3.6)
    verts = np.asarray(surf.mesh.vertices)
    centre = surface_centre(surf.mesh)
    for ax, name in zip(axes, names):
        vals = surf.fields[name]
        _map_image(ax, verts, vals, centre, FIELD_CMAPS[name], robust_limits(vals, name),
                   surf.label(name), fig, n_polar)
        ax.set_title(f"{name} ({surf.key} surface)", fontsize=10)
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
    ax_h.hist(c, bins=np.linspace(-1, 1, 41), density=True, color="tab:purple", alpha=0.85)
    if c.size:
        ax_h.axvline(float(c.mean()), color="k", ls="--", lw=1)
    ax_h.set_xlim(-1, 1)
    ax_h.set_xlabel(field_label("c"))
    ax_h.set_ylabel("probability density")
    ax_h.set_title(f"mean c = {c.mean():+.2f} (n = {c.size})" if c.size else "no values", fontsize=10)
    return fig


def _defect_centres(df: pd.DataFrame, centres: dict | None) -> np.ndarray:
    """Per-row origin of the spherical coordinates: the frame's surface centroid from
    ``centres[(t, c)]``, else the mean position of that frame's defects. Shape (M, 3)."""
    xyz = df[["x", "y", "z"]].to_numpy(float)
    cs = df["c"].astype(int) if "c" in df.columns else pd.Series(0, index=df.index)
    keys = list(zip(df["t"].astype(int), cs))
    frame_mean = pd.DataFrame(xyz, columns=["x", "y", "z"]).assign(_k=keys).groupby("_k").mean()
    centres = centres or {}
    return np.array([centres[k] if k in centres else frame_mean.loc[[k]].to_numpy()[0]
                     for k in keys]).reshape(-1, 3)


def _layer_rows(defects: pd.DataFrame, layer: str | None) -> pd.DataFrame:
    df = defects
    if layer is not None and "layer" in df.columns:
        df = df[df["layer"].astype(str) == str(layer)]
    return df.sort_values(["track_id", "t"]) if len(df) and "track_id" in df.columns else df


def tracks_figure(defects: pd.DataFrame, layer: str | None = None,
                  centres: dict[tuple[int, int], np.ndarray] | None = None):
    """Defect tracks over time for one layer.

    Parameters
    ----------
    defects : DataFrame
        ``summary/defects.parquet``: ``t, c, layer, x, y, z, charge, track_id`` (rows of other
        layers are ignored when ``layer`` is given).
    layer : str, optional
    centres : dict (t, c) -> (3,), optional
        Surface centroid per frame; default the mean defect position of each frame.

    Returns
    -------
    matplotlib.figure.Figure
        Left: tracks in (azimuth, polar) with one colour per track; right: distance from the
        track's first position along the sphere of the mean radius, versus t.
    """
    import matplotlib
    from matplotlib.ticker import MaxNLocator

    df = _layer_rows(defects, layer)
    fig, (ax_m, ax_d) = _figure(2, 6.0, 3.8)
    fig.set_size_inches(13, 4.0)
    _map_axes(ax_m)
    ax_d.set_xlabel(field_label("t"))
    ax_d.set_ylabel("distance from first position [µm]")
    ax_d.xaxis.set_major_locator(MaxNLocator(integer=True))
    if not len(df):
        ax_m.set_title("no defects", fontsize=10)
        return fig
    rel = df[["x", "y", "z"]].to_numpy(float) - _defect_centres(df, centres)
    r = np.linalg.norm(rel, axis=1)
    az, pol = spherical_angles(rel, np.zeros(3))
    cmap = matplotlib.colormaps["tab10"]
    ids = df["track_id"].to_numpy()
    t = df["t"].to_numpy(float)
    for i, tid in enumerate(pd.unique(ids)):
        sel = ids == tid
        colour = cmap(i % 10)
        a, p_ = az[sel], pol[sel]
        for seg in _seam_segments(a):  # do not draw across the ±180° seam
            ax_m.plot(a[seg], p_[seg], "-", color=colour, lw=1.5)
        ax_m.scatter(a, p_, color=colour, s=18, zorder=4)
        q = float(np.nanmedian(df["charge"].to_numpy(float)[sel]))
        ax_m.annotate(f"{tid} ({charge_text(q)})", (a[-1], p_[-1]), xytext=(5, 5),
                      textcoords="offset points", fontsize=8, color=colour, zorder=6,
                      bbox={"boxstyle": "round,pad=0.1", "fc": "white", "alpha": 0.75, "lw": 0})
        u = rel[sel] / np.maximum(r[sel, None], 1e-12)
        ang = np.arccos(np.clip(u @ u[0], -1, 1))
        ax_d.plot(t[sel], ang * r[sel].mean(), "-o", color=colour, ms=3, label=f"{tid} ({charge_text(q)})")
    ax_m.set_title(f"defect tracks{'' if layer is None else f' (layer {layer})'}: "
                   f"{len(pd.unique(ids))} tracks over {len(np.unique(t))} frames", fontsize=10)
    if len(pd.unique(ids)) <= 12:
        ax_d.legend(fontsize=7, title="track (charge)", title_fontsize=7)
    return fig


def _seam_segments(lon_deg: np.ndarray) -> list[np.ndarray]:
    """Index runs of a track that do not jump across the ±180° longitude seam."""
    jumps = np.flatnonzero(np.abs(np.diff(lon_deg)) > 180) + 1
    return np.split(np.arange(len(lon_deg)), jumps)


def defect_lonlat(defects: pd.DataFrame, centres: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Longitude and latitude of defects around their frame's surface centroid, in degrees.

    Longitude is the azimuth φ = atan2(y, x) in (−180, 180]; latitude is 90° − θ (θ the polar
    angle from +z), so +z is the north pole. Origins as in :func:`tracks_figure`.
    """
    if not len(defects):
        return np.zeros(0), np.zeros(0)
    az, pol = spherical_angles(defects[["x", "y", "z"]].to_numpy(float) - _defect_centres(defects, centres),
                               np.zeros(3))
    return az, 90.0 - pol


#: Marker of a defect by the sign of its charge: ``+`` comet-like circle, ``−`` trefoil-like triangle.
_CHARGE_MARKERS = {1: ("o", "m > 0 (e.g. +½)"), -1: ("^", "m < 0 (e.g. −½)"), 0: ("s", "m ≈ 0")}


def _defect_map_points(ax, df: pd.DataFrame, lon: np.ndarray, lat: np.ndarray):
    """Scatter the defects of every frame on a Mollweide axis; returns the last collection."""
    from matplotlib.colors import TwoSlopeNorm

    q = df["charge"].to_numpy(float)
    t = df["t"].to_numpy(float)
    span = max(float(np.ptp(t)), 1.0) if len(t) else 1.0
    alpha = 0.35 + 0.65 * (t - (t.min() if len(t) else 0)) / span  # earlier frames fainter
    sign = np.where(q > 0.1, 1, np.where(q < -0.1, -1, 0))
    norm = TwoSlopeNorm(vcenter=0.0, vmin=-1.0, vmax=1.0)
    sc = None
    for s, (marker, _) in _CHARGE_MARKERS.items():
        sel = sign == s
        if not sel.any():
            continue
        last = t[sel] == t.max()
        sc = ax.scatter(np.radians(lon[sel]), np.radians(lat[sel]), c=q[sel], cmap="RdBu_r", norm=norm,
                        marker=marker, s=np.where(last, 70, 40), alpha=alpha[sel], edgecolors="k",
                        linewidths=np.where(last, 1.2, 0.5), zorder=5)
        sc.set_gid("defects")
    return sc, norm


def defect_map_figure(defects: pd.DataFrame, layer: str | None = None,
                      centres: dict[tuple[int, int], np.ndarray] | None = None):
    """Every frame's defects and the tracks of one layer on an equal-area world map.

    Parameters
    ----------
    defects : DataFrame
        ``summary/defects.parquet``: ``t, x, y, z, charge`` (+ ``c``, ``layer``, ``track_id``).
    layer : str, optional
        Only this layer's rows.
    centres : dict (t, c) -> (3,), optional
        Surface centroid per frame (default: each frame's mean defect position).

    Returns
    -------
    matplotlib.figure.Figure
        One Mollweide (equal-area) panel: longitude = azimuth φ about the centroid, latitude =
        90° − θ (north = +z); equal areas on the surface stay equal, so the poles are not
        stretched as in the (φ, θ) maps. Defects are coloured by charge m on a diverging map
        centred on 0 (red positive, blue negative) and shaped by sign (circle +, triangle −);
        earlier frames are fainter, the last frame has bold edges; grey lines join the
        positions of each track (``track_id``), never across the ±180° seam. Scatter
        collections have gid ``"defects"``; offsets are radians (lon, lat).
    """
    import matplotlib
    from matplotlib.cm import ScalarMappable
    from matplotlib.figure import Figure as MplFigure
    from matplotlib.lines import Line2D

    df = _layer_rows(defects, layer)
    fig = MplFigure(figsize=(11, 6.4), layout="constrained")
    ax = fig.add_subplot(projection="mollweide")
    ax.grid(True, color="0.75", lw=0.5)
    ax.tick_params(labelsize=8, colors="0.3")
    ax.set_xlabel("longitude φ (azimuth from +x towards +y) [°]")
    ax.set_ylabel("latitude 90° − θ (north = +z) [°]")
    name = "" if layer is None else f"layer {layer}: "
    lon, lat = defect_lonlat(df, centres)
    if "track_id" in df.columns:
        for tid in pd.unique(df["track_id"]):
            sel = (df["track_id"] == tid).to_numpy()
            for seg in _seam_segments(lon[sel]):
                ax.plot(np.radians(lon[sel][seg]), np.radians(lat[sel][seg]), "-", color="0.35",
                        lw=1.3, zorder=3)
    sc, norm = _defect_map_points(ax, df, lon, lat)
    cb = fig.colorbar(sc if sc is not None else ScalarMappable(norm, "RdBu_r"), ax=ax,
                      orientation="horizontal", shrink=0.45, pad=0.02, aspect=30)
    cb.set_label(field_label("charge") + " (0 = white)")
    cb.set_ticks([-1, -0.5, 0, 0.5, 1], labels=["−1", "−½", "0", "+½", "+1"])
    cmap = matplotlib.colormaps["RdBu_r"]
    handles = [Line2D([], [], ls="", marker=m, mfc=cmap(norm(0.5 * s)), mec="k", ms=8, label=lab)
               for s, (m, lab) in _CHARGE_MARKERS.items()
               if s != 0 or (len(df) and (np.abs(df["charge"].to_numpy(float)) <= 0.1).any())]
    handles.append(Line2D([], [], color="0.35", lw=1.3, label="track (same track_id)"))
    t = df["t"].to_numpy(int) if len(df) else np.zeros(0, int)
    if len(t):
        handles.append(Line2D([], [], ls="", marker="o", mfc="0.6", mec="k", mew=1.2, ms=8,
                              label=f"bold edge: last frame t = {t.max()}; fainter = earlier"))
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(0.0, -0.08), ncols=2, fontsize=8,
              frameon=False)
    n_tr = df["track_id"].nunique() if "track_id" in df.columns else 0
    ax.set_title(f"{name}{len(df)} defects in {len(np.unique(t))} frames"
                 f"{f' (t = {t.min()}–{t.max()})' if len(t) else ''}, {n_tr} tracks\n"
                 "equal-area map around the surface centroid", fontsize=11, pad=24)
    return fig


#: Largest |Σ charge − χ| that passes when frames.parquet has no ``qc_pass`` column (as in
#: :mod:`nemo.summary`): a missed or spurious ±½ defect changes the sum by 0.5.
QC_CHARGE_TOLERANCE = 0.25

#: Panels of :func:`frames_figure`: key, title, columns (column, line label), per ``layer`` or
#: per ``surface``, y label (``{u}`` the length unit) and the y-limits policy.
FRAME_PANELS: tuple[tuple, ...] = (
    ("S", "nematic order S", (("S_mean", "mean"), ("S_median", "median")), "layer", "S", "unit"),
    ("n_defects", "number of defects", (("n_defects", None),), "layer", "defects", "count"),
    ("charge", "Σ charge vs Euler characteristic χ", (("charge_sum", None),), "layer",
     "Σ charge m", "charge"),
    ("thickness", "wall thickness", (("thickness_mean", "mean"), ("thickness_median", "median")),
     "surface", "thickness [{u}]", "relative"),
    ("H", "mean curvature H", (("H_mean", "mesh mean"), ("H_fit_mean", "fit mean")), "surface",
     "H [1/{u}]", "relative"),
    ("area", "surface area", (("area", None),), "surface", "area [{u}²]", "relative"),
    ("volume", "enclosed volume", (("volume", None),), "surface", "volume [{u}³]", "relative"),
)
#: Smallest half-span of a ``relative`` panel, as a fraction of the mean.
RELATIVE_SPAN = 0.05
_STYLES = ("-", "--")
#: Line colours of the layers in :func:`frames_figure` (no green or red: those mean QC pass/fail).
LAYER_COLOURS = ("tab:blue", "tab:orange", "tab:purple", "tab:brown", "tab:pink", "tab:olive",
                 "tab:cyan", "tab:gray")
#: Line colours of the surfaces (dark, so they read apart from the layers).
SURFACE_COLOURS = ("black", "dimgray", "darkslateblue", "saddlebrown")
_LAYER_MARKERS = ("o", "s", "D", "^", "v", "P", "*", "h")


def frame_qc(frames: pd.DataFrame) -> pd.DataFrame:
    """``qc_pass`` (bool) and ``qc_flags`` (str, '; '-joined reasons) of each row.

    The table's own columns when present (:func:`nemo.summary.quality_flags`); otherwise a row
    with a layer fails when |charge_sum − euler_characteristic| > :data:`QC_CHARGE_TOLERANCE`
    or it has no defects.
    """
    out = pd.DataFrame(index=frames.index)
    if "qc_pass" in frames.columns:
        out["qc_pass"] = frames["qc_pass"].fillna(True).astype(bool)
        flags = frames["qc_flags"] if "qc_flags" in frames.columns else pd.Series("", index=frames.index)
        flags = flags.fillna("").astype(str)
        out["qc_flags"] = flags.where(out["qc_pass"] | (flags != ""), "failed quality control")
        return out
    reasons = []
    for _, row in frames.iterrows():
        r = []
        q, chi = row.get("charge_sum", np.nan), row.get("euler_characteristic", np.nan)
        if pd.notna(q) and pd.notna(chi) and abs(float(q) - float(chi)) > QC_CHARGE_TOLERANCE:
            r.append(f"Σ charge {round(float(q), 2) + 0.0:.2f} ≠ χ {float(chi):.0f}")
        has_layer = pd.notna(row.get("layer")) and str(row.get("layer", "")) != ""
        if has_layer and "n_defects" in row and pd.notna(row["n_defects"]) and int(row["n_defects"]) == 0:
            r.append("no defects")
        reasons.append("; ".join(r))
    out["qc_flags"] = reasons
    out["qc_pass"] = out["qc_flags"] == ""
    return out


def _frame_groups(frames: pd.DataFrame) -> tuple[dict, dict]:
    """(layer groups, surface groups): label -> rows sorted by t (surface rows deduplicated)."""
    multi_c = "c" in frames.columns and frames["c"].nunique() > 1

    def label(c, name, what):
        return f"{'c' + str(c) + ' ' if multi_c else ''}{what}{name}"

    cs = frames["c"] if "c" in frames.columns else pd.Series(0, index=frames.index)
    lay = frames["layer"].astype(str) if "layer" in frames.columns else pd.Series("", index=frames.index)
    layers = {label(c, L, "layer " if L else "all"): g.sort_values("t")
              for (c, L), g in frames.groupby([cs, lay], sort=True)}
    if "surface" not in frames.columns:
        return layers, layers
    surf = frames["surface"].astype(str)
    surfaces = {label(c, f"{S} surface", ""): g.sort_values("t").drop_duplicates("t")
                for (c, S), g in frames.groupby([cs, surf], sort=True)}
    return layers, surfaces


def _scale(values: np.ndarray) -> tuple[float, str]:
    """A factor 10^-3k that brings values ≥ 10⁴ to plain numbers, and its label prefix."""
    v = np.abs(values[np.isfinite(values)])
    if not v.size or v.max() < 1e4:
        return 1.0, ""
    k = int(np.floor(np.log10(v.max()) / 3) * 3)
    return 10.0 ** -k, f"10$^{{{k}}}$ "


def _panel_limits(policy: str, values: np.ndarray, chi: np.ndarray) -> tuple[float, float]:
    """y limits: ``unit`` [0, 1]; ``count`` [0, max + 1]; ``charge`` the charges and χ with at
    least ±1 about χ; ``relative`` the data range, at least ±:data:`RELATIVE_SPAN` × mean."""
    v = values[np.isfinite(values)]
    if policy == "unit":
        return 0.0, 1.0
    if policy == "count":
        return 0.0, float(v.max()) + 1 if v.size else 1.0
    if policy == "charge":
        ref = np.concatenate([v, chi[np.isfinite(chi)]])
        c = chi[np.isfinite(chi)]
        lo = min(ref.min(), c.min() - 1) if c.size else (ref.min() - 1 if ref.size else -1)
        hi = max(ref.max(), c.max() + 1) if c.size else (ref.max() + 1 if ref.size else 1)
        return float(lo) - 0.25, float(hi) + 0.25
    if not v.size:
        return 0.0, 1.0
    lo, hi = float(v.min()), float(v.max())
    half = max(RELATIVE_SPAN * abs(float(v.mean())), 0.6 * (hi - lo)) or 1.0
    mid = 0.5 * (lo + hi)
    return mid - half, mid + half


def _plot_panel(ax, spec: tuple, groups: dict, styles: dict, unit: str, qc: pd.DataFrame) -> bool:
    """Draw one :data:`FRAME_PANELS` entry; False when the table has none of its columns."""
    key, title, cols, _, ylabel, policy = spec
    cols = [(c, lab) for c, lab in cols if any(c in g.columns for g in groups.values())]
    ax.set_title(title, fontsize=10)
    if not cols:
        ax.text(0.5, 0.5, "not in frames.parquet", ha="center", va="center", color="0.5",
                transform=ax.transAxes)
        ax.set_yticks([])
        return False
    allv = np.concatenate([g[c].to_numpy(float) for g in groups.values() for c, _ in cols if c in g])
    factor, prefix = _scale(allv)
    chi = np.concatenate([np.zeros(0)] + [g["euler_characteristic"].to_numpy(float) for g in groups.values()
                                          if "euler_characteristic" in g and key == "charge"])
    for i, (name, g) in enumerate(groups.items()):
        # layers side by side (±0.04 in t) so that equal values stay visible
        t = g["t"].to_numpy(float) + 0.04 * (i - (len(groups) - 1) / 2) * (spec[3] == "layer")
        for (c, _), ls in zip(cols, _STYLES):
            if c in g:
                ax.plot(t, g[c].to_numpy(float) * factor, ls, marker=styles[name][1], ms=4.5,
                        color=styles[name][0])
        bad = ~qc.loc[g.index, "qc_pass"].to_numpy(bool)
        if spec[3] == "layer" and bad.any():
            ax.plot(t[bad], g[cols[0][0]].to_numpy(float)[bad] * factor, "x", color="red", ms=8, mew=1.8,
                    zorder=6)
    if key == "charge" and chi.size:
        _chi_reference(ax, groups)
    lo, hi = _panel_limits(policy, allv * factor, chi)
    ax.set_ylim(lo, hi)
    ax.set_ylabel(ylabel.replace("[", f"[{prefix}" if prefix else "[").replace("{u}", unit))
    if policy == "count":
        from matplotlib.ticker import MaxNLocator

        ax.yaxis.set_major_locator(MaxNLocator(integer=True))
    if len(cols) > 1:
        from matplotlib.lines import Line2D

        ax.legend(handles=[Line2D([], [], color="0.3", ls=ls, label=lab) for (_, lab), ls in zip(cols, _STYLES)],
                  fontsize=7, loc="lower right", framealpha=0.7)
    return True


def _chi_reference(ax, groups: dict) -> None:
    """χ per frame as a black dashed line with the ±tolerance band of quality control."""
    rows = pd.concat([g[["t", "euler_characteristic"]] for g in groups.values()
                      if "euler_characteristic" in g]).drop_duplicates().sort_values("t")
    t, chi = rows["t"].to_numpy(float), rows["euler_characteristic"].to_numpy(float)
    ax.fill_between(t, chi - QC_CHARGE_TOLERANCE, chi + QC_CHARGE_TOLERANCE, color="0.88", zorder=0,
                    step="mid" if len(t) > 1 else None)
    ax.plot(t, chi, "k--", marker="_", ms=14, lw=1.2, zorder=4)


def _qc_strip(ax, groups: dict, styles: dict, qc: pd.DataFrame) -> list[str]:
    """One row of pass (green ●) / fail (red ✕) markers per layer; returns the reasons."""
    reasons = []
    names = list(groups)
    for i, name in enumerate(names):
        g = groups[name]
        ok = qc.loc[g.index, "qc_pass"].to_numpy(bool)
        t = g["t"].to_numpy(float)
        ax.plot(t[ok], np.full(ok.sum(), i), "o", color="tab:green", ms=9)
        ax.plot(t[~ok], np.full((~ok).sum(), i), "X", color="red", ms=11)
        for tt, why in zip(t[~ok], qc.loc[g.index, "qc_flags"].to_numpy(str)[~ok]):
            reasons.append((tt, i, f"t = {tt:.0f}, {name}: {why}"))
    ax.set_yticks(range(len(names)), names, fontsize=9)
    for lab, name in zip(ax.get_yticklabels(), names):
        lab.set_color(styles[name][0])
    ax.set_ylim(len(names) - 0.5, -0.5)
    ax.set_title("quality control per frame (green ● pass, red ✕ flagged; flagged frames shaded "
                 "red in every panel)", fontsize=10)
    return [text for *_, text in sorted(reasons)]


def _frames_legend(ax, styles: dict, has_chi: bool) -> None:
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    ax.axis("off")
    h = [Line2D([], [], color=c, marker=m, ms=5, label=n) for n, (c, m) in styles.items()]
    if has_chi:
        h.append(Line2D([], [], color="k", ls="--", marker="_", ms=12, label="χ (Euler characteristic)"))
        h.append(Patch(color="0.88", label=f"χ ± {QC_CHARGE_TOLERANCE} (QC tolerance)"))
    h.append(Line2D([], [], ls="", marker="x", color="red", ms=10, mew=2, label="flagged frame (layer)"))
    h.append(Patch(color="red", alpha=0.15, label="t with a QC flag"))
    ax.legend(handles=h, loc="center", fontsize=9, frameon=False)


def frames_figure(frames: pd.DataFrame, unit: str = "um", title: str = ""):
    """Per-frame summary of a time-lapse for a biophysicist, with quality control.

    Parameters
    ----------
    frames : DataFrame
        ``summary/frames.parquet`` (:data:`nemo.summary.FRAME_COLUMNS`; missing columns give
        an empty panel). ``mean_S`` is read as ``S_mean``.
    unit : str
        Length unit of the table (its provenance ``unit``; ``"um"`` shown as µm).
    title : str
        Figure title (e.g. the dataset).

    Returns
    -------
    matplotlib.figure.Figure or None
        None without a ``t`` column. Panels (:data:`FRAME_PANELS`) versus integer t: S
        (mean solid, median dashed; 0–1), number of defects (from 0), Σ charge with χ as a
        dashed reference and the ±0.25 QC band, per layer (one colour per channel and layer);
        thickness, mean curvature H, area and volume per surface (deduplicated over layers).
        Y limits never use an offset or scientific notation: values ≥ 10⁴ are scaled by 10³ᵏ
        stated in the label, and each morphology panel spans at least ±5 % of its mean
        (:data:`RELATIVE_SPAN`), so numerical noise of 0.01 % looks flat while a real change
        of a few percent shows. A bottom strip marks each layer's frames as passing or
        flagged (:func:`frame_qc`) and lists the reasons; flagged t are shaded red everywhere.
    """
    from matplotlib.figure import Figure as MplFigure
    from matplotlib.ticker import MaxNLocator

    if "t" not in frames.columns or not len(frames):
        return None
    if "S_mean" not in frames.columns and "mean_S" in frames.columns:
        frames = frames.rename(columns={"mean_S": "S_mean"})
    frames = frames.reset_index(drop=True)
    qc = frame_qc(frames)
    layers, surfaces = _frame_groups(frames)
    styles = {n: (LAYER_COLOURS[i % len(LAYER_COLOURS)], _LAYER_MARKERS[i % len(_LAYER_MARKERS)])
              for i, n in enumerate(layers)}
    styles.update({n: (SURFACE_COLOURS[i % len(SURFACE_COLOURS)], "o")
                   for i, n in enumerate(s for s in surfaces if s not in layers)})
    bad_t = sorted(set(frames.loc[~qc["qc_pass"], "t"].astype(int)))
    n_lines = max(1, len(bad_t) and int((~qc["qc_pass"]).sum()))
    fig = MplFigure(figsize=(16, 8.6 + 0.3 * len(layers) + 0.2 * min(n_lines, 12)), layout="constrained")
    gs = fig.add_gridspec(4, 4, height_ratios=[3, 3, 0.5 + 0.35 * len(layers), 0.3 + 0.22 * min(n_lines, 13)])
    axes = [fig.add_subplot(gs[i // 4, i % 4]) for i in (0, 1, 2, 4, 5, 6, 7)]
    t_all = np.unique(frames["t"].to_numpy(int))
    for ax, spec in zip(axes, FRAME_PANELS):
        _plot_panel(ax, spec, layers if spec[3] == "layer" else surfaces, styles, _u(unit), qc)
    ax_qc = fig.add_subplot(gs[2, :], sharex=axes[0])
    reasons = _qc_strip(ax_qc, layers, styles, qc)
    for ax in [*axes, ax_qc]:
        for t in bad_t:
            ax.axvspan(t - 0.5, t + 0.5, color="red", alpha=0.12, lw=0, zorder=0)
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.set_xlim(t_all.min() - 0.5, t_all.max() + 0.5)
        ax.ticklabel_format(axis="y", style="plain", useOffset=False) if ax is not ax_qc else None
        ax.grid(True, axis="y", color="0.9", lw=0.6)
        ax.set_xlabel(field_label("t"))
    _frames_legend(fig.add_subplot(gs[0, 3]), styles, "euler_characteristic" in frames)
    _reasons_text(fig.add_subplot(gs[3, :]), reasons)
    fig.suptitle(title or "per-frame summary", fontsize=13)
    return fig


def _reasons_text(ax, reasons: list[str], max_lines: int = 12) -> None:
    ax.axis("off")
    if not reasons:
        ax.text(0, 1, "All frames pass quality control.", va="top", fontsize=10, color="tab:green",
                transform=ax.transAxes)
        return
    lines = reasons[:max_lines] + ([f"… and {len(reasons) - max_lines} more (frames.parquet qc_flags)"]
                                   if len(reasons) > max_lines else [])
    ax.text(0, 1, "Flagged frames:\n" + "\n".join(lines), va="top", fontsize=9, color="darkred",
            transform=ax.transAxes, linespacing=1.3)


# --------------------------------------------------------------------------------------------
# per-frame and summary drivers


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
        prov = _provenance(p)
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

    def done(path: Path, kind: str, sources, **nm) -> None:
        figs.append(Figure(path, kind, caption(kind, **nm), [str(s) for s in sources], nm))

    with step(f"rendering figures of t={ff.t} c={ff.c} into {outdir}"):
        for L in names:
            lay = frame.layers[L]
            surf = frame.surfaces[lay.surface]
            mesh = surf.mesh
            src = list(lay.sources.values()) + [surf.path]
            nm = {"layer": L, "surface": lay.surface}
            if surface_renders and lay.intensity is not None:
                done(render_surface(outdir / f"surface_intensity_{L}.png", mesh, scalars=lay.intensity,
                                    label=field_label("intensity"), cmap="gray",
                                    clim=robust_limits(lay.intensity),
                                    title=f"t={ff.t} c={ff.c} layer {L}: intensity"),
                     "surface_intensity", src, **nm)
            if surface_renders and lay.order is not None:
                od = lay.order
                pos = od[["x", "y", "z"]].to_numpy(float)
                keep = subsample_even(pos, glyph_spacing(mesh))
                done(render_surface(outdir / f"surface_order_{L}.png", mesh,
                                    scalars=surf.fields.get(f"S ({L})"), label=field_label("S"),
                                    cmap="viridis", clim=(0, 1),
                                    segments=(pos[keep], od[["nx", "ny", "nz"]].to_numpy(float)[keep],
                                              od["S"].to_numpy(float)[keep]),
                                    title=f"t={ff.t} c={ff.c} layer {L}: S and n_avg"),
                     "surface_order", src, **nm)
            if surface_renders and lay.defects is not None:
                d = lay.defects
                done(render_surface(outdir / f"surface_defects_{L}.png", mesh, scalars=lay.intensity,
                                    label=field_label("intensity") if lay.intensity is not None else "",
                                    cmap="gray", clim=robust_limits(lay.intensity)
                                    if lay.intensity is not None else None,
                                    defects=(d[["x", "y", "z"]].to_numpy(float), d["charge"].to_numpy(float)),
                                    title=f"t={ff.t} c={ff.c} layer {L}: {len(d)} defects"),
                     "surface_defects", src, **nm)
            if lay.order is not None or lay.defects is not None:
                S = surf.fields.get(f"S ({L})", np.zeros(0)) if lay.order is not None else np.zeros(0)
                q = lay.defects["charge"].to_numpy(float) if lay.defects is not None else np.zeros(0)
                done(save_figure(distributions_figure(S, q, f"t={ff.t} c={ff.c} layer {L}"),
                                 outdir / f"distributions_{L}.png"), "distributions", src, **nm)
            done(save_figure(spherical_figure(frame, L), outdir / f"spherical_{L}.png"),
                 "spherical", src, **nm)

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
                    done(render_surface(outdir / f"surface_{col}{sfx}.png", surf.mesh, scalars=vals,
                                        label=surf.label(col), cmap=FIELD_CMAPS[col],
                                        clim=robust_limits(vals, col),
                                        title=f"t={ff.t} c={ff.c} {col} ({surf.key})"),
                         f"surface_{col}", [path, surf.path], surface=surf.key)
        for sfx, (surf, src) in sorted(morph.items()):
            fig = morphology_figure(surf)
            if fig is not None:
                done(save_figure(fig, outdir / f"morphology_map{sfx}.png"), "morphology_map",
                     sorted(set(src)), surface=surf.key)

        for pair, suffix in frame.align_suffix.items():
            path = ff.align[suffix]
            done(save_figure(alignment_figure(frame, pair), outdir / f"alignment_{suffix}.png"),
                 "alignment", [path], a=pair[0], b=pair[1])
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


def _frame_centres(dataset_dir: Path) -> dict[tuple[int, int], np.ndarray]:
    from nemo.mesh import load_mesh

    centres = {}
    try:
        tree = find_frames(dataset_dir)
    except NemoError:
        return centres
    for key, d in tree.frames.items():
        ff = discover_frame(d)
        mkey = next((k for k in (*_MESH_PREFERENCE, *ff.meshes) if k in ff.meshes), None)
        try:
            centres[key] = surface_centre(load_mesh(ff.meshes[mkey], manifold=False))
        except NemoError:
            continue
    return centres


def _table_unit(*paths: Path) -> str:
    """The length unit recorded in the provenance of the first table that has one (else µm)."""
    for path in paths:
        unit = _provenance(path).get("unit")
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
