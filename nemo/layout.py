"""The results layout: folder and file names shared by the workflow, ``nemo run``, ``nemo render``
and the napari reader.

One frame (time point ``t``, channel ``c``) of a dataset lives in ``{results}/{dataset}/t{t}/c{c}/``;
the meshes and morphology of a time point in the folder of the segmented channel; the summaries
of a dataset in ``{results}/{dataset}/summary/``. ``nemo run -o OUTDIR`` writes one frame's files
under the same names into OUTDIR.

The second part finds these files again: :func:`discover_frame` classifies the files of one
frame folder (or an explicit list of files) by name, :func:`find_frames` lists the frames of a
results tree (``nemo render``, ``nemo view``, the napari reader).
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path

from nemo._log import logger
from nemo.errors import NemoError

#: Mesh file of each surface.
MESH = {"whole": "mesh.ply", "inner": "mesh.inner.ply", "outer": "mesh.outer.ply"}
#: Per-layer tables, in the order of the analysis.
LAYER_KINDS = ("layer", "directors", "order", "defects")
THICKNESS = "thickness.parquet"
#: One frame deconvolved by the dataset's PSF (``nemo deconvolve``; the workflow keeps it for its
#: mesh and peel rules).
DECONVOLVED = "deconvolved.tif"
SUMMARY_JSON = "summary.json"
#: Per-dataset folders below ``{results}/{dataset}``.
SUMMARY_DIR, LOG_DIR, BENCH_DIR = "summary", "logs", "benchmarks"
#: Summary tables of a dataset.
SUMMARY_TABLES = ("frames.parquet", "defects.parquet", "tracks.parquet", "alignment.parquet")
UNTRACKED_DEFECTS = "defects_untracked.parquet"


def frame_dir(results: str, dataset: str, t: int | str, c: int | str) -> str:
    """``{results}/{dataset}/t{t}/c{c}`` (wildcard strings such as ``"{t}"`` are kept)."""
    return f"{results.rstrip('/')}/{dataset}/t{t}/c{c}"


def dataset_dir(results: str, dataset: str, sub: str = "") -> str:
    """``{results}/{dataset}`` or a folder below it (``summary``, ``logs``, ``benchmarks``)."""
    return f"{results.rstrip('/')}/{dataset}" + (f"/{sub}" if sub else "")


def measure_file(surface: str) -> str:
    return f"measure_{surface}.json"


def curvature_file(surface: str) -> str:
    return f"curvature_{surface}.parquet"


def layer_file(kind: str, layer: str) -> str:
    """``{kind}_{layer}.parquet`` for kind in :data:`LAYER_KINDS`."""
    return f"{kind}_{layer}.parquet"


def frame_record(sections: dict, t: int, c: int, layer: str, morphology_dir: str, layer_dir: str | None = None,
                 surface: str | None = None) -> dict:
    """The files of one frame and layer that :func:`nemo.summary.frame_summary` reads.

    ``sections`` is the analysis (:func:`nemo.config.analysis`); ``morphology_dir`` the folder of
    the segmented channel's meshes, measures, curvature and thickness, ``layer_dir`` that of the
    layer's tables. ``layer`` "" is a morphology-only record of ``surface``. The workflow's
    aggregation rules and ``nemo run`` build their records here, so they summarise alike.
    """
    if layer:
        surface = sections["layers"][layer]["surface"]
    thick = sections["thickness"] is not None and sections["thickness"]["from"] == surface
    record = {"t": t, "c": c, "layer": layer, "surface": surface,
              "measure": f"{morphology_dir}/{measure_file(surface)}",
              "curvature": (f"{morphology_dir}/{curvature_file(surface)}" if sections["curvature"] is not None
                            else None),
              "thickness": f"{morphology_dir}/{THICKNESS}" if thick else None}
    if layer:
        imported = bool(sections["layers"][layer].get("directors_from"))  # no layer table
        record.update({"layer_table" if k == "layer" else k: f"{layer_dir}/{layer_file(k, layer)}"
                       for k in LAYER_KINDS if k != "layer" or not imported})
    return record


def refined_file(layer: str) -> str:
    """The refinement directors measured near each defect of a layer."""
    return f"refined_{layer}.parquet"


def align_file(a: str, b: str) -> str:
    return f"align_{a}_{b}.parquet"


# ============================================================================================
# Results discovery (moved here from nemo.render): which files of a folder belong to a frame,
# and which frames a results tree holds. Used by ``nemo render``, ``nemo view`` and the napari
# reader; stdlib only at import (the Parquet provenance is read lazily).

_MESH_PREFIX = re.compile(r"^mesh[._-]?")
_TABLE = re.compile(  # the per-frame tables above (named, or unnamed single files)
    rf"^(?P<kind>{'|'.join((*LAYER_KINDS, 'curvature', 'thickness', 'align'))})(?:[._-](?P<name>.+))?$"
)
_FRAME_DIR = re.compile(r"^t(\d+)$")
_CHANNEL_DIR = re.compile(r"^c(\d+)$")
#: Name given to the layer of the single-frame ``nemo run`` files (``layer.parquet`` ...).
DEFAULT_LAYER = "layer"
#: Preference when a table fits several meshes (paper: layers live on the inner mesh).
MESH_PREFERENCE = ("inner", "mesh", "outer")


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


def provenance_strings(obj) -> list[str]:
    """Every string in a nested dict/list/tuple (the file names in a table's provenance)."""
    if isinstance(obj, str):
        return [obj]
    if isinstance(obj, dict):
        return [s for v in obj.values() for s in provenance_strings(v)]
    if isinstance(obj, (list, tuple)):
        return [s for v in obj for s in provenance_strings(v)]
    return []


def table_provenance(path: Path) -> dict:
    """A table's provenance (:func:`nemo.tables.read_provenance`); ``{}`` when unreadable."""
    from nemo.errors import NemoError
    from nemo.tables import read_provenance

    try:
        return read_provenance(path)
    except (NemoError, OSError, ValueError):  # a convenience: a mesh, a foreign or broken file has none
        return {}


def _find_image(ff: FrameFiles) -> Path | None:
    """The frame's hyperstack: a TIFF named in a table's provenance, else one beside it."""
    roots = [Path.cwd()]
    if ff.path is not None:
        roots += [ff.path, *ff.path.resolve().parents]
    for table in list(ff.layers.values()) + ff.tables():
        for s in provenance_strings(table_provenance(table)):
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


def _run_frame(folder: Path) -> tuple[int, int]:
    """(t, c) of a ``nemo run`` folder, from its ``summary.json`` ((0, 0) without one)."""
    import json

    try:
        summary = json.loads((folder / SUMMARY_JSON).read_text())
        return int(summary.get("t") or 0), int(summary.get("c") or 0)
    except (OSError, ValueError, TypeError, AttributeError):
        return 0, 0


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
        key = (t or 0, c or 0) if c is not None and t is not None else _run_frame(root)
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


def surface_mesh_path(pattern: str, t: int) -> str:
    """The surface file of time point ``t`` (``{t}`` in a dataset's ``surface_mesh``)."""
    from nemo.errors import NemoError

    try:
        return pattern.format(t=t)
    except (KeyError, IndexError, ValueError):
        raise NemoError(f"surface_mesh {pattern!r}: the only placeholder it may hold is {{t}}") from None
