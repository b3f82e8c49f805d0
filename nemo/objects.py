"""Several objects in one frame: per-vertex object labels, and each step run object by object.

With ``mesh.keep: all`` the mesh step keeps every object of the image (:func:`nemo.surface.find_objects`:
separate surfaces, not nested in each other) and labels every vertex of its meshes with its
object in the vertex field ``object`` (0 = the largest by area, 1 = the next, ...; saved in the
PLY). The steps then analyse each object on its own: curvature fits, director patches, the
averaging discs and the defect search never reach across objects, and every data-derived
default (patch radius, averaging radius, curvature radius) follows the object's own size.

Every vertex-keyed table gets an ``object`` column, the defects table too; a step's resolved
parameters are those of object 0 with ``objects``, the list of each object's. The summary has
one row per object (``frames.parquet``'s ``object`` column). A mesh without the field (one
object, ``keep: largest``, a user's surface) runs as before, with ``object`` 0.

Object labels are area ranks within a frame: the same object can change rank between frames
when objects have similar sizes (``frames.parquet`` gives each object's centre to match them).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd
import trimesh

from nemo.errors import NemoError

#: Name of the per-vertex object label (a vertex field of the meshes, a column of the tables).
OBJECT_FIELD = "object"


@dataclass(frozen=True)
class Part:
    """One object of a labelled mesh."""

    label: int
    mesh: trimesh.Trimesh
    vertices: np.ndarray  # (n,) indices of the part's vertices in the whole mesh, in local order


def vertex_labels(mesh: trimesh.Trimesh) -> np.ndarray:
    """The object of every vertex, shape (N,) int64 (all 0 when the mesh has no labels)."""
    values = mesh.vertex_attributes.get(OBJECT_FIELD)
    if values is None:
        return np.zeros(len(mesh.vertices), dtype=np.int64)
    labels = np.asarray(values, dtype=np.float64)
    if labels.shape != (len(mesh.vertices),) or not np.isfinite(labels).all() or (labels < 0).any():
        raise NemoError(f"the mesh's '{OBJECT_FIELD}' vertex field is not one non-negative label per vertex: "
                        "remake the mesh with `nemo mesh`")
    return np.rint(labels).astype(np.int64)


def set_labels(mesh: trimesh.Trimesh, labels: np.ndarray) -> trimesh.Trimesh:
    """Store per-vertex object labels (shape (N,)) in ``mesh`` (in place) and return it."""
    mesh.vertex_attributes[OBJECT_FIELD] = np.asarray(labels, dtype=np.float64)
    return mesh


def labelled(mesh: trimesh.Trimesh) -> bool:
    """The mesh carries object labels (made with ``mesh.keep: all`` from several objects)."""
    return OBJECT_FIELD in mesh.vertex_attributes


def parts(mesh: trimesh.Trimesh) -> list[Part] | None:
    """The objects of a labelled mesh as sub-meshes, or None when it has no labels.

    A labelled surface may hold a single object (e.g. the inner walls when the other objects
    are droplets): it still gets its label.

    Returns
    -------
    list of Part or None
        Sorted by label; each part's mesh keeps the unit, metadata and vertex fields except the
        labels (a part is one object).
    """
    from nemo.surface import submesh

    if not labelled(mesh):
        return None
    labels = vertex_labels(mesh)
    present = np.unique(labels)
    faces = np.asarray(mesh.faces)
    face_label = labels[faces[:, 0]]
    if (labels[faces] != face_label[:, None]).any():
        raise NemoError("a face of the mesh joins two objects: the 'object' vertex field does not follow the "
                        "mesh's connected pieces; remake the mesh with `nemo mesh`")
    out = []
    for label in present:  # a loop over objects (a handful), not over vertices
        sub = submesh(mesh, np.flatnonzero(face_label == label))
        sub.vertex_attributes.pop(OBJECT_FIELD, None)
        vertices = np.asarray(sub.metadata.pop("parent_vertices"))
        sub.metadata.pop("parent_faces", None)
        sub.metadata.update({k: v for k, v in mesh.metadata.items() if k not in ("parent_faces", "parent_vertices")})
        out.append(Part(int(label), sub, vertices))
    if sum(len(p.vertices) for p in out) != len(mesh.vertices):
        raise NemoError("the mesh has vertices outside every face: remake the mesh with `nemo mesh`")
    return out


def local_table(df: pd.DataFrame, part: Part) -> pd.DataFrame:
    """The rows of a whole-mesh vertex-keyed table that belong to ``part``, re-keyed to its vertices."""
    index = np.full(int(max(part.vertices.max(), df["vertex"].max() if len(df) else 0)) + 1, -1, dtype=np.int64)
    index[part.vertices] = np.arange(len(part.vertices))
    local = index[df["vertex"].to_numpy(dtype=np.int64)]
    out = df[local >= 0].copy()
    out["vertex"] = local[local >= 0]
    return out.drop(columns=[OBJECT_FIELD], errors="ignore").reset_index(drop=True)


def global_table(df: pd.DataFrame, part: Part) -> pd.DataFrame:
    """A part's vertex-keyed table re-keyed to the whole mesh, with the ``object`` column."""
    out = df.copy()
    out["vertex"] = part.vertices[out["vertex"].to_numpy(dtype=np.int64)] if len(out) else out["vertex"]
    return with_object(out, part.label)


def with_object(df: pd.DataFrame, labels: int | np.ndarray) -> pd.DataFrame:
    """``df`` with an ``object`` column right after ``vertex`` (a label, or per-vertex labels by ``vertex``)."""
    out = df.drop(columns=[OBJECT_FIELD], errors="ignore")
    value = (np.full(len(out), labels, dtype=np.int64) if np.ndim(labels) == 0
             else np.asarray(labels, dtype=np.int64)[out["vertex"].to_numpy(dtype=np.int64)])
    out.insert(int(out.columns.get_loc("vertex")) + 1 if "vertex" in out.columns else 0, OBJECT_FIELD, value)
    return out


def combine_tables(tables: Sequence[pd.DataFrame], all_parts: Sequence[Part], sort: bool = True) -> pd.DataFrame:
    """One whole-mesh table from the parts' tables (sorted by vertex unless ``sort`` is False)."""
    pieces = [global_table(df, part) for df, part in zip(tables, all_parts)]
    out = pd.concat([p for p in pieces if len(p)] or pieces[:1], ignore_index=True)
    if sort:
        out = out.sort_values("vertex", kind="stable").reset_index(drop=True)
    return out


def combine_params(params: Sequence[dict], all_parts: Sequence[Part]) -> dict:
    """Resolved parameters of several objects: the first analysed object's (one not ``skipped``),
    with ``objects`` = each object's (with its label)."""
    out = dict(next((p for p in params if not p.get("skipped")), params[0]))
    out["objects"] = [dict(p, object=part.label) for p, part in zip(params, all_parts)]
    return out


def pick(params: dict | None, k: int) -> dict | None:
    """Object ``k``'s parameters from a record of :func:`combine_params` (a plain record as is)."""
    if params and params.get("objects"):
        return params["objects"][k]
    return params


def value_for(value, k: int):
    """Object ``k``'s entry of a per-object list (a scalar as is)."""
    return value[k] if isinstance(value, (list, tuple)) else value


def values(params: dict | None, key: str):
    """``params[key]`` for every object (a list) when ``params`` has ``objects``, else ``params[key]``."""
    if not params:
        return None
    if params.get("objects"):
        return [p.get(key) for p in params["objects"]]
    return params.get(key)


def concatenate(meshes: Sequence[trimesh.Trimesh], labels: Sequence[int]) -> trimesh.Trimesh:
    """One mesh of several objects' meshes, every vertex labelled with its object.

    Vertex fields present in every mesh are kept; unit and metadata come from the first mesh.
    """
    metadata = {k: v for k, v in meshes[0].metadata.items() if k not in ("parent_faces", "parent_vertices")}
    out = trimesh.util.concatenate(list(meshes))  # vertices in order, shared vertex fields and unit kept
    out.metadata.clear()
    out.metadata.update(metadata)
    out.vertex_attributes.pop(OBJECT_FIELD, None)
    sizes = [len(m.vertices) for m in meshes]
    return set_labels(out, np.repeat(np.asarray(labels, dtype=np.int64), sizes))


def object_meshes(whole: trimesh.Trimesh, found: Sequence[dict]) -> list[trimesh.Trimesh]:
    """Each object of ``found`` (:func:`nemo.surface.find_objects`) with the surfaces nested in it."""
    from nemo.surface import objects_with_nested  # the same nesting test as find_objects

    return objects_with_nested(whole, [o["components"] for o in found])


def split_objects(pieces: Sequence[trimesh.Trimesh], by: str, axis, walls: Sequence[int] | None = None,
                  centres: Sequence[np.ndarray | None] | None = None) -> dict[str, trimesh.Trimesh]:
    """``whole``, ``inner`` and ``outer`` meshes of several objects, each split about its own centre.

    Parameters
    ----------
    pieces : sequence of trimesh.Trimesh
        The objects (:func:`object_meshes`), largest first: object ``k`` is ``pieces[k]``.
    by, axis
        The split (``mesh.split``, ``mesh.axis``; :func:`nemo.surface.split_mesh`).
    walls : sequence of int, optional
        Each object's walls as found by ``split: auto`` (:func:`nemo.surface.count_walls`): an
        object with one is not split, its ``inner`` and ``outer`` are its whole surface.
    centres : sequence of (3,) arrays or None, optional
        Each object's split centre for ``by="centre"`` (None: its centroid).

    Returns
    -------
    dict
        Labelled meshes. Each object's walls are the largest piece of each half; an object with
        one wall (a droplet) has no inner wall and is left out of ``inner`` (a warning says so),
        unless ``walls`` says it has one.

    Raises
    ------
    NemoError
        No object has two walls.
    """
    import warnings

    from nemo._log import logger
    from nemo.errors import NemoWarning
    from nemo.surface import split_mesh

    inner, outer, labels = [], [], []
    for k, piece in enumerate(pieces):  # a loop over objects
        if walls is not None and walls[k] == 1:
            inner.append(piece)
            outer.append(piece)
            labels.append(k)
            continue
        try:
            i, o = split_mesh(piece, by=by, axis=axis, keep="largest", centre=None if centres is None else centres[k])
        except NemoError as exc:
            warnings.warn(f"object {k} is not split into walls ({exc}); it is left out of the inner and outer "
                          "surfaces", NemoWarning, stacklevel=2)
            continue
        inner.append(i)
        outer.append(o)
        labels.append(k)
    if not labels:
        raise NemoError("no object of the image has an inner and an outer wall: set `split` auto or none "
                        "(config mesh.split) to analyse each object's surface")
    two = len(labels) if walls is None else sum(w == 2 for w in walls)
    logger.info("split %d of %d objects into inner and outer walls, each about its own centre%s", two, len(pieces),
                "" if walls is None else f" ({len(pieces) - two} of one wall: inner and outer are its whole surface)")
    return {"whole": concatenate(pieces, range(len(pieces))), "inner": concatenate(inner, labels),
            "outer": concatenate(outer, labels)}
