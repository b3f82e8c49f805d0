"""Tangent frames: an orthonormal basis (t1, t2) of the tangent plane at every vertex.

Every angle NEMO reports on a surface is measured in such a basis, with ``t1 x t2 = N`` (the
outward normal), so that an angle θ lifts to the 3D unit director ``n = cos θ t1 + sin θ t2``.

Two constructions (method note §5, paper "Local tangential projection"):

* ``"axis"`` -- ``t1 = N × x̂`` normalised (``N × ŷ`` where ``N`` is nearly parallel to x̂,
  ``|N × x̂| < 0.3``), ``t2 = N × t1``. Vectorised, O(N), never fails; discontinuous only
  where the x̂/ŷ switch happens. :func:`axis_frames` is NEMO's only such construction: the
  morphology fits, the synthetic ground truth (:func:`nemo.synthetic.nematic_angle`) and the
  defect contours all use it, so angles from different modules are comparable.
* ``"smooth"`` -- a unit vector parallel-transported from one vertex over the whole surface by
  the vector heat method of Sharp et al. (potpourri3d ``MeshVectorHeatSolver``). Smooth
  everywhere except the unavoidable singularities (hairy-ball theorem). It costs a sparse
  factorisation (≈ 10 s and 0.6 GB at 160 k vertices, minutes and more memory at 1 M), so it
  is only attempted below :data:`SMOOTH_MAX_VERTICES`; above, on non-manifold meshes or when
  the solver fails, the axis frames are used with a :class:`~nemo.errors.NemoWarning`.

The nematic quantities (Q-tensor average, S, averaged director, inter-layer alignment ``c``)
are computed from 3D directors and are independent of the frame choice; frames only fix the
reference direction of reported angles.
"""

from __future__ import annotations

import warnings

import numpy as np
import trimesh

from nemo.errors import NemoError, NemoWarning
from nemo.mesh import vertex_normals

#: Largest mesh (vertices) on which the potpourri3d transport is attempted by default.
SMOOTH_MAX_VERTICES = 60_000

#: |N × x̂| below this switches the axis construction to N × ŷ.
_AXIS_SWITCH = 0.3


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
    n = _unit(np.asarray(normals, dtype=np.float64))
    # N × x̂ = (0, nz, -ny); N × ŷ = (-nz, 0, nx)
    t1 = np.stack([np.zeros(len(n)), n[:, 2], -n[:, 1]], axis=1)
    near_x = np.hypot(n[:, 1], n[:, 2]) < _AXIS_SWITCH
    if near_x.any():
        t1[near_x] = np.stack([-n[near_x, 2], np.zeros(near_x.sum()), n[near_x, 0]], axis=1)
    t1 = _unit(t1)
    t2 = np.cross(n, t1)
    return t1, t2


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
    n = _unit(np.asarray(normals, dtype=np.float64))
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
    except Exception as exc:  # potpourri3d raises RuntimeError/ValueError on bad meshes
        warnings.warn(
            f"smooth tangent frames failed ({exc}); using N × x̂ frames instead (repair the "
            "mesh, e.g. keep the largest component, for smooth frames)",
            NemoWarning, stacklevel=3,
        )
        return None
    return frames_from_vectors(normals, vec)


def _unit(v: np.ndarray) -> np.ndarray:
    norm = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(norm > 0, norm, 1.0)
