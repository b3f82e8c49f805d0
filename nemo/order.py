"""Tangential nematic order: Q-tensor average and inter-layer alignment (method note §6).

Each director ``n`` at a surface point with normal ``N`` is lifted to the 3D tensor

    Q̃ = n nᵀ − ½ (I − N Nᵀ)   (= q_ij t_i ⊗ t_j with q = n nᵀ − ½ I₂ in any tangent basis),

averaged over the directors within ``radius`` of a target vertex, projected onto the target's
tangent plane (2 × 2 components in a tangent basis), made traceless and diagonalised in closed
form: ``S = 2 λ_max`` and the averaged director is the eigenvector of ``λ_max``. All of it is
frame independent: the result does not depend on the tangent basis used.

``weights="none"`` is the paper's plain mean. ``weights="coherency"`` takes the mean weighted by
each director's coherency ``c`` (structure tensor of its micro-image, in [0, 1]):
``Q = Σ c_i Q̃_i / Σ c_i``. Since the traceless part of a micro-image's trace-normalised
structure tensor is ``c (n nᵀ − ½ I₂)`` up to sign, ``c Q̃`` is the patch's own measured
nematic tensor: the weighted mean sums the micro-images' orientation tensors, so a patch of
noise (``c ≈ 0``) adds almost nothing while a cleanly striped one counts fully, and a perfectly
aligned field still gives S = 1. A fraction ``f`` of random directors of weight ``w`` among
aligned ones of weight 1 gives ``S ≈ (1 − f) / (1 − f + f w)`` instead of ``1 − f``.
The default (library, config ``order.weights`` and ``nemo order``) is the paper's mean.
``coherency`` is opt-in: on synthetic vesicles it raises the S contrast between ordered field
and defect cores at low SNR and, on clean images, moves S towards the truth (directors of low
coherency are the inaccurate ones) by at most 0.02 (``benchmarks/bench_order_noise.py``); on one
vesicle it moved two defects by 0.3-0.8 µm (the config schema).

The neighbour sums run over (target, director) pairs from ``cKDTree.sparse_distance_matrix``
in chunks of targets (bounded memory for millions of targets), accumulated with
``np.bincount``.
"""

from __future__ import annotations

import warnings

import numpy as np
import pandas as pd
import trimesh
from scipy.spatial import cKDTree

from nemo._log import logger, step
from nemo.errors import NemoError, NemoWarning
from nemo.geometry import axis_frames, project_tangent, unit_vectors
from nemo.mesh import vertex_normals

#: Upper bound on (target, director) pairs held at once.
_CHUNK_PAIRS = 4_000_000

#: Director weights of the Q average (``order(..., weights=)``, config ``order.weights``).
WEIGHTS = ("none", "coherency")

#: Index pairs of the 6 independent components of a symmetric 3 × 3 tensor.
_SYM = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def lift_q(n: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Lifted tangential Q-tensors ``n nᵀ − ½ (I − N Nᵀ)``.

    Parameters
    ----------
    n : ndarray, shape (P, 3)
        Unit directors (sign irrelevant: ``n`` and ``−n`` give the same tensor).
    normals : ndarray, shape (P, 3)
        Unit surface normals at the directors.

    Returns
    -------
    ndarray, shape (P, 6)
        Components ``(xx, xy, xz, yy, yz, zz)``.
    """
    out = np.empty((len(n), 6))
    for k, (i, j) in enumerate(_SYM):
        out[:, k] = n[:, i] * n[:, j] + 0.5 * normals[:, i] * normals[:, j] - (0.5 if i == j else 0.0)
    return out


def tangential_eig(q6: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project symmetric 3D tensors onto tangent planes, remove the trace, diagonalise.

    Parameters
    ----------
    q6 : ndarray, shape (T, 6)
        Tensors as ``(xx, xy, xz, yy, yz, zz)``.
    normals : ndarray, shape (T, 3)
        Unit normals of the target tangent planes.

    Returns
    -------
    S : ndarray, shape (T,)
        ``2 λ_max`` of the traceless tangential part (in [0, 1] for averages of unit directors).
    n : ndarray, shape (T, 3)
        Unit eigenvector of ``λ_max`` (tangent to the target plane).

    Both are NaN where the normal is not a unit vector (e.g. a vertex on zero-area faces
    only): there is no tangent plane to project on, and S = 0 there would read as a defect.
    """
    normals = np.asarray(normals, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        no_plane = ~(np.abs(np.linalg.norm(normals, axis=1) - 1.0) < 1e-3)
    t1, t2 = axis_frames(np.where(no_plane[:, None], (0.0, 0.0, 1.0), normals))
    q = np.empty((len(q6), 3, 3))
    for k, (i, j) in enumerate(_SYM):
        q[:, i, j] = q6[:, k]
        q[:, j, i] = q6[:, k]
    qt1 = np.einsum("tij,tj->ti", q, t1)
    m11 = np.einsum("ti,ti->t", t1, qt1)
    m12 = np.einsum("ti,ti->t", t2, qt1)
    m22 = np.einsum("ti,tij,tj->t", t2, q, t2)
    a = 0.5 * (m11 - m22)
    lam = np.hypot(a, m12)
    phi = 0.5 * np.arctan2(m12, a)
    n = np.cos(phi)[:, None] * t1 + np.sin(phi)[:, None] * t2
    s = 2.0 * lam
    s[no_plane] = np.nan
    n[no_plane] = np.nan
    return s, n


def _director_arrays(mesh: trimesh.Trimesh | None, df: pd.DataFrame, name: str):
    """Positions, unit directors, normals (when a mesh is given) of a directors table."""
    need = ["x", "y", "z", "nx", "ny", "nz"]
    missing = [c for c in need if c not in df.columns]
    if missing:
        raise NemoError(f"{name} lacks column(s) {', '.join(missing)}: is it a directors table?")
    pos = df[["x", "y", "z"]].to_numpy(dtype=np.float64)
    n = unit_vectors(df[["nx", "ny", "nz"]].to_numpy(dtype=np.float64))
    ok = np.isfinite(pos).all(axis=1) & np.isfinite(n).all(axis=1)
    normals = None
    if mesh is not None:
        vert = df["vertex"].to_numpy() if "vertex" in df.columns else None
        n_vert = len(mesh.vertices)
        if vert is None or (len(vert) and (vert.min() < 0 or vert.max() >= n_vert)):
            raise NemoError(
                f"{name} refers to vertices the mesh (with {n_vert} vertices) does not have: "
                "the directors were computed on another mesh"
            )
        mesh_normals = vertex_normals(mesh)
        if len(vert):
            gap = np.linalg.norm(np.asarray(mesh.vertices)[vert] - pos, axis=1)
            scale = float(np.ptp(np.asarray(mesh.vertices), axis=0).max()) or 1.0
            if np.nanmax(gap) > 1e-4 * scale:
                raise NemoError(
                    f"the positions in {name} do not match the mesh's vertices (up to "
                    f"{np.nanmax(gap):.3g} apart): use the mesh the directors were computed on"
                )
        normals = mesh_normals[vert]
    return pos, n, normals, ok


def director_weights(directors_df: pd.DataFrame, weights: str) -> np.ndarray | None:
    """Weight of every director row in the Q average.

    Parameters
    ----------
    directors_df : DataFrame, P rows
        Directors table (``coherency`` used with ``weights="coherency"``).
    weights : {"none", "coherency"}
        ``none``: the paper's unweighted mean; ``coherency``: each director weighted by its
        coherency clipped to [0, 1] (NaN = 0: no confidence).

    Returns
    -------
    ndarray, shape (P,), or None
        None for ``none`` (plain mean, today's numbers exactly), else the weights. A table
        without a ``coherency`` column gets weight 1 everywhere (with a warning).
    """
    if weights not in WEIGHTS:
        raise NemoError(f"unknown weights {weights!r}: use one of {', '.join(WEIGHTS)}")
    if weights == "none":
        return None
    if "coherency" not in directors_df.columns:
        warnings.warn("the directors table has no `coherency` column: the Q average is unweighted "
                      "(weights 'none')", NemoWarning, stacklevel=3)
        return None
    c = directors_df["coherency"].to_numpy(dtype=np.float64)
    return np.clip(np.nan_to_num(c, nan=0.0), 0.0, 1.0)


def _pair_sums(tpos: np.ndarray, pos: np.ndarray, q6: np.ndarray, w: np.ndarray | None, radius: float,
               chunk: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sums over the directors within ``radius`` of each target, in chunks of targets.

    Parameters
    ----------
    tpos : ndarray, shape (T, 3)
        Target positions.
    pos, q6 : ndarray, shapes (P, 3), (P, 6)
        Director positions and lifted tensors (already multiplied by the weights).
    w : ndarray, shape (P,), or None
        Director weights (None: unweighted).
    radius : float
    chunk : int
        Targets per chunk.

    Returns
    -------
    qsum : ndarray, shape (T, 6)
    count : ndarray, shape (T,)
        Directors within ``radius``.
    wsum : ndarray, shape (T,)
        Their total weight (``count`` when unweighted).
    """
    n_t = len(tpos)
    qsum, count, wsum = np.zeros((n_t, 6)), np.zeros(n_t), np.zeros(n_t)
    dtree = cKDTree(pos)
    for start in range(0, n_t, chunk):
        stop = min(n_t, start + chunk)
        pairs = cKDTree(tpos[start:stop]).sparse_distance_matrix(dtree, radius, output_type="ndarray")
        ti = pairs["i"].astype(np.int64)
        dj = pairs["j"].astype(np.int64)
        count[start:stop] = np.bincount(ti, minlength=stop - start)
        if w is not None:
            wsum[start:stop] = np.bincount(ti, weights=w[dj], minlength=stop - start)
        for k in range(6):
            qsum[start:stop, k] = np.bincount(ti, weights=q6[dj, k], minlength=stop - start)
        logger.debug("order chunk %d-%d: %d pairs", start, stop, len(ti))
    return qsum, count, (count if w is None else wsum)


def order(
    mesh: trimesh.Trimesh,
    directors_df: pd.DataFrame,
    radius: float,
    targets: str | np.ndarray = "all",
    weights: str = "none",
) -> pd.DataFrame:
    """Tangential Q-tensor average: order parameter ``S`` and averaged director per target.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The surface the directors were computed on (N vertices, outward normals).
    directors_df : DataFrame
        Directors table (``vertex``, ``x``, ``y``, ``z``, ``nx``, ``ny``, ``nz``).
    radius : float
        Averaging radius (µm, 3D distance).
    targets : {"all", "directors"} or ndarray of int
        Every vertex, the directors' vertices, or the given vertex indices.
    weights : {"none", "coherency"}
        ``none``: the paper's unweighted mean; ``coherency``: the mean weighted by each
        director's ``coherency`` (:func:`director_weights`; module notes).

    Returns
    -------
    DataFrame
        One row per target: ``vertex``, ``S`` (2 λ_max, in [0, 1]), ``nx``, ``ny``, ``nz``
        (averaged director, tangent), ``x``, ``y``, ``z``, ``count`` (directors averaged).
        Targets with no director within ``radius``, or whose directors all have weight 0:
        ``S`` and the director are NaN.
    """
    if not (np.isfinite(radius) and radius > 0):
        raise NemoError(f"averaging radius must be > 0 µm, got {radius}")
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    normals = vertex_normals(mesh)
    pos, n, d_normals, ok = _director_arrays(mesh, directors_df, "the directors table")
    ok &= np.isfinite(d_normals).all(axis=1)  # a director needs its tangent plane
    pos, n, d_normals = pos[ok], n[ok], d_normals[ok]
    if len(pos) == 0:
        raise NemoError("the directors table has no valid director: rerun 'nemo directors'")
    if isinstance(targets, str):
        if targets == "all":
            target_idx = np.arange(len(vertices))
        elif targets == "directors":
            target_idx = np.unique(directors_df["vertex"].to_numpy()[ok].astype(np.int64))
        else:
            raise NemoError(f"unknown targets {targets!r}: use 'all' or 'directors'")
    else:
        target_idx = np.asarray(targets, dtype=np.int64)
    w = director_weights(directors_df, weights)
    q6 = lift_q(n, d_normals)
    if w is not None:
        w = w[ok]
        q6 = q6 * w[:, None]
    n_t = len(target_idx)
    # expected pairs per target: directors per unit area × disc area (bounded by all directors)
    area = float(mesh.area) if len(mesh.faces) else 1.0
    per_target = min(len(pos), len(pos) * np.pi * radius**2 / max(area, 1e-12)) + 1
    chunk = int(max(256, min(n_t, _CHUNK_PAIRS // per_target)))
    tpos = vertices[target_idx]
    with step(f"order: {n_t} targets, {len(pos)} directors, radius {radius:g}, weights {weights}"):
        qsum, count, wsum = _pair_sums(tpos, pos, q6, w, radius, chunk)
    with np.errstate(invalid="ignore", divide="ignore"):
        qmean = qsum / wsum[:, None]
    s, navg = tangential_eig(qmean, normals[target_idx])
    _mark_empty(s, navg, count, wsum, radius)
    return _order_table(target_idx, s, navg, tpos, count)


def _order_table(vertex: np.ndarray, s: np.ndarray, navg: np.ndarray, xyz: np.ndarray,
                 count: np.ndarray) -> pd.DataFrame:
    """The order table (:func:`order`): shapes (T,), (T,), (T, 3), (T, 3), (T,)."""
    return pd.DataFrame({
        "vertex": vertex.astype(np.int64),
        "S": s,
        "nx": navg[:, 0], "ny": navg[:, 1], "nz": navg[:, 2],
        "x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2],
        "count": count.astype(np.int64),
    })


def no_order(vertices: np.ndarray) -> pd.DataFrame:
    """The order table of a surface without directors: every vertex (N of ``vertices``, shape
    (N, 3)), S and the director NaN, count 0."""
    n = len(vertices)
    return _order_table(np.arange(n), np.full(n, np.nan), np.full((n, 3), np.nan),
                        np.asarray(vertices, dtype=np.float64), np.zeros(n, np.int64))


def _mark_empty(s: np.ndarray, navg: np.ndarray, count: np.ndarray, wsum: np.ndarray, radius: float) -> None:
    """Set S and the director (shapes (T,), (T, 3)) to NaN, in place, at targets without a
    director within ``radius`` or whose directors all have weight 0, and warn."""
    empty = count == 0
    weightless = (wsum <= 0) & ~empty
    for mask, why in ((empty, f"have no director within {radius:g}"),
                      (weightless, "average only directors of weight 0 (coherency 0)")):
        if mask.any():
            s[mask] = np.nan
            navg[mask] = np.nan
            warnings.warn(f"{int(mask.sum())} of {len(s)} targets {why}: S is NaN there (use a larger "
                          "`radius` or more patches)", NemoWarning, stacklevel=3)


#: Largest distance (10th percentile of the matches) between the two layers, in A's rms radii.
MAX_MATCH_DISTANCE_PER_SIZE = 1.0


def _check_overlap(dist: np.ndarray, pos_a: np.ndarray) -> None:
    """Refuse two director sets that do not lie on the same object: even the closest tenth of the
    matches is farther than A's size (walls of a thick shell, or B covering part of A, pass)."""
    size = float(np.sqrt(np.mean(np.sum((pos_a - pos_a.mean(axis=0)) ** 2, axis=1))))
    near = float(np.quantile(dist, 0.1))
    if near > MAX_MATCH_DISTANCE_PER_SIZE * size:
        raise NemoError(
            f"the two director tables do not overlap: 90 % of the directors of A have no director of B "
            f"within {near:.4g}, while A's layer spans about {size:.4g} (rms radius). Pass tables of the "
            "same object, frame and unit (e.g. two layers of one `nemo run`), or give `max_distance`"
        )


def alignment(
    dir_a: pd.DataFrame,
    dir_b: pd.DataFrame,
    mesh_a: trimesh.Trimesh | None = None,
    normals_a: np.ndarray | None = None,
    max_distance: float | None = None,
    order_a: pd.DataFrame | None = None,
    order_b: pd.DataFrame | None = None,
) -> pd.DataFrame:
    """Inter-layer nematic alignment ``c = cos 2(θ_B − θ_A)`` for every director of A.

    For each director of A the nearest director of B (by position) is taken; B's director is
    projected onto A's tangent plane and both angles are measured in A's basis, so
    ``c = 2 (n_A · n̂_B)² − 1`` with ``n̂_B`` the normalised projection (the paper's measure).

    Noise in either layer pulls the mean of ``c`` towards 0: a director off by ε contributes
    cos 2ε, so ⟨c⟩ ≈ cos 2Δθ · S_A · S_B where S is the local order (a review's Hydra layers at
    90°, SNR 8: mean c −0.47, as if they met at 62°). With both layers' order tables, ``c_avg``
    is the same measure between their averaged directors ``n_avg`` (nearest by position to the
    director of A), whose direction noise does not shrink, and ``weight`` = S_A · S_B there
    (the same review: S-weighted mean c_avg −0.89, median −0.96).

    Parameters
    ----------
    dir_a, dir_b : DataFrame
        Directors tables.
    mesh_a : trimesh.Trimesh, optional
        The mesh of A's directors, for A's normals. Without it (and without ``normals_a``),
        ``n_B`` is not projected (exact when both layers share the surface or are parallel).
    normals_a : ndarray, shape (len(dir_a), 3), optional
        A's normals, given directly.
    max_distance : float, optional
        A director of A whose nearest director of B is farther than this (mesh unit) gets
        ``c = NaN``: there is no director of B near it to compare with.
    order_a, order_b : DataFrame, optional
        The two layers' order tables (``nemo order``: ``S``, ``nx``, ``ny``, ``nz``, ``x``, ``y``,
        ``z``), both or neither.

    Returns
    -------
    DataFrame
        ``vertex`` (A's), ``c`` in [−1, 1] (1 parallel, −1 orthogonal; NaN beyond
        ``max_distance``), ``x``, ``y``, ``z`` (A's director), ``distance`` (to the matched
        director of B), ``c_avg`` and ``weight`` (NaN without the order tables).
    """
    if max_distance is not None and not (np.isfinite(max_distance) and max_distance > 0):
        raise NemoError(f"max_distance must be a positive length, got {max_distance}")
    if normals_a is not None:
        normals_a = np.asarray(normals_a, dtype=np.float64)
        if normals_a.shape != (len(dir_a), 3):
            raise NemoError(
                f"normals_a must have one (x, y, z) normal per director of A: shape "
                f"({len(dir_a)}, 3), got {normals_a.shape}"
            )
    if (order_a is None) != (order_b is None):
        raise NemoError("give both layers' order tables (order_a and order_b) for c_avg, or neither")
    if not len(dir_a) or not len(dir_b):  # a layer whose directors were skipped (an empty frame or channel)
        warnings.warn("a layer has no directors (see its directors step): no alignment", NemoWarning, stacklevel=2)
        return _align_table(np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3)), np.zeros(0), np.zeros(0), np.zeros(0))
    pos_a, n_a, nrm_mesh, ok_a = _director_arrays(mesh_a, dir_a, "directors A")
    pos_b, n_b, _, ok_b = _director_arrays(None, dir_b, "directors B")
    pos_b, n_b = pos_b[ok_b], n_b[ok_b]
    if not ok_a.any() or len(pos_b) == 0:
        raise NemoError("a directors table has no valid director: rerun 'nemo directors'")
    normals = nrm_mesh if normals_a is None else normals_a
    dist, j = cKDTree(pos_b).query(pos_a[ok_a], workers=-1)
    if max_distance is None:  # with a limit, directors of A without a B near them get NaN instead
        _check_overlap(dist, pos_a[ok_a])
    nrm = None if normals is None else unit_vectors(normals[ok_a])
    c = _cos2(n_a[ok_a], n_b[j], nrm)
    pa = pos_a[ok_a]
    c_avg, weight = np.full(len(pa), np.nan), np.full(len(pa), np.nan)
    if order_a is not None:
        c_avg, weight = _averaged_alignment(order_a, order_b, pa, nrm)
    if max_distance is not None:
        far = dist > max_distance
        c[far], c_avg[far], weight[far] = np.nan, np.nan, np.nan
    vert = dir_a["vertex"].to_numpy()[ok_a] if "vertex" in dir_a.columns else np.flatnonzero(ok_a)
    return _align_table(vert, c, pa, dist, c_avg, weight)


def _cos2(na: np.ndarray, nb: np.ndarray, normals: np.ndarray | None) -> np.ndarray:
    """c = cos 2Δθ between directors (M, 3), both projected onto ``normals``' tangent planes when given."""
    if normals is not None:
        na, nb = project_tangent(na, normals), project_tangent(nb, normals)
    return np.clip(2.0 * np.einsum("ij,ij->i", na, nb) ** 2 - 1.0, -1.0, 1.0)


def _averaged_alignment(order_a: pd.DataFrame, order_b: pd.DataFrame, points: np.ndarray,
                        normals: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """``c_avg`` and ``weight`` = S_A · S_B (shape (M,) each) at ``points`` (M, 3): cos 2Δθ
    between the two layers' averaged directors nearest to each point (NaN where either has none)."""
    fields = []
    for name, table in (("order_a", order_a), ("order_b", order_b)):
        missing = {"S", "nx", "ny", "nz", "x", "y", "z"} - set(table.columns)
        if missing:
            raise NemoError(f"{name} is not an order table (no {', '.join(sorted(missing))}): give nemo order's output")
        _, k = cKDTree(table[["x", "y", "z"]].to_numpy(np.float64)).query(points, workers=-1)
        fields.append((table[["nx", "ny", "nz"]].to_numpy(np.float64)[k], table["S"].to_numpy(np.float64)[k]))
    (na, sa), (nb, sb) = fields
    with np.errstate(invalid="ignore"):
        return _cos2(na, nb, normals), sa * sb


def _align_table(vertex: np.ndarray, c: np.ndarray, xyz: np.ndarray, distance: np.ndarray,
                 c_avg: np.ndarray, weight: np.ndarray) -> pd.DataFrame:
    """The alignment table (:func:`alignment`): shapes (A,), (A,), (A, 3), (A,), (A,), (A,)."""
    return pd.DataFrame({"vertex": vertex.astype(np.int64), "c": c,
                         "x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "distance": distance,
                         "c_avg": c_avg, "weight": weight})
