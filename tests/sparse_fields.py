"""Sparse director fields with known defects: one director per vertex of a coarse mesh.

Independent of ``nemo.synthetic`` (no images): the surfaces are Fibonacci point sets on a sphere
triangulated by their convex hull (nearly uniform spacing, chosen in µm), and the directors are
analytic. On the sphere the director angle is ψ = Σ m_k arg(w − w_k) in the stereographic chart
w = (x + i y) / (R + z) (the chart is conformal, so the index of the field at w_k is m_k, and
the point at infinity, the south pole, carries the remaining 2 − Σ m_k). Angle noise is added
per director from a seeded generator. This is the situation of real sparse data (one director
per cell or grid point, 5-10 µm apart) fed to ``nemo order`` and ``nemo defects``.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import trimesh
from scipy.spatial import ConvexHull
from scipy.spatial.transform import Rotation

#: Area of one point of a hexagonal lattice of unit spacing.
HEX_AREA = math.sqrt(3) / 2

#: Defect directions of four +1/2 defects at the vertices of a regular tetrahedron.
TETRA = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float) / math.sqrt(3)


def fibonacci_sphere(radius: float, spacing: float) -> trimesh.Trimesh:
    """Sphere of ``radius`` about the origin with vertices ≈ ``spacing`` apart (hexagonal density).

    Returns
    -------
    trimesh.Trimesh
        Convex-hull triangulation of a Fibonacci point set, outward faces.
    """
    n = round(4 * math.pi * radius**2 / (HEX_AREA * spacing**2))
    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n
    phi = math.pi * (1 + math.sqrt(5)) * k
    r = np.sqrt(1 - z * z)
    pts = radius * np.column_stack([r * np.cos(phi), r * np.sin(phi), z])
    hull = ConvexHull(pts)
    mesh = trimesh.Trimesh(pts, hull.simplices, process=False)
    mesh.fix_normals()
    return mesh


def spherical_cap(radius: float, spacing: float, max_polar_deg: float) -> trimesh.Trimesh:
    """Open cap of :func:`fibonacci_sphere` around +z: the faces within ``max_polar_deg`` of the pole."""
    full = fibonacci_sphere(radius, spacing)
    keep = np.asarray(full.vertices)[full.faces][:, :, 2].min(axis=1) > radius * math.cos(math.radians(max_polar_deg))
    cap = full.submesh([np.flatnonzero(keep)], append=True)
    return cap


def mean_spacing(mesh: trimesh.Trimesh) -> float:
    """Mean edge length of the mesh (the director spacing when there is one director per vertex)."""
    return float(np.mean(mesh.edges_unique_length))


def stereo_field(points: np.ndarray, defect_dirs: np.ndarray, charges) -> np.ndarray:
    """Unit tangent director on a sphere about the origin, angle ψ = Σ m_k arg(w − w_k).

    Parameters
    ----------
    points : ndarray, shape (P, 3)
    defect_dirs : ndarray, shape (K, 3)
        Directions of the defects (not at the south pole).
    charges : sequence of K floats

    Returns
    -------
    ndarray, shape (P, 3)
    """
    u = points / np.linalg.norm(points, axis=1, keepdims=True)
    w = (u[:, 0] + 1j * u[:, 1]) / (1 + u[:, 2])
    dd = defect_dirs / np.linalg.norm(defect_dirs, axis=1, keepdims=True)
    wk = (dd[:, 0] + 1j * dd[:, 1]) / (1 + dd[:, 2])
    psi = sum(m * np.angle(w - c) for m, c in zip(charges, wk))
    # images of the chart's unit vectors: d(point)/d(Re w) and d(point)/d(Im w), normalised
    a, b = w.real, w.imag
    d = 1 + a * a + b * b
    eu = np.column_stack([2 / d - 4 * a * a / d**2, -4 * a * b / d**2, -4 * a / d**2])
    ev = np.column_stack([-4 * a * b / d**2, 2 / d - 4 * b * b / d**2, -4 * b / d**2])
    eu /= np.linalg.norm(eu, axis=1, keepdims=True)
    ev /= np.linalg.norm(ev, axis=1, keepdims=True)
    n = np.cos(psi)[:, None] * eu + np.sin(psi)[:, None] * ev
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def rotated_defects(dirs: np.ndarray, seed: int, min_z: float = -0.9) -> np.ndarray:
    """Random rotation of a defect set keeping every defect away from the south pole (the chart's ∞)."""
    rng = np.random.default_rng(seed)
    while True:
        out = dirs @ Rotation.random(random_state=rng).as_matrix().T
        if out[:, 2].min() > min_z:
            return out


def vertex_directors(mesh: trimesh.Trimesh, field: np.ndarray, noise_deg: float,
                     rng: np.random.Generator | int | None) -> pd.DataFrame:
    """One director per vertex: ``field`` (V, 3) projected on the tangent plane, rotated by noise.

    Returns
    -------
    DataFrame
        Directors table (``vertex``, ``x``, ``y``, ``z``, ``nx``, ``ny``, ``nz``, ``coherency``).
    """
    rng = np.random.default_rng(rng)
    pos = np.asarray(mesh.vertices, dtype=np.float64)
    normal = np.asarray(mesh.vertex_normals, dtype=np.float64)
    n = field - np.einsum("ij,ij->i", field, normal)[:, None] * normal
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    ang = np.radians(noise_deg) * rng.standard_normal(len(pos))
    n = np.cos(ang)[:, None] * n + np.sin(ang)[:, None] * np.cross(normal, n)
    return pd.DataFrame({"vertex": np.arange(len(pos)), "x": pos[:, 0], "y": pos[:, 1], "z": pos[:, 2],
                         "nx": n[:, 0], "ny": n[:, 1], "nz": n[:, 2], "coherency": np.ones(len(pos))})


def sphere_case(radius: float, spacing: float, defect_dirs: np.ndarray, charges, noise_deg: float,
                seed: int) -> tuple[trimesh.Trimesh, pd.DataFrame, np.ndarray]:
    """Coarse sphere, one noisy director per vertex, true defect positions (K, 3) on the sphere."""
    mesh = fibonacci_sphere(radius, spacing)
    ddf = vertex_directors(mesh, stereo_field(np.asarray(mesh.vertices), defect_dirs, charges), noise_deg, seed)
    return mesh, ddf, radius * defect_dirs / np.linalg.norm(defect_dirs, axis=1, keepdims=True)


def cap_case(radius: float, spacing: float, max_polar_deg: float, defect_dirs: np.ndarray, charges,
             noise_deg: float, seed: int) -> tuple[trimesh.Trimesh, pd.DataFrame, np.ndarray]:
    """Open spherical cap, one noisy director per vertex, true defect positions (K, 3)."""
    mesh = spherical_cap(radius, spacing, max_polar_deg)
    ddf = vertex_directors(mesh, stereo_field(np.asarray(mesh.vertices), defect_dirs, charges), noise_deg, seed)
    return mesh, ddf, radius * defect_dirs / np.linalg.norm(defect_dirs, axis=1, keepdims=True)


def close_pair(first: np.ndarray, second: np.ndarray, separation: float, radius: float) -> np.ndarray:
    """Unit vectors (2, 3) of two points ``separation`` apart (chord) on a sphere of ``radius``, midway
    between the unit vectors ``first`` and ``second``, along the great circle through them."""
    mid = (first + second) / np.linalg.norm(first + second)
    t = np.cross(mid, first) / np.linalg.norm(np.cross(mid, first))
    a = np.arcsin(separation / (2 * radius))
    return np.array([np.cos(a) * mid + np.sin(a) * t, np.cos(a) * mid - np.sin(a) * t])


def polar_dirs(polar_deg, azimuth_deg) -> np.ndarray:
    """Unit vectors (K, 3) at the given polar and azimuthal angles (degrees)."""
    t, p = np.radians(np.asarray(polar_deg, float)), np.radians(np.asarray(azimuth_deg, float))
    return np.column_stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)])


def score(found: pd.DataFrame, truth: np.ndarray, charges) -> dict:
    """Greedy nearest matching of found to true defects.

    Returns
    -------
    dict
        ``found`` (true defects with a found one nearest to them, one-to-one), ``dist`` (K,)
        distance of each true defect to its match (inf when unmatched), ``charge_ok`` (every
        matched charge_rounded equals the truth), ``extras`` (found defects matched to none).
    """
    p = found[["x", "y", "z"]].to_numpy() if len(found) else np.zeros((0, 3))
    d = np.linalg.norm(truth[:, None] - p[None], axis=2) if len(p) else np.full((len(truth), 0), np.inf)
    dist = np.full(len(truth), np.inf)
    used: set[int] = set()
    ok = True
    for k in np.argsort(d.min(axis=1) if d.shape[1] else np.zeros(len(truth))):  # K true defects
        free = [j for j in np.argsort(d[k]) if j not in used]
        if not free:
            continue
        j = int(free[0])
        used.add(j)
        dist[k] = d[k, j]
        ok &= bool(found["charge_rounded"].iloc[j] == charges[k])
    return {"found": int(np.isfinite(dist).sum()), "dist": dist, "charge_ok": ok, "extras": len(p) - len(used)}
