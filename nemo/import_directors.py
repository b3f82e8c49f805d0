"""Directors from other tools: a director field given at points, mapped onto a NEMO surface.

Another program (OrientationJ, a fibre tracer, a simulation) gives one orientation per point
``x, y, z`` in the image's physical frame (x = column × dx, y = row × dy, z = plane × dz, in
the image's unit, the origin at the first voxel: NEMO's mesh coordinates). Each point is
mapped to the nearest vertex of the mesh and its orientation turned into a unit tangent
director there, given either

* as a 3-D vector ``nx, ny, nz`` (any length, any sign, not necessarily tangent): projected
  onto the vertex's tangent plane and normalised; or
* as an ``angle`` in a tangent basis ``(e1, e2 = N × e1)`` (N the outward normal, so the angle
  runs counter-clockwise seen from outside): ``n = cos θ e1 + sin θ e2``, with ``e1`` the
  projection of a fixed axis (``basis="axis"``), a per-point reference ``e1x, e1y, e1z``
  (``"local"``), or NEMO's own tangent frames :func:`nemo.geometry.axis_frames` (``"frames"``).

Points farther than ``max_distance`` from the surface are refused (most of them far: an error,
the points are in another unit or frame); vectors (or reference directions) nearly normal to
the surface have no tangent direction and are dropped. Several points on one vertex are
averaged as a nematic (weighted mean of their Q-tensors), so θ and θ + 180° give θ. The
result is a directors table (:data:`nemo.tables.SCHEMAS` ``["directors"]``) on which
``nemo order``, ``nemo defects``, ``nemo align`` and ``nemo track`` run as on measured ones.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import trimesh
from scipy.spatial import cKDTree

from nemo.errors import NemoError, NemoWarning
from nemo.geometry import axis_frames
from nemo.mesh import mean_edge_length, vertex_normals

#: Default largest distance of a point from the surface, in mean edge lengths of the mesh.
MAX_DISTANCE_EDGES = 2.0
#: More than this fraction of the points far from the surface is an error (unit or frame).
FAR_FRACTION_ERROR = 0.5
#: Default smallest tangential fraction ``|v_t| / |v|`` of a vector or reference direction
#: (0.3: within 17.5° of the normal a direction is dropped as nearly normal).
MIN_TANGENTIAL = 0.3
#: Tangent bases of an ``angle`` column.
BASES = ("axis", "local", "frames")
ANGLE_UNITS = ("degrees", "radians")
#: Readable point files.
SUFFIXES = (".csv", ".tsv", ".parquet", ".npy", ".npz")

XYZ = ("x", "y", "z")
VECTOR = ("nx", "ny", "nz")
LOCAL_E1 = ("e1x", "e1y", "e1z")
#: Output columns (those of nemo.tables.SCHEMAS["directors"]).
COLUMNS = ("vertex", "x", "y", "z", "nx", "ny", "nz", "coherency")


# ----------------------------------------------------------------------------- reading
def read_points(path: str | os.PathLike) -> pd.DataFrame:
    """Read a director file (CSV/TSV, Parquet, ``.npy`` structured array, ``.npz``).

    Parameters
    ----------
    path : path-like
        A table with one row per point. ``.npy``: a structured array whose field names are the
        columns; ``.npz``: one 1-D array per column (``np.savez(path, x=..., y=..., ...)``).

    Returns
    -------
    DataFrame, shape (P, k)
        Column names stripped and lower-cased (``X`` and ``x`` are the same column).

    Raises
    ------
    NemoError
        Missing, unreadable or empty file, unknown suffix, unnamed NumPy columns, two columns of
        the same name.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise NemoError(f"cannot read directors from {path}: use a {', '.join(SUFFIXES)} file")
    if not path.is_file():
        raise NemoError(f"director file not found: {path}" + (" (it is a folder)" if path.is_dir() else ""))
    try:
        df = _READERS[suffix](path)
    except NemoError:
        raise
    except Exception as exc:  # noqa: BLE001 (pandas, pyarrow and numpy each raise their own for a corrupt file)
        raise NemoError(f"cannot read {path} as a {suffix[1:]} table ({exc})") from None
    if len(df.columns) == 1 and any(sep in str(df.columns[0]) for sep in ";\t "):
        raise NemoError(f"{path} has one column named {str(df.columns[0])[:60]!r}: separate the columns with "
                        "commas (.csv) or tabs (.tsv)")
    names = [str(c).strip().lower() for c in df.columns]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise NemoError(f"{path} has the column(s) {', '.join(twice)} twice (column names ignore case): "
                        "rename or remove the duplicates")
    df.columns = names
    if len(df) == 0:
        raise NemoError(f"{path} has no rows: it holds no director")
    return df


def _read_npy(path: Path) -> pd.DataFrame:
    array = np.load(path, allow_pickle=False)
    if array.dtype.names is None:
        raise NemoError(f"{path} is a plain array of shape {array.shape}: the columns need names; save a "
                        "structured array, or use np.savez(path, x=..., y=..., z=..., nx=..., ...) (.npz)")
    return pd.DataFrame({name: array[name] for name in array.dtype.names})


def _read_npz(path: Path) -> pd.DataFrame:
    with np.load(path, allow_pickle=False) as data:
        arrays = {key: np.asarray(data[key]) for key in data.files}
    if len(arrays) == 1 and next(iter(arrays.values())).dtype.names is not None:
        return _structured(next(iter(arrays.values())))
    shapes = {key: a.shape for key, a in arrays.items()}
    if any(len(s) != 1 for s in shapes.values()) or len(set(shapes.values())) > 1:
        raise NemoError(f"{path} must hold one 1-D array per column, all of one length (it holds "
                        f"{', '.join(f'{k} {s}' for k, s in shapes.items())})")
    return pd.DataFrame(arrays)


def _structured(array: np.ndarray) -> pd.DataFrame:
    return pd.DataFrame({name: array[name] for name in array.dtype.names})


_READERS = {
    ".csv": lambda p: pd.read_csv(p, skipinitialspace=True),
    ".tsv": lambda p: pd.read_csv(p, sep="\t", skipinitialspace=True),
    ".parquet": pd.read_parquet,
    ".npy": _read_npy,
    ".npz": _read_npz,
}


# ----------------------------------------------------------------------------- checks
def input_kind(
    points: pd.DataFrame,
    basis: str | None = None,
    axis: np.ndarray | None = None,
    angle_unit: str | None = None,
    source: str = "the points",
) -> str:
    """``"vectors"`` or ``"angles"``: which director columns ``points`` has, checked against the options.

    Raises
    ------
    NemoError
        Missing position or director columns, both kinds at once, an angle without its basis or
        unit, an unknown basis, options that do not apply.
    """
    cols = set(points.columns)
    have = ", ".join(map(str, points.columns))
    missing = [c for c in XYZ if c not in cols]
    if missing:
        raise NemoError(f"{source} lacks the position column(s) {', '.join(missing)} (it has: {have}); "
                        "positions are x, y, z in the image's unit")
    vec = [c for c in VECTOR if c in cols]
    if vec and "angle" in cols:
        raise NemoError(f"{source} has both a vector ({', '.join(vec)}) and an angle column: keep one of them")
    if vec:
        if len(vec) < 3:
            raise NemoError(f"{source} has {', '.join(vec)} but lacks {', '.join(sorted(set(VECTOR) - set(vec)))}: "
                            "a vector director needs nx, ny, nz")
        if basis is not None or axis is not None or angle_unit is not None:
            raise NemoError(f"{source} gives vectors (nx, ny, nz): `basis`, `axis` and `angle_unit` apply to "
                            "an angle column only; drop them")
        return "vectors"
    if "angle" not in cols:
        raise NemoError(f"{source} has no director column (it has: {have}): give nx, ny, nz (a 3-D vector "
                        "per point) or angle (in a tangent basis, with `basis` and `angle_unit`)")
    _check_angle_options(cols, basis, axis, angle_unit, source)
    return "angles"


def _check_angle_options(cols: set, basis, axis, angle_unit, source: str) -> None:
    if basis is None:
        raise NemoError(f"{source} gives angles: state their tangent basis with `basis` (axis: from the "
                        "projection of `axis`; local: from per-point columns e1x, e1y, e1z; frames: NEMO's "
                        "own tangent frames)")
    if basis not in BASES:
        raise NemoError(f"unknown `basis` {basis!r}: use one of {', '.join(BASES)}")
    if angle_unit not in ANGLE_UNITS:
        raise NemoError(f"{source} gives angles: state their unit with `angle_unit` (degrees or radians)"
                        + (f", not {angle_unit!r}" if angle_unit is not None else ""))
    if basis == "axis":
        a = None if axis is None else np.asarray(axis, dtype=np.float64)
        if a is None or a.shape != (3,) or not np.isfinite(a).all() or not np.linalg.norm(a) > 0:
            raise NemoError("`basis` axis measures angles from the projection of a fixed axis: give `axis` "
                            "as three numbers X Y Z, not all 0 (e.g. 1 0 0)")
    elif axis is not None:
        raise NemoError(f"`axis` is only used with `basis` axis (the basis is {basis}): drop it")
    if basis == "local" and not set(LOCAL_E1) <= cols:
        missing = [c for c in LOCAL_E1 if c not in cols]
        raise NemoError(f"`basis` local takes the reference direction of each angle from the columns "
                        f"e1x, e1y, e1z, but {source} lacks {', '.join(missing)}")


def numeric_columns(points: pd.DataFrame, columns: tuple[str, ...], source: str = "the points") -> np.ndarray:
    """The given columns as a finite float array.

    Returns
    -------
    ndarray, shape (P, len(columns))

    Raises
    ------
    NemoError
        A non-numeric column, or rows with NaN/infinite values (counted, the first few named).
    """
    try:
        values = points[list(columns)].to_numpy(dtype=np.float64)
    except (TypeError, ValueError):
        bad = [c for c in columns if not pd.api.types.is_numeric_dtype(points[c])]
        raise NemoError(f"{source}: the column(s) {', '.join(bad or columns)} are not numbers") from None
    rows = np.flatnonzero(~np.isfinite(values).all(axis=1))
    if len(rows):
        first = ", ".join(map(str, rows[:5])) + (", ..." if len(rows) > 5 else "")
        raise NemoError(f"{source}: {len(rows)} of {len(values)} rows have missing (NaN) or infinite values in "
                        f"{', '.join(columns)} (rows {first}, counted from 0 after the header): remove or fill them")
    return values


def point_weights(points: pd.DataFrame, source: str = "the points") -> tuple[np.ndarray, np.ndarray]:
    """Averaging weights and coherencies of the points.

    The weight is the ``weight`` column, else ``coherency``, else 1; the coherency the
    ``coherency`` column, else 1.

    Returns
    -------
    weight, coherency : ndarray, shape (P,)

    Raises
    ------
    NemoError
        Non-finite or negative weights, a coherency outside [0, 1].
    """
    n = len(points)
    weight = coherency = np.ones(n)
    if "coherency" in points.columns:
        coherency = numeric_columns(points, ("coherency",), source)[:, 0]
        if coherency.min() < 0 or coherency.max() > 1:
            raise NemoError(f"{source}: coherency must lie in [0, 1] (found {coherency.min():.3g} to "
                            f"{coherency.max():.3g}); give other confidences as a `weight` column")
        weight = coherency
    if "weight" in points.columns:
        weight = numeric_columns(points, ("weight",), source)[:, 0]
        if weight.min() < 0:
            raise NemoError(f"{source}: {int((weight < 0).sum())} negative weight(s): weights must be ≥ 0")
    return weight, coherency


# ----------------------------------------------------------------------------- mapping
def map_points(
    mesh: trimesh.Trimesh, xyz: np.ndarray, max_distance: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest vertex of every point and whether the point is farther than ``max_distance`` from the surface.

    The distance to the surface is bounded by the distance ``d`` to the nearest vertex:
    ``d - e_max ≤ distance ≤ d`` (``e_max`` the longest edge), so only the points between the
    two bounds get an exact closest-point query.

    Parameters
    ----------
    mesh : trimesh.Trimesh
    xyz : ndarray, shape (P, 3)
    max_distance : float

    Returns
    -------
    vertex : ndarray of int, shape (P,)
        Nearest vertex.
    distance : ndarray, shape (P,)
        Distance to that vertex.
    far : ndarray of bool, shape (P,)
        Farther than ``max_distance`` from the surface.
    """
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    distance, vertex = cKDTree(vertices).query(xyz)
    edges = vertices[np.asarray(mesh.edges_unique)]
    longest = float(np.linalg.norm(edges[:, 0] - edges[:, 1], axis=1).max()) if len(edges) else 0.0
    far = distance > max_distance + longest
    unsure = np.flatnonzero((distance > max_distance) & ~far)
    if len(unsure):
        _, exact, _ = trimesh.proximity.closest_point(mesh, xyz[unsure])
        far[unsure] = exact > max_distance
    return vertex.astype(np.int64), distance, far


def _refuse_far(far: np.ndarray, xyz: np.ndarray, mesh: trimesh.Trimesh, max_distance: float, source: str) -> None:
    """Error when most points are far from the surface; a warning with the count when some are."""
    n_far = int(far.sum())
    if n_far == 0:
        return
    unit = getattr(mesh, "units", None) or "um"
    what = (f"{n_far} of {len(far)} points of {source} lie farther than `max_distance` {max_distance:.3g} {unit} "
            "from the surface")
    if n_far <= FAR_FRACTION_ERROR * len(far):
        warnings.warn(f"{what}: refused (raise `max_distance` to keep them)", NemoWarning, stacklevel=3)
        return
    vertices = np.asarray(mesh.vertices)
    lo_p, hi_p, lo_m, hi_m = xyz.min(0), xyz.max(0), vertices.min(0), vertices.max(0)
    ratio = float(np.ptp(xyz, axis=0).max() / max(np.ptp(vertices, axis=0).max(), 1e-300))
    raise NemoError(
        f"{what}: the points span {_fmt(lo_p)} to {_fmt(hi_p)}, the mesh {_fmt(lo_m)} to {_fmt(hi_m)}"
        + (f" (the points are {ratio:.3g} × as large: another unit?)" if not 1 / 3 < ratio < 3 else "")
        + ". The points must be in the mesh's frame: x = column, y = row, z = plane, times the voxel size, "
        "in the image's unit (µm), the origin at the first voxel; convert them (unit, axis order, "
        "origin), or raise `max_distance` if they really are that far"
    )


def _fmt(v: np.ndarray) -> str:
    return "(" + ", ".join(f"{x:.4g}" for x in v) + ")"


def point_normals(mesh: trimesh.Trimesh, xyz: np.ndarray, k: int = 4) -> np.ndarray:
    """Unit surface normals at points off the vertices: inverse-square-distance mean of the
    normals of the ``k`` nearest vertices (the normal of a vertex the point sits on).

    Parameters
    ----------
    mesh : trimesh.Trimesh
    xyz : ndarray, shape (P, 3)

    Returns
    -------
    ndarray, shape (P, 3)
        NaN where the nearest vertices have no normal.
    """
    normals = vertex_normals(mesh)
    k = min(k, len(normals))
    distance, index = cKDTree(np.asarray(mesh.vertices, dtype=np.float64)).query(xyz, k=k)
    distance, index = distance.reshape(len(xyz), k), index.reshape(len(xyz), k)
    weight = 1.0 / np.maximum(distance, 1e-9 * mean_edge_length(mesh)) ** 2
    mean = np.einsum("pk,pkj->pj", weight, normals[index])
    with np.errstate(invalid="ignore", divide="ignore"):
        return mean / np.linalg.norm(mean, axis=1, keepdims=True)


def tangent_directors(
    points: pd.DataFrame,
    kind: str,
    normals: np.ndarray,
    at_points: np.ndarray | None = None,
    basis: str | None = None,
    axis: np.ndarray | None = None,
    angle_unit: str | None = None,
    min_tangential: float = MIN_TANGENTIAL,
    source: str = "the points",
) -> tuple[np.ndarray, np.ndarray]:
    """Unit tangent directors of the points at the normals of their vertices.

    An angle is turned into a 3-D direction in the tangent plane at the point itself
    (``at_points``: its basis ``e1`` is the reference projected onto that plane, ``e2 = N × e1``),
    which is then, like a given vector, projected onto the tangent plane of the point's vertex.

    Parameters
    ----------
    points : DataFrame, shape (P, k)
        Checked by :func:`input_kind` (``kind``).
    normals : ndarray, shape (P, 3)
        Unit outward normal of each point's vertex.
    at_points : ndarray, shape (P, 3), optional
        Unit normal at each point (:func:`point_normals`); default ``normals``.
    min_tangential : float
        A vector (or, for angles, the reference ``e1``) whose tangential part is shorter than
        this fraction of its length is nearly normal to the surface: no director.

    Returns
    -------
    directors : ndarray, shape (P, 3)
        Unit, tangent (NaN where not ``ok``).
    ok : ndarray of bool, shape (P,)
        False where the direction is nearly normal (or the vertex has no tangent plane).
    """
    if kind == "vectors":
        vectors = numeric_columns(points, VECTOR, source)
        zero = np.flatnonzero(~(np.linalg.norm(vectors, axis=1) > 0))
        if len(zero):
            raise NemoError(f"{source}: {len(zero)} row(s) have the zero vector as director (rows "
                            f"{', '.join(map(str, zero[:5]))}, counted from 0): remove them")
        return _project(vectors, normals, min_tangential)
    at_points = normals if at_points is None else at_points
    if basis == "axis":
        ref = np.broadcast_to(np.asarray(axis, dtype=np.float64), at_points.shape)
    elif basis == "local":
        ref = numeric_columns(points, LOCAL_E1, source)
    else:
        ref = axis_frames(np.nan_to_num(at_points))[0]
    e1, ok = _project(ref, at_points, min_tangential)
    theta = numeric_columns(points, ("angle",), source)[:, 0]
    _check_angle_unit(theta, angle_unit)
    theta = np.deg2rad(theta) if angle_unit == "degrees" else theta
    lifted = np.cos(theta)[:, None] * e1 + np.sin(theta)[:, None] * np.cross(at_points, e1)
    directors, tangent = _project(np.nan_to_num(lifted), normals, min_tangential)
    ok &= tangent
    directors[~ok] = np.nan
    return directors, ok


def _project(v: np.ndarray, normals: np.ndarray, min_tangential: float) -> tuple[np.ndarray, np.ndarray]:
    """Unit tangential parts of ``v`` (P, 3) and where they are long enough (P,)."""
    tangential = v - np.einsum("ij,ij->i", v, normals)[:, None] * normals
    length = np.linalg.norm(tangential, axis=1)
    with np.errstate(invalid="ignore"):
        ok = (length > 0) & (length >= min_tangential * np.linalg.norm(v, axis=1))  # NaN normals: False
    unit = np.full_like(tangential, np.nan)
    unit[ok] = tangential[ok] / length[ok, None]
    return unit, ok


def _check_angle_unit(theta: np.ndarray, unit: str) -> None:
    """Warn when the angles look like the other unit."""
    largest = float(np.abs(theta).max())
    if unit == "degrees" and len(theta) >= 10 and largest <= 2 * np.pi:
        warnings.warn(f"all angles lie within ±2π (largest {largest:.3g}) although `angle_unit` is degrees: "
                      "if they are radians, give `angle_unit` radians", NemoWarning, stacklevel=3)
    elif unit == "radians" and largest > 4 * np.pi:  # beyond two turns: degrees, most likely
        warnings.warn(f"angles up to {largest:.4g} although `angle_unit` is radians: if they are degrees, "
                      "give `angle_unit` degrees", NemoWarning, stacklevel=3)


def nematic_mean(
    vertex: np.ndarray, directors: np.ndarray, weights: np.ndarray, normals: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Weighted nematic (Q-tensor) mean of the directors that fall on each vertex.

    Each director is an angle ``φ`` in the vertex's tangent frame (:func:`nemo.geometry.axis_frames`);
    the mean of ``w (cos 2φ, sin 2φ)`` gives the mean director ``φ̄`` and its agreement
    ``S = |mean|`` (1 when all agree), so ``φ`` and ``φ + π`` are the same director.

    Parameters
    ----------
    vertex : ndarray of int, shape (P,)
    directors : ndarray, shape (P, 3)
        Unit tangent directors at ``normals[vertex]``.
    weights : ndarray, shape (P,)
        Non-negative.
    normals : ndarray, shape (N, 3)
        Unit normals of all vertices.

    Returns
    -------
    vertices : ndarray of int, shape (M,)
        The vertices with a positive total weight, sorted.
    mean : ndarray, shape (M, 3)
        Unit mean directors.
    agreement : ndarray, shape (M,)
        ``S`` in [0, 1].
    count : ndarray of int, shape (M,)
        Points averaged.
    """
    uniq, inverse = np.unique(vertex, return_inverse=True)
    t1, t2 = axis_frames(normals[uniq])
    phi = np.arctan2(np.einsum("ij,ij->i", directors, t2[inverse]), np.einsum("ij,ij->i", directors, t1[inverse]))
    total = np.bincount(inverse, weights=weights, minlength=len(uniq))
    c2 = np.bincount(inverse, weights=weights * np.cos(2 * phi), minlength=len(uniq))
    s2 = np.bincount(inverse, weights=weights * np.sin(2 * phi), minlength=len(uniq))
    count = np.bincount(inverse, minlength=len(uniq))
    keep = total > 0
    half = 0.5 * np.arctan2(s2[keep], c2[keep])
    mean = np.cos(half)[:, None] * t1[keep] + np.sin(half)[:, None] * t2[keep]
    agreement = np.clip(np.hypot(c2[keep], s2[keep]) / total[keep], 0.0, 1.0)
    return uniq[keep], mean, agreement, count[keep]


# ----------------------------------------------------------------------------- the import
def import_directors(
    mesh: trimesh.Trimesh,
    points: pd.DataFrame,
    basis: str | None = None,
    axis: np.ndarray | None = None,
    angle_unit: str | None = None,
    max_distance: float | None = None,
    min_tangential: float = MIN_TANGENTIAL,
    source: str = "the points",
) -> tuple[pd.DataFrame, dict]:
    """A directors table from a director field given at points (see the module docstring).

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The surface (N vertices, outward normals, the image's physical frame).
    points : DataFrame, shape (P, k)
        Columns ``x, y, z`` and either ``nx, ny, nz`` or ``angle`` (+ ``e1x, e1y, e1z`` for the
        local basis); optional ``weight`` and ``coherency`` (:func:`point_weights`). Not modified.
    basis : {"axis", "local", "frames"}, optional
        Tangent basis of an angle column (required with angles).
    axis : array-like, shape (3,), optional
        The fixed axis of ``basis="axis"``.
    angle_unit : {"degrees", "radians"}, optional
        Required with angles.
    max_distance : float, optional
        Points farther from the surface are refused (default ``2 ×`` the mean edge length);
        more than half of them far is an error.
    min_tangential : float
        See :func:`tangent_directors`.
    source : str
        Name of the points in messages (their file).

    Returns
    -------
    directors : DataFrame, shape (M, 8)
        ``vertex, x, y, z`` (the vertex's position), ``nx, ny, nz`` (unit, tangent),
        ``coherency`` (the points' weighted mean coherency × their agreement S), one row per
        vertex that received a point, sorted by vertex.
    counts : dict
        ``n_points``, ``n_far``, ``n_nearly_normal``, ``n_zero_weight``, ``n_directors``,
        ``n_shared`` (vertices that averaged several points), ``median_distance`` (point to
        its vertex, over the points kept) and the ``max_distance`` used.

    Raises
    ------
    NemoError
        Missing or bad columns, NaN rows, options that do not fit the columns, most points far
        from the surface (another unit or frame), no director left.
    """
    kind = input_kind(points, basis, axis, angle_unit, source)
    xyz = numeric_columns(points, XYZ, source)
    weight, coherency = point_weights(points, source)
    if max_distance is None:
        max_distance = MAX_DISTANCE_EDGES * mean_edge_length(mesh)
    vertex, distance, far = map_points(mesh, xyz, float(max_distance))
    _refuse_far(far, xyz, mesh, float(max_distance), source)
    normals = vertex_normals(mesh)
    at_points = point_normals(mesh, xyz) if kind == "angles" else None
    directors, ok = tangent_directors(points, kind, normals[vertex], at_points, basis, axis, angle_unit,
                                      min_tangential, source)
    nearly_normal = ~ok & ~far
    if nearly_normal.any():
        warnings.warn(f"{int(nearly_normal.sum())} of {len(ok)} points of {source} have a "
                      f"{'vector' if kind == 'vectors' else 'reference direction e1'} nearly normal to the surface "
                      f"(tangential part < {min_tangential:g} of it): dropped", NemoWarning, stacklevel=2)
    keep = ok & ~far & (weight > 0)
    if not keep.any():
        raise NemoError(f"no director of {source} is left ({int(far.sum())} far from the surface, "
                        f"{int(nearly_normal.sum())} nearly normal, {int((weight == 0).sum())} of weight 0)")
    v, w = vertex[keep], weight[keep]
    vertices, mean, agreement, count = nematic_mean(v, directors[keep], w, normals)
    coh = np.bincount(v, weights=w * coherency[keep], minlength=len(normals))[vertices]
    coh /= np.bincount(v, weights=w, minlength=len(normals))[vertices]
    pos = np.asarray(mesh.vertices, dtype=np.float64)[vertices]
    df = pd.DataFrame({"vertex": vertices.astype(np.int64), "x": pos[:, 0], "y": pos[:, 1], "z": pos[:, 2],
                       "nx": mean[:, 0], "ny": mean[:, 1], "nz": mean[:, 2], "coherency": coh * agreement})
    counts = {"n_points": len(points), "n_far": int(far.sum()), "n_nearly_normal": int(nearly_normal.sum()),
              "n_zero_weight": int((ok & ~far & (weight == 0)).sum()), "n_directors": len(df),
              "n_shared": int((count > 1).sum()), "median_distance": float(np.median(distance[keep])),
              "max_distance": float(max_distance)}
    return df, counts
