"""Geometry shared by NEMO's modules: unit vectors, tangent frames and the mesh-edge graph.

Every angle NEMO reports on a surface is measured in an orthonormal basis ``(t1, t2)`` of the
tangent plane with ``t1 × t2 = N`` (the outward normal), so that an angle θ lifts to the 3D
unit director ``n = cos θ t1 + sin θ t2``. Keeping the one construction of that basis, and the
few helpers every module needs around it, in one place makes angles from different modules
comparable and gives a reader one module to look up.

Unit vectors
------------
:func:`unit_vectors` normalises rows; :func:`project_tangent` takes the tangential part of
vectors and normalises it. Zero-length rows become NaN (a direction that does not exist), or
stay zero where a caller asks for it (the frame constructions below).

Tangent frames (method note §5, paper "Local tangential projection")
--------------------------------------------------------------------
* ``"axis"`` -- ``t1 = N × x̂`` normalised (``N × ŷ`` where ``N`` is nearly parallel to x̂,
  ``|N × x̂| < 0.3``), ``t2 = N × t1``. Vectorised, O(N), never fails; discontinuous only
  where the x̂/ŷ switch happens. :func:`axis_frames` is NEMO's only such construction: the
  morphology fits, the synthetic ground truth (:func:`nemo.synthetic.nematic_angle`), the
  imported directors and the defect contours all use it (:func:`tangent_basis` for one normal).
* ``"smooth"`` -- a unit vector parallel-transported from one vertex over the whole surface by
  the vector heat method of Sharp et al. (potpourri3d ``MeshVectorHeatSolver``). Smooth
  everywhere except the unavoidable singularities (hairy-ball theorem). It needs a sparse
  factorisation of the whole mesh, slow and memory-hungry on large meshes, so it is only
  attempted below :data:`SMOOTH_MAX_VERTICES`; above, on non-manifold meshes or when the
  solver fails, the axis frames are used with a :class:`~nemo.errors.NemoWarning`.

The nematic quantities (Q-tensor average, S, averaged director, inter-layer alignment ``c``)
are computed from 3D directors and are independent of the frame choice; frames only fix the
reference direction of reported angles.

Mesh-edge graph
---------------
:func:`edge_graph` is the mesh's edges weighted by their length; distances on it
(:func:`geodesic_ball`, SciPy's Dijkstra with a distance limit) are the paper's "shortest path
along the mesh edges". :func:`smooth_conserving` averages a per-vertex quantity over edge
neighbours without changing its sum, and :func:`boundary_loop` walks the boundary of a patch of
faces counter-clockwise (the defect contours of :mod:`nemo.defects`).

Open rim
--------
A surface cut by the field of view (``mesh.border: open``) has a rim: the edges used by one face
only. :func:`boundary_edges` lists them in the faces' winding order and :func:`rim` gives the
rim vertices, the number of rim loops and each vertex's distance to the rim (Euclidean, to the
nearest rim vertex): curvature fits, defect contours and renders use it to stay honest there.
"""

from __future__ import annotations

import warnings

import numpy as np
import trimesh
from scipy import sparse
from scipy.sparse.csgraph import dijkstra

from nemo.errors import NemoError, NemoWarning
from nemo.mesh import vertex_normals

#: Largest mesh (vertices) on which the potpourri3d transport is attempted by default.
SMOOTH_MAX_VERTICES = 60_000

#: |N × x̂| below this switches the axis construction to N × ŷ.
_AXIS_SWITCH = 0.3


# ----------------------------------------------------------------------------------------------
# unit vectors


def unit_vectors(v: np.ndarray, *, zero_stays_zero: bool = False) -> np.ndarray:
    """Vectors divided by their length along the last axis.

    Parameters
    ----------
    v : ndarray, shape (..., D)
    zero_stays_zero : bool
        False (default): zero-length vectors become NaN (0/0, without a warning), as do
        vectors with a NaN component. True: vectors whose length is not positive (zero, or NaN)
        are returned undivided, so zero vectors stay zero (the frame constructions).

    Returns
    -------
    ndarray, shape (..., D)
    """
    norm = np.linalg.norm(v, axis=-1, keepdims=True)
    if zero_stays_zero:
        return v / np.where(norm > 0, norm, 1.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return v / norm


def project_tangent(vec: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Tangential parts of vectors, normalised.

    Parameters
    ----------
    vec : ndarray, shape (M, 3)
    normals : ndarray, shape (M, 3)
        Unit normals.

    Returns
    -------
    ndarray, shape (M, 3)
        ``vec − (vec·N) N`` normalised; NaN where the tangential part vanishes.
    """
    return unit_vectors(vec - np.einsum("ij,ij->i", vec, normals)[:, None] * normals)


# ----------------------------------------------------------------------------------------------
# tangent frames


def axis_frames(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Tangent frames from the normals alone: ``t1 = N × x̂`` (``N × ŷ`` near ``N ∥ x̂``).

    Parameters
    ----------
    normals : ndarray, shape (N, 3)
        Unit normals (normalised here again for safety).

    Returns
    -------
    t1, t2 : ndarray, shape (N, 3)
        Orthonormal, ``t1 × t2 = N``; NaN rows for NaN normals.
    """
    n = unit_vectors(np.asarray(normals, dtype=np.float64), zero_stays_zero=True)
    # N × x̂ = (0, nz, -ny); N × ŷ = (-nz, 0, nx)
    t1 = np.stack([np.zeros(len(n)), n[:, 2], -n[:, 1]], axis=1)
    near_x = np.hypot(n[:, 1], n[:, 2]) < _AXIS_SWITCH
    if near_x.any():
        t1[near_x] = np.stack([-n[near_x, 2], np.zeros(near_x.sum()), n[near_x, 0]], axis=1)
    t1 = unit_vectors(t1, zero_stays_zero=True)
    t2 = np.cross(n, t1)
    return t1, t2


def rotate_between(vec: np.ndarray, from_normals: np.ndarray, to_normals: np.ndarray) -> np.ndarray:
    """``vec[i]`` rotated by the smallest rotation taking ``from_normals[i]`` to ``to_normals[i]``.

    The discrete parallel transport of a tangent vector between two points of a surface (Rodrigues'
    formula about ``from × to``); NaN where the two unit normals are opposite.

    Parameters
    ----------
    vec, from_normals, to_normals : ndarray, shape (L, 3)

    Returns
    -------
    ndarray, shape (L, 3)
    """
    axis = np.cross(from_normals, to_normals)
    cos = np.einsum("ij,ij->i", from_normals, to_normals)[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        along = np.einsum("ij,ij->i", axis, vec)[:, None] / (1 + cos)
    return vec * cos + np.cross(axis, vec) + axis * np.where(cos > -1, along, np.nan)


def tangent_basis(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Tangent basis of one normal: :func:`axis_frames` of a single row.

    Parameters
    ----------
    normal : ndarray, shape (3,)

    Returns
    -------
    t1, t2 : ndarray, shape (3,)
        Orthonormal, ``t1 × t2 = normal``.
    """
    t1, t2 = axis_frames(np.asarray(normal, dtype=np.float64)[None])
    return t1[0], t2[0]


def frames_from_vectors(normals: np.ndarray, vectors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Tangent frames with ``t1`` along the tangential part of ``vectors``.

    Rows where the tangential part vanishes (or is not finite) fall back to :func:`axis_frames`.

    Parameters
    ----------
    normals, vectors : ndarray, shape (N, 3)

    Returns
    -------
    t1, t2 : ndarray, shape (N, 3)
    """
    n = unit_vectors(np.asarray(normals, dtype=np.float64), zero_stays_zero=True)
    v = np.asarray(vectors, dtype=np.float64)
    v = v - np.einsum("ij,ij->i", v, n)[:, None] * n
    norm = np.linalg.norm(v, axis=1)
    bad = ~(norm > 1e-8) | ~np.isfinite(norm)
    t1 = v / np.where(bad, 1.0, norm)[:, None]
    if bad.any():
        t1[bad] = axis_frames(n[bad])[0]
    t2 = np.cross(n, t1)
    return t1, t2


def tangent_frames(
    mesh: trimesh.Trimesh,
    method: str = "axis",
    vertices: np.ndarray | None = None,
    max_vertices: int = SMOOTH_MAX_VERTICES,
    source: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Orthonormal tangent frames ``(t1, t2)`` with ``t1 × t2 = N`` at mesh vertices.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        NEMO surface (outward normals).
    method : {"axis", "smooth"}
        ``"axis"``: ``N × x̂`` construction (fast). ``"smooth"``: potpourri3d vector-heat
        transport of ``t1`` from ``source``; falls back to ``"axis"`` with a warning when the
        mesh has more than ``max_vertices`` vertices, is not manifold/watertight-consistent, or
        the solver fails.
    vertices : ndarray of int, shape (M,), optional
        Only return the frames at these vertices (the axis method then only computes them).
    max_vertices : int
        Size limit for the smooth method.
    source : int, optional
        Source vertex of the transport (default: the vertex closest to the top, max z).

    Returns
    -------
    t1, t2 : ndarray, shape (N, 3) or (M, 3)
    """
    if method not in ("axis", "smooth"):
        raise NemoError(f"unknown tangent-frame method {method!r}: use 'axis' or 'smooth'")
    normals = vertex_normals(mesh)
    idx = slice(None) if vertices is None else np.asarray(vertices, dtype=np.int64)
    if method == "smooth":
        frames = _smooth_frames(mesh, normals, max_vertices, source)
        if frames is not None:
            return frames[0][idx], frames[1][idx]
    return axis_frames(normals[idx])


def _smooth_frames(mesh, normals, max_vertices, source):
    """Vector-heat transported frames at every vertex, or None (with a warning) when not possible."""
    n_vert = len(mesh.vertices)
    if n_vert > max_vertices:
        warnings.warn(
            f"smooth tangent frames skipped: the mesh has {n_vert} vertices (> {max_vertices}; "
            "the potpourri3d transport would take minutes); using N × x̂ frames instead",
            NemoWarning, stacklevel=3,
        )
        return None
    try:
        import potpourri3d as pp3d

        edges = mesh.edges_sorted
        _, counts = np.unique(edges, axis=0, return_counts=True)
        if counts.max(initial=0) > 2:
            raise ValueError("the mesh has non-manifold edges")
        if source is None:
            source = int(np.argmax(mesh.vertices[:, 2]))
        solver = pp3d.MeshVectorHeatSolver(np.asarray(mesh.vertices), np.asarray(mesh.faces))
        basis_x, basis_y, _ = solver.get_tangent_frames()
        coeff = solver.transport_tangent_vector(source, [1.0, 0.0])
        vec = coeff[:, :1] * basis_x + coeff[:, 1:2] * basis_y
        if not np.isfinite(vec).all():
            raise ValueError("the transported field has NaN values")
    except Exception as exc:  # noqa: BLE001 (potpourri3d raises RuntimeError/ValueError on bad meshes)
        warnings.warn(
            f"smooth tangent frames failed ({exc}); using N × x̂ frames instead (repair the "
            "mesh, e.g. keep the largest component, for smooth frames)",
            NemoWarning, stacklevel=3,
        )
        return None
    return frames_from_vectors(normals, vec)


# ----------------------------------------------------------------------------------------------
# mesh-edge graph


def surface_centre(mesh) -> np.ndarray:
    """Area-weighted centroid of a surface (the origin of the spherical maps, an object's centre), shape (3,)."""
    tri = np.asarray(mesh.vertices)[np.asarray(mesh.faces)]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    if area.sum() <= 0:
        return np.asarray(mesh.vertices).mean(axis=0)
    return (tri.mean(axis=1) * area[:, None]).sum(axis=0) / area.sum()


def edge_graph(mesh: trimesh.Trimesh) -> sparse.csr_matrix:
    """Symmetric sparse graph of the mesh edges weighted by their length, shape (N, N).

    Distances on it (scipy Dijkstra with a limit, from one source per defect) are the paper's
    "shortest path along the mesh edges": a few % longer than true geodesics. potpourri3d's
    heat method is not used here because it solves on the whole mesh for every source, while a
    limited Dijkstra touches only the ball around the defect.
    """
    edges = np.asarray(mesh.edges_unique)
    length = np.asarray(mesh.edges_unique_length, dtype=np.float64)
    n = len(mesh.vertices)
    g = sparse.coo_matrix((length, (edges[:, 0], edges[:, 1])), shape=(n, n))
    return (g + g.T).tocsr()


def geodesic_ball(graph: sparse.csr_matrix, source: int, limit: float) -> tuple[np.ndarray, np.ndarray]:
    """Vertices within edge-path distance ``limit`` of ``source`` and their distances.

    Returns
    -------
    idx : ndarray of int, shape (M,)
    dist : ndarray of float, shape (M,)
    """
    # the graph is symmetric: directed=True gives the same distances without a transposed copy
    d = dijkstra(graph, directed=True, indices=int(source), limit=float(limit))
    idx = np.flatnonzero(np.isfinite(d))
    return idx, d[idx]


def smooth_conserving(values: np.ndarray, graph: sparse.csr_matrix, iterations: int) -> np.ndarray:
    """Spread each vertex's value equally over itself and its edge neighbours, ``iterations`` times.

    The operator is column-stochastic, so the sum over the mesh is preserved exactly (discrete
    Gauss–Bonnet still holds) while the vertex-to-vertex noise of angle defects, which would
    otherwise enter the curvature term through the contour's boundary band, is averaged out.
    """
    n = graph.shape[0]
    adj = (graph != 0).astype(np.float64) + sparse.identity(n, format="csr")
    deg = np.asarray(adj.sum(axis=0)).ravel()
    op = (adj @ sparse.diags(1.0 / deg)).tocsr()
    out = np.asarray(values, dtype=np.float64)
    for _ in range(iterations):
        out = op @ out
    return out


def boundary_loop(faces: np.ndarray, inside: np.ndarray,
                  candidates: np.ndarray | None = None) -> tuple[np.ndarray | None, np.ndarray]:
    """Outer boundary loop of the faces whose three vertices are ``inside``.

    Parameters
    ----------
    faces : ndarray, shape (F, 3)
        Outward-wound faces.
    inside : ndarray of bool, shape (N,)
    candidates : ndarray of int, optional
        Indices of the faces that may be inside (e.g. those touching the ball), for speed.

    Returns
    -------
    loop : ndarray of int, shape (L,) or None
        Vertices of the longest boundary loop, in the faces' winding order, i.e.
        counter-clockwise seen from the outward normal. None when the boundary is not a set of
        simple loops (non-manifold) or there is no face inside.
    region_vertices : ndarray of int
        Vertices of the selected faces.
    """
    if candidates is not None:
        faces = faces[candidates]
    sel = faces[inside[faces].all(axis=1)]
    if len(sel) == 0:
        return None, np.zeros(0, dtype=np.int64)
    a = sel.ravel()
    b = sel[:, [1, 2, 0]].ravel()
    n = int(max(a.max(), b.max())) + 1
    key = a.astype(np.int64) * n + b
    rkey = b.astype(np.int64) * n + a
    border = ~np.isin(key, rkey)
    a, b = a[border], b[border]
    region = np.unique(sel)
    if len(a) == 0:
        return None, region  # the ball covers a closed surface
    if len(np.unique(a)) != len(a):
        return None, region  # pinched (non-manifold) boundary: caller falls back
    loops = _follow_loops(a.tolist(), dict(zip(a.tolist(), b.tolist())))
    if loops is None:
        return None, region
    longest = max(loops, key=len)
    return np.asarray(longest, dtype=np.int64), region


def _follow_loops(starts: list[int], nxt: dict[int, int]) -> list[list[int]] | None:
    """Closed loops of the successor map ``nxt`` over the boundary vertices; None if one is open."""
    loops = []
    seen: set[int] = set()
    for start in starts:  # loop over boundary vertices of one ball (a few hundred), not the mesh
        if start in seen:
            continue
        loop = [start]
        seen.add(start)
        cur = nxt.get(start)
        while cur is not None and cur != start and cur not in seen:
            loop.append(cur)
            seen.add(cur)
            cur = nxt.get(cur)
        if cur != start:
            return None
        loops.append(loop)
    return loops


# ----------------------------------------------------------------------------------------------
# open rim


def boundary_edges(faces: np.ndarray) -> np.ndarray:
    """Edges used by exactly one face, as directed half-edges in the faces' winding order.

    Parameters
    ----------
    faces : ndarray, shape (F, 3)

    Returns
    -------
    ndarray of int, shape (B, 2)
        ``(a, b)`` per rim edge, running from ``a`` to ``b`` as in its face (empty for a closed
        surface). Walking them goes counter-clockwise around the surface seen from outside.
    """
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(faces) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    a = faces.ravel()
    b = faces[:, [1, 2, 0]].ravel()
    n = np.int64(max(int(faces.max()) + 1, 1))
    key = np.minimum(a, b) * n + np.maximum(a, b)
    _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    once = counts[inverse.ravel()] == 1
    return np.column_stack([a[once], b[once]])


def rim(faces: np.ndarray, n_vertices: int, vertices: np.ndarray | None = None) -> dict:
    """The open rim of a surface: its vertices, loops and every vertex's distance to it.

    Parameters
    ----------
    faces : ndarray, shape (F, 3)
    n_vertices : int
    vertices : ndarray, shape (N, 3), optional
        Positions; with them the distance of every vertex to the nearest rim vertex.

    Returns
    -------
    dict
        ``edges`` (B, 2) (:func:`boundary_edges`), ``vertices`` (N,) bool (on the rim),
        ``n_vertices`` and ``n_loops`` (connected rim curves; 0 for a closed surface), ``loop``
        (N,) int (each rim vertex's rim curve, 0 … n_loops − 1; −1 off the rim), and with
        ``vertices`` given ``distance`` (N,) (Euclidean distance to the nearest rim vertex, inf
        on a closed surface).
    """
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    edges = boundary_edges(faces)
    on_rim = np.zeros(int(n_vertices), dtype=bool)
    on_rim[edges.ravel()] = True
    n_loops = 0
    loop = np.full(int(n_vertices), -1, dtype=np.int64)
    if len(edges):
        nodes, inv = np.unique(edges, return_inverse=True)
        inv = inv.reshape(-1, 2)
        g = sparse.coo_matrix((np.ones(len(inv)), (inv[:, 0], inv[:, 1])), shape=(len(nodes), len(nodes)))
        n_loops, loop[nodes] = connected_components(g, directed=False)
        n_loops = int(n_loops)
    out = {"edges": edges, "vertices": on_rim, "n_vertices": int(on_rim.sum()), "n_loops": n_loops, "loop": loop}
    if vertices is not None:
        vertices = np.asarray(vertices, dtype=np.float64)
        dist = np.full(len(vertices), np.inf)
        if on_rim.any():
            dist = cKDTree(vertices[on_rim]).query(vertices)[0]
        out["distance"] = dist
    return out


def close_rim(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The surface with every rim loop closed by a fan of triangles to the loop's centroid.

    The fans keep the surface's orientation (each rim half-edge ``a → b`` gets the face
    ``(b, a, centroid)``), so a surface cut by a plane is closed by the flat cap it lost (a
    planar loop's fan covers exactly the region it encloses, convex or not): winding numbers
    then tell inside from outside as for the closed surface.

    Parameters
    ----------
    vertices : ndarray, shape (N, 3)
    faces : ndarray, shape (F, 3)

    Returns
    -------
    vertices : ndarray, shape (N + L, 3)
        With the L loop centroids appended.
    faces : ndarray, shape (F + B, 3)
    """
    from scipy.sparse.csgraph import connected_components

    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    edges = boundary_edges(faces)
    if len(edges) == 0:
        return vertices, faces
    nodes, inv = np.unique(edges, return_inverse=True)
    inv = inv.reshape(-1, 2)
    g = sparse.coo_matrix((np.ones(len(inv)), (inv[:, 0], inv[:, 1])), shape=(len(nodes), len(nodes)))
    n_loops, label = connected_components(g, directed=False)
    count = np.bincount(label, minlength=n_loops)
    centroid = np.stack([np.bincount(label, weights=vertices[nodes, k], minlength=n_loops) / count
                         for k in range(3)], axis=1)
    fan = np.column_stack([edges[:, 1], edges[:, 0], len(vertices) + label[inv[:, 0]]])
    return np.vstack([vertices, centroid]), np.vstack([faces, fan])
