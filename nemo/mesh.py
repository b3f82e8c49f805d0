"""Surface meshes: the container, PLY/OBJ input and output, and validation.

A NEMO surface is a :class:`trimesh.Trimesh` whose vertices are physical ``(x, y, z)``
coordinates (x = image column, y = row, z = plane, in the image's unit, usually µm) and whose
faces are wound so that ``mesh.vertex_normals`` point **outward**. Two trimesh attributes make
it the container the rest of NEMO uses:

* ``mesh.units`` -- the physical unit (``"um"``), written into the PLY header as a comment;
* ``mesh.metadata["spacing"]`` -- ``(dz, dy, dx)`` of the image the mesh was reconstructed
  from (a PLY header comment), so later steps can check they read the same image;
* ``mesh.vertex_attributes`` -- per-vertex fields (``(N,)`` float arrays), written as extra
  PLY vertex properties and read back; a name starting with ``_`` is private to a run (e.g.
  :data:`nemo.surface.CLOSED_SURFACE_FIELD`) and not written.

Meshes edited elsewhere (MeshLab, Blender) come back through :func:`load_mesh`.
"""

from __future__ import annotations

import json
import os
import re
import warnings
from pathlib import Path

import numpy as np
import trimesh

from nemo.atomic import atomic_path
from nemo.errors import NemoError, NemoWarning

_UNIT_COMMENT = re.compile(rb"comment nemo unit (\S+)")
_SPACING_COMMENT = re.compile(rb"comment nemo spacing (\S+) (\S+) (\S+)")
_PARAMS_COMMENT = re.compile(rb"\ncomment nemo params ([^\n]*)")
_XYZ = ("x", "y", "z")
_PLY_SKIP = {"x", "y", "z", "nx", "ny", "nz", "red", "green", "blue", "alpha"}


def make_mesh(
    vertices: np.ndarray,
    faces: np.ndarray,
    unit: str = "um",
    fields: dict[str, np.ndarray] | None = None,
    orient_outward: bool = True,
) -> trimesh.Trimesh:
    """Build a NEMO surface from arrays.

    Parameters
    ----------
    vertices : ndarray, shape (N, 3)
        Physical x, y, z.
    faces : ndarray, shape (F, 3)
        Vertex indices of triangles.
    unit : str
        Physical unit of ``vertices``.
    fields : dict of str to ndarray, shape (N,), optional
        Per-vertex fields to carry along.
    orient_outward : bool
        Flip the winding of every face when the signed volume is negative, so that normals of
        a closed surface point outward (open surfaces keep the winding they were given).

    Returns
    -------
    trimesh.Trimesh
    """
    mesh = trimesh.Trimesh(
        vertices=np.asarray(vertices, dtype=np.float64),
        faces=np.asarray(faces, dtype=np.int64),
        process=False,
    )
    if orient_outward and len(mesh.faces):
        orient_outward_(mesh)
    mesh.units = unit
    for name, values in (fields or {}).items():
        mesh.vertex_attributes[name] = np.asarray(values, dtype=np.float64)
    return mesh


def signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Signed enclosed volume (positive for outward winding), divergence theorem."""
    tri = vertices[faces]
    return float(np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0)


#: An open user mesh is warned about when the area-weighted balance of its normals points this far
#: towards its centroid (−1: all inward, +1: all outward; a flat sheet ≈ 0).
OPEN_INWARD_SHARE = 0.5


def orient_outward_(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Make the winding consistent and outward, in place.

    Winding consistency comes from trimesh's face-adjacency repair. Each connected component is
    then oriented by how many other closed components enclose it: an even depth (an outer wall)
    gets positive signed volume, an odd depth (the wall of a cavity, e.g. the inner wall of a
    hollow shell) negative, so that normals point out of the solid everywhere.
    """
    if not mesh.is_winding_consistent:
        trimesh.repair.fix_winding(mesh)
    faces = mesh.faces.copy()
    labels = trimesh.graph.connected_component_labels(mesh.face_adjacency, len(faces))
    comps = np.unique(labels)
    if len(comps) == 1:
        if signed_volume(mesh.vertices, faces) < 0:
            faces = faces[:, ::-1]
    else:
        parts = {k: trimesh.Trimesh(mesh.vertices, faces[labels == k], process=False) for k in comps}
        probes = {k: mesh.vertices[faces[labels == k][0, 0]] for k in comps}
        for k in comps:
            depth = sum(
                bool(parts[j].is_watertight and parts[j].contains([probes[k]])[0])
                for j in comps if j != k
            )
            want = 1.0 if depth % 2 == 0 else -1.0
            sel = labels == k
            if np.sign(signed_volume(mesh.vertices, faces[sel])) != want:
                faces[sel] = faces[sel][:, ::-1]
    mesh.faces = faces
    return mesh


def face_normals_areas(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit face normals (F, 3) (zero for degenerate faces) and face areas (F,)."""
    tri = vertices[faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(cross, axis=1)
    normals = np.divide(cross, norm[:, None], out=np.zeros_like(cross), where=norm[:, None] > 0)
    return normals, 0.5 * norm


def vertex_areas(mesh: trimesh.Trimesh) -> np.ndarray:
    """Barycentric vertex areas, shape (N,): a third of every incident face (sum = mesh area)."""
    _, areas = face_normals_areas(np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces))
    third = np.repeat(areas / 3.0, 3)
    return np.bincount(np.asarray(mesh.faces).ravel(), weights=third, minlength=len(mesh.vertices))


def vertex_normals(mesh: trimesh.Trimesh) -> np.ndarray:
    """Unit outward vertex normals, shape (N, 3) (area-weighted face normals).

    A vertex whose faces all have zero area (marching cubes duplicates a vertex wherever the
    level equals a voxel value) takes the normal of a coincident twin; vertices on no face, or
    without a usable twin, get NaN (never a zero vector that would pass as a direction).
    """
    normals = np.array(mesh.vertex_normals, dtype=np.float64)
    bad = ~np.isfinite(normals).all(axis=1) | (np.abs(normals).sum(axis=1) == 0)
    if bad.any():
        from scipy.spatial import cKDTree

        normals[bad] = np.nan
        good = np.flatnonzero(~bad)
        if len(good):
            vertices = np.asarray(mesh.vertices, dtype=np.float64)
            dist, idx = cKDTree(vertices[good]).query(vertices[bad])
            twin = dist <= 1e-6 * max(float(np.linalg.norm(np.ptp(vertices, axis=0))), 1e-300)
            normals[np.flatnonzero(bad)[twin]] = normals[good[idx[twin]]]
    return normals


def merge_coincident_vertices(
    vertices: np.ndarray, faces: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Merge exactly coincident vertices and drop the faces that collapse.

    Returns
    -------
    vertices : ndarray, shape (M, 3)
    faces : ndarray, shape (G, 3)
    index : ndarray, shape (N,)
        New index of every old vertex.
    """
    order = np.lexsort(vertices.T[::-1])
    sv = vertices[order]
    new = np.concatenate([[True], np.any(sv[1:] != sv[:-1], axis=1)])
    index = np.empty(len(vertices), dtype=np.int64)
    index[order] = np.cumsum(new) - 1
    f = index[faces]
    keep = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    return sv[new], f[keep], index


def object_radius(mesh: trimesh.Trimesh) -> float:
    """Radius of the sphere with the mesh's area, ``sqrt(area / 4π)``: the object's scale."""
    return float(np.sqrt(max(float(mesh.area), 0.0) / (4 * np.pi)))


def mean_edge_length(mesh: trimesh.Trimesh) -> float:
    """Mean length of the unique edges: the mesh spacing that default length scales follow."""
    v = np.asarray(mesh.vertices, dtype=np.float64)
    f = np.asarray(mesh.faces, dtype=np.int64)
    edges = np.sort(np.stack([f, np.roll(f, -1, axis=1)], axis=2).reshape(-1, 2), axis=1)
    # one int64 key per edge: faster than trimesh's row hashing (the workflow's steps each need it)
    _, first = np.unique(edges[:, 0] * len(v) + edges[:, 1], return_index=True)
    a, b = edges[first, 0], edges[first, 1]
    return float(np.mean(np.linalg.norm(v[a] - v[b], axis=1)))


def save_mesh(mesh: trimesh.Trimesh, path: str | os.PathLike) -> None:
    """Write a mesh as PLY (binary, with unit and per-vertex fields) or OBJ, atomically."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".ply", ".obj"):
        raise NemoError(f"cannot write mesh {path}: use a .ply or .obj file name")
    if suffix == ".ply":
        out = trimesh.Trimesh(vertices=mesh.vertices, faces=mesh.faces, process=False)
        for name, values in mesh.vertex_attributes.items():
            values = np.asarray(values)
            if values.ndim == 1 and len(values) == len(mesh.vertices) and not name.startswith("_"):  # _: private
                out.vertex_attributes[name] = values.astype(np.float64)
        data = out.export(file_type="ply", encoding="binary")
        unit = getattr(mesh, "units", None) or "um"
        comments = f"comment nemo unit {unit}\n"
        spacing = mesh.metadata.get("spacing")
        if spacing is not None:
            comments += "comment nemo spacing {:.9g} {:.9g} {:.9g}\n".format(*spacing)
        params = mesh.metadata.get("nemo_params")
        if params:  # the resolved mesh parameters (provenance), one JSON line
            comments += f"comment nemo params {json.dumps(params, default=str)}\n"
        data = data.replace(b"\nelement vertex", f"\n{comments}element vertex".encode(), 1)
    else:
        data = mesh.export(file_type="obj").encode()
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)  # trimesh stores vertices as float32: ~1e-7 relative precision


def _load_ply(path: Path) -> trimesh.Trimesh:
    raw = path.read_bytes()
    header = raw[: raw.find(b"end_header") + 10] if b"end_header" in raw else b""
    if not raw.startswith(b"ply") or not header:
        raise NemoError(f"{path} is not a PLY file (no 'ply' ... 'end_header' header)")
    try:
        loaded = trimesh.load(trimesh.util.wrap_as_stream(raw), file_type="ply", process=False)
    except Exception as exc:  # noqa: BLE001 - trimesh raises many types on corrupt files
        raise NemoError(f"{path} is a corrupt PLY file ({type(exc).__name__}: {exc}); re-export it") from None
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise NemoError(f"{path} holds no triangles (a point cloud?); NEMO needs a triangle mesh")
    mesh = trimesh.Trimesh(vertices=loaded.vertices, faces=loaded.faces, process=False)
    match = _UNIT_COMMENT.search(header)
    mesh.units = match.group(1).decode() if match else "um"
    mesh.metadata["unit_in_file"] = match is not None
    match = _SPACING_COMMENT.search(header)
    if match:
        mesh.metadata["spacing"] = tuple(float(v) for v in match.groups())
    # written by nemo's mesh step (outward normals by construction: no orientation check needed)
    match = _PARAMS_COMMENT.search(header)
    mesh.metadata["nemo_surface"] = match is not None
    if match:
        try:
            mesh.metadata["nemo_params"] = json.loads(match.group(1).decode())
        except (ValueError, UnicodeDecodeError):  # provenance only: an edited comment is no error
            pass
    ply_raw = loaded.metadata.get("_ply_raw", {})
    vertex_data = ply_raw.get("vertex", {}).get("data")
    if isinstance(vertex_data, dict):  # ASCII PLY: trimesh returns a dict of arrays
        items = vertex_data.items()
    elif vertex_data is not None and getattr(vertex_data, "dtype", None) is not None and vertex_data.dtype.names:
        items = ((n, vertex_data[n]) for n in vertex_data.dtype.names)
    else:
        items = ()
    for name, values in items:
        values = np.asarray(values, dtype=np.float64).ravel()
        if name not in _PLY_SKIP and len(values) == len(mesh.vertices):
            mesh.vertex_attributes[name] = values
    return mesh


def _load_other(path: Path, kind: str) -> trimesh.Trimesh:
    """An OBJ or STL surface (no unit in the file: ``units`` "um", ``unit_in_file`` False)."""
    try:
        loaded = trimesh.load(path, file_type=kind, process=False, force="mesh")
    except Exception as exc:  # noqa: BLE001 - trimesh raises many types on corrupt files
        raise NemoError(f"{path} is a corrupt {kind.upper()} file ({exc}); re-export it") from None
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise NemoError(f"{path} holds no triangles; NEMO needs a triangle mesh")
    mesh = trimesh.Trimesh(vertices=loaded.vertices, faces=loaded.faces, process=False)
    if kind == "stl":  # STL stores every triangle's corners apart: weld them into one surface
        mesh.merge_vertices()
    mesh.units = "um"
    mesh.metadata["unit_in_file"] = False
    return mesh


def load_mesh(path: str | os.PathLike, unit: str | None = None, manifold: bool = True) -> trimesh.Trimesh:
    """Read a PLY or OBJ surface and check it is usable.

    Parameters
    ----------
    path : path-like
        ``.ply`` (NEMO's or any other program's), ``.obj`` or ``.stl``.
    unit : str, optional
        Unit to assume when the file does not say (default ``"um"``).
    manifold : bool
        Refuse a non-manifold surface (the analysis steps); False for diagnostics (``nemo
        measure``, renders). Meshes written by NEMO's mesh step are manifold by construction and
        not checked again (the check costs about a second per million vertices).

    Returns
    -------
    trimesh.Trimesh
        With ``units`` and any per-vertex fields found in the file; ``metadata["unit_in_file"]``
        says whether the file named its unit (NEMO's PLY comment) or ``units`` is the default.

    Raises
    ------
    NemoError
        Missing, unreadable or corrupt file, no faces, NaN vertices, faces indexing outside the
        vertex list, a non-manifold surface (see :func:`check_mesh`).
    """
    path = Path(path)
    if not path.exists():
        raise NemoError(f"mesh file not found: {path}")
    suffix = path.suffix.lower()
    if suffix == ".ply":
        mesh = _load_ply(path)
    elif suffix in (".obj", ".stl"):
        mesh = _load_other(path, suffix[1:])
    else:
        raise NemoError(f"cannot read mesh {path}: NEMO reads .ply, .obj and .stl meshes")
    if unit is not None:
        mesh.units = unit
    trusted = mesh.metadata.get("nemo_surface") is True  # written by NEMO's mesh step: manifold
    check_mesh(mesh, str(path), manifold=manifold and not trusted)
    if not trusted:
        _orient_user_mesh(mesh, path)
    return mesh


def _orient_user_mesh(mesh: trimesh.Trimesh, path: Path) -> None:
    """Consistent, outward winding for a mesh from another tool, in place, with a warning for
    each fix; an open surface (no enclosed volume to tell) is only warned about."""
    if not mesh.is_winding_consistent:
        trimesh.repair.fix_winding(mesh)  # trimesh's face-adjacency walk (as orient_outward_)
        warnings.warn(f"{path} has faces wound both ways (some normals in, some out): made consistent. Re-export "
                      "it with one winding to silence this.", NemoWarning, stacklevel=3)
    if mesh.is_watertight:
        if signed_volume(mesh.vertices, mesh.faces) < 0:
            mesh.faces = mesh.faces[:, ::-1]
            warnings.warn(f"{path} is wound inward (negative enclosed volume): its faces were flipped so that "
                          "normals point outward. Re-export it with outward normals to silence this.",
                          NemoWarning, stacklevel=3)
        return
    normals, areas = face_normals_areas(mesh.vertices, mesh.faces)
    centres = mesh.vertices[mesh.faces].mean(axis=1)
    away = np.sign(np.einsum("ij,ij->i", centres - np.average(centres, axis=0, weights=areas), normals))
    if np.average(away, weights=areas) < -OPEN_INWARD_SHARE:
        warnings.warn(f"{path} is open and most of its normals point towards its centre: if the object bulges "
                      "outward there (a cap, a tissue cut by the field of view), its faces are wound inward and "
                      "every depth and sign will be reversed; re-export it with outward normals", NemoWarning,
                      stacklevel=3)


def check_mesh(mesh: trimesh.Trimesh, name: str = "mesh", manifold: bool = True) -> None:
    """Raise :class:`NemoError` if a mesh cannot be analysed.

    Rejects empty meshes, NaN or infinite vertices, faces indexing missing vertices, and (with
    ``manifold``, the default) non-manifold surfaces (see :func:`nonmanifold_problem`): faces
    with a repeated vertex, duplicated faces, edges shared by more than two faces and vertices
    where separate fans of faces meet. Open surfaces (with a boundary) and several separate
    components are fine. The manifold check costs about 0.5 s per million vertices.
    """
    if len(mesh.vertices) < 4 or len(mesh.faces) < 2:
        raise NemoError(f"{name} has only {len(mesh.vertices)} vertices and {len(mesh.faces)} faces")
    if not np.all(np.isfinite(mesh.vertices)):
        raise NemoError(f"{name} has vertices with NaN or infinite coordinates; repair the mesh")
    if mesh.faces.min() < 0 or mesh.faces.max() >= len(mesh.vertices):
        raise NemoError(f"{name} has faces that refer to missing vertices; the file is corrupt")
    problem = nonmanifold_problem(np.asarray(mesh.faces), len(mesh.vertices)) if manifold else None
    if problem is not None:
        raise NemoError(
            f"{name} is not a manifold surface: {problem}. NEMO's steps (peel, directors, order, "
            "curvature, thickness) would give silently wrong numbers on it; repair it first, e.g. "
            "in MeshLab › Filters › Cleaning and Repairing › Remove Duplicate Faces, Remove Zero "
            "Area Faces, Repair non Manifold Edges and Split non Manifold Vertices, or in Python "
            "with nemo.mesh.split_nonmanifold_vertices / trimesh (mesh.update_faces("
            "mesh.unique_faces() & mesh.nondegenerate_faces())), then save it again"
        )


def _sorted_half_edges(faces: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """The 3F half-edges sorted by their undirected edge.

    Half-edge ``h = 3 f + k`` runs from ``faces[f, k]`` to ``faces[f, (k + 1) % 3]``; its key is
    ``lo * n_vertices + hi``. Returns ``order`` (half-edge ids sorted by key) and the sorted
    ``keys``. When key and id fit one int64, a plain sort of the packed values replaces the
    (twice slower) argsort.
    """
    a = faces.ravel()
    b = np.roll(faces, -1, axis=1).ravel()
    n = np.int64(n_vertices)
    keys = np.minimum(a, b) * n + np.maximum(a, b)
    m = np.int64(len(a))
    if int(n_vertices) ** 2 * int(m) <= 2**63:  # largest packed value n² m − 1 fits an int64
        packed = keys * m + np.arange(m, dtype=np.int64)
        packed.sort()
        return packed % m, packed // m
    order = np.argsort(keys)
    return order, keys[order]


def nonmanifold_problem(faces: np.ndarray, n_vertices: int) -> str | None:
    """Describe the first non-manifold defect of a triangle mesh, or None if it is manifold.

    Vectorised (sorts and one sparse connected-components pass, no loop over faces). Checked in
    this order, as each check assumes the previous ones passed:

    1. faces with a repeated vertex index (a triangle collapsed to an edge or a point);
    2. duplicated faces (the same three vertices, in any order or winding);
    3. edges used by more than two faces (a "book" of pages on one spine);
    4. non-manifold vertices: the faces around a vertex form more than one fan (e.g. two
       spheres touching at a single shared vertex, a "bowtie"). The graph's nodes are the face
       corners (face, vertex); the corners of vertex v in faces f1 and f2 are joined when f1
       and f2 share an edge containing v, and v is non-manifold when its corners fall in more
       than one connected component.

    Boundaries (edges used by one face) are allowed, as are unreferenced vertices.

    Parameters
    ----------
    faces : ndarray, shape (F, 3)
        Vertex indices, all in ``[0, n_vertices)``.
    n_vertices : int

    Returns
    -------
    str or None
        E.g. ``"3 faces repeat a vertex index (e.g. face 7: vertices 4, 4, 9)"``.
    """
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    n_faces = len(faces)
    if n_faces == 0:
        return None
    f0, f1, f2 = faces[:, 0], faces[:, 1], faces[:, 2]
    degenerate = (f0 == f1) | (f1 == f2) | (f0 == f2)
    if degenerate.any():
        bad = np.flatnonzero(degenerate)
        a, b, c = faces[bad[0]]
        return (f"{len(bad)} face{'s repeat' if len(bad) > 1 else ' repeats'} a vertex index "
                f"(e.g. face {bad[0]}: vertices {a}, {b}, {c})")

    # 2. duplicated faces: one sort of the per-face sorted triples
    tri = np.sort(faces, axis=1)
    if n_vertices < 2_000_000:  # one int64 per triple (n³ < 2⁶³)
        n = np.int64(n_vertices)
        tkey = (tri[:, 0] * n + tri[:, 1]) * n + tri[:, 2]
        sk = np.sort(tkey)  # a plain sort first: the index is only needed for the message
        same = sk[1:] == sk[:-1]
        if same.any():
            torder = np.argsort(tkey, kind="stable")
            same = tkey[torder][1:] == tkey[torder][:-1]
    else:
        torder = np.lexsort(tri.T[::-1])
        st = tri[torder]
        same = np.all(st[1:] == st[:-1], axis=1)
    if same.any():
        i = int(np.flatnonzero(same)[0])
        first, second = sorted((int(torder[i]), int(torder[i + 1])))
        a, b, c = faces[second]
        n_dup = int(same.sum())
        return (f"{n_dup} face{'s duplicate' if n_dup > 1 else ' duplicates'} another face on the same "
                f"three vertices (e.g. faces {first} and {second}: vertices {a}, {b}, {c})")

    # 3. edges used by more than two faces
    order, keys = _sorted_half_edges(faces, n_vertices)
    starts = np.flatnonzero(np.concatenate([[True], keys[1:] != keys[:-1]]))
    counts = np.diff(np.append(starts, len(keys)))
    over = counts > 2
    if over.any():
        j = int(np.flatnonzero(over)[0])
        lo_v, hi_v = divmod(int(keys[starts[j]]), n_vertices)
        these = np.sort(order[starts[j]:starts[j] + counts[j]] // 3)
        n_over = int(over.sum())
        return (f"{n_over} edge{'s are' if n_over > 1 else ' is'} shared by more than two faces "
                f"(e.g. the edge between vertices {lo_v} and {hi_v} is in {counts[j]} faces: "
                f"{', '.join(str(int(f)) for f in these[:5])}{', ...' if len(these) > 5 else ''})")

    # 4. non-manifold vertices: more than one fan (corner component) per vertex
    fans = np.bincount(_corner_components(faces, order, starts, counts)[0], minlength=n_vertices)
    bad = np.flatnonzero(fans > 1)
    if len(bad):
        v = int(bad[0])
        return (f"{len(bad)} {'vertices are' if len(bad) > 1 else 'vertex is'} shared by separate "
                f"fans of faces that meet only at that vertex (e.g. vertex {v} joins {int(fans[v])} "
                "fans, like two surfaces touching at one point)")
    return None


def _corner_components(
    faces: np.ndarray, order: np.ndarray, starts: np.ndarray, counts: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Fans of faces around each vertex: connected components of the face-corner graph.

    Corner ``c = 3 f + k`` is vertex ``faces[f, k]`` in face ``f``; it starts half-edge ``c``
    and ends half-edge ``3 f + (k - 1) % 3``. Corners of the same vertex in two faces are joined
    across every edge that exactly two faces share (edges of one face are boundary, edges of
    more than two are treated as cuts), so every corner has at most two neighbours.

    Parameters
    ----------
    faces : ndarray, shape (F, 3), int64
    order, starts, counts : ndarray
        From :func:`_sorted_half_edges`: half-edges sorted by edge, the first position and the
        number of half-edges of every edge.

    Returns
    -------
    comp_vertex : ndarray, shape (n_components,)
        The vertex of every component (a component never spans two vertices).
    labels : ndarray, shape (3 F,)
        Component of every corner.
    """
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import connected_components

    flat = faces.ravel()
    n_corners = len(flat)
    corner = np.arange(n_corners, dtype=np.int64)
    end = corner + np.where(corner % 3 == 2, -2, 1)  # the end corner of half-edge h
    pair = starts[counts == 2]
    h1, h2 = order[pair], order[pair + 1]  # the two half-edges of each interior edge
    same = flat[h1] == flat[h2]  # same direction (inconsistent winding): start meets start
    e1, e2 = end[h1], end[h2]
    nbr = np.repeat(corner[:, None], 2, axis=1)  # nbr[c, 0] across half-edge c, nbr[c, 1] across the one c ends
    nbr[h1, 0] = np.where(same, h2, e2)
    nbr[h2, 0] = np.where(same, h1, e1)
    nbr[e1, 1] = np.where(same, e2, h2)
    nbr[e2, 1] = np.where(same, e1, h1)
    # symmetric by construction with two entries per row: CSR without sorting, and the strong
    # components of a symmetric graph are its undirected ones (no transposed copy needed)
    graph = csr_matrix(
        (np.ones(2 * n_corners, dtype=np.int8), nbr.ravel(), np.arange(0, 2 * n_corners + 1, 2)),
        shape=(n_corners, n_corners),
    )
    n_comp, labels = connected_components(graph, directed=True, connection="strong")
    comp_vertex = np.empty(n_comp, dtype=np.int64)
    comp_vertex[labels] = flat
    return comp_vertex, labels


def split_nonmanifold_vertices(
    vertices: np.ndarray, faces: np.ndarray, return_index: bool = False
) -> tuple[np.ndarray, np.ndarray] | tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Give every fan of faces around a vertex its own copy of the vertex (MeshLab's "Split non
    Manifold Vertices").

    Where separate fans meet at one vertex (two surfaces touching at a point, or the pinched
    vertices that selecting a subset of faces leaves along the cut), each fan beyond the first
    gets a new vertex at the same position. Edges shared by more than two faces are cut too:
    a "book" of faces on one edge falls apart into its pages wherever the pages are not
    connected around the edge's ends (two sheets touching along edges, as marching cubes makes
    where the iso-level equals voxel values, are separated into two sheets). Vectorised: one
    sparse connected-components pass.

    Parameters
    ----------
    vertices : ndarray, shape (N, 3)
    faces : ndarray, shape (F, 3)
        Without repeated indices in a face or duplicated faces (drop those first, e.g.
        ``trimesh``'s ``nondegenerate_faces`` / ``unique_faces``).
    return_index : bool
        Also return the source vertex of every output vertex.

    Returns
    -------
    vertices : ndarray, shape (M, 3)
        The input vertices, in order, followed by the M − N copies.
    faces : ndarray, shape (F, 3)
        Same faces, in order, re-pointed at the copies where needed.
    index : ndarray, shape (M,)
        With ``return_index``: ``vertices[i]`` is a copy of input vertex ``index[i]`` (carry
        per-vertex fields with ``field[index]``).
    """
    vertices = np.asarray(vertices)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    n_vertices = len(vertices)
    index = np.arange(n_vertices, dtype=np.int64)
    if len(faces):
        order, keys = _sorted_half_edges(faces, n_vertices)
        starts = np.flatnonzero(np.concatenate([[True], keys[1:] != keys[:-1]]))
        counts = np.diff(np.append(starts, len(keys)))
        comp_vertex, labels = _corner_components(faces, order, starts, counts)
        n_comp = len(comp_vertex)
        # the lowest-numbered component of each vertex keeps the vertex, the others get copies
        first = np.full(n_vertices, -1, dtype=np.int64)
        first[comp_vertex[::-1]] = np.arange(n_comp - 1, -1, -1)
        extra = np.ones(n_comp, dtype=bool)
        extra[first[first >= 0]] = False
        new_id = comp_vertex.copy()
        new_id[extra] = n_vertices + np.arange(int(extra.sum()))
        faces = new_id[labels].reshape(-1, 3)
        index = np.concatenate([index, comp_vertex[extra]])
        vertices = vertices[index]
    if return_index:
        return vertices, faces, index
    return vertices, faces
