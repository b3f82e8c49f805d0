"""Spherical-chart geometry: surfaces seen from their centroid as (azimuth, polar) maps.

The maps of :mod:`nemo.render.figures` (paper Fig. 2D) place every point by its direction
from the area-weighted centroid of its surface: azimuth φ = atan2(y, x) from +x towards +y,
polar angle θ from +z. This module holds the geometry of that chart -- angles, tangent
directions in chart coordinates, resampling a per-vertex field on a regular grid -- and the
even thinning of glyphs shared with the pyvista renders and the napari layers.

Pure numpy/scipy on physical ``x, y, z`` arrays; no plotting.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from nemo.geometry import surface_centre  # noqa: F401  (re-exported: the origin of the charts)


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
