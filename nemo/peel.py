"""Peeling: project an intensity layer of a 3D image onto a surface (method note §4).

For every vertex ``v`` with unit normal ``N`` the volume is sampled along

    x_s = v + (d_min + shift + τ) N,   τ ∈ [0, d_max − d_min]  (``n_samples`` values),

in physical units, and the samples are reduced to one value per vertex (mean or max). The
physical point ``(x, y, z)`` is the voxel index ``(z/dz, y/dy, x/dx)`` exactly, so anisotropic
voxels need no resampling. Interpolation is SciPy's ``map_coordinates`` (linear, or cubic
B-spline with the volume prefiltered once). Samples outside the volume are NaN and a vertex
whose segment leaves the volume gets NaN (never a partial, biased value).
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy import ndimage

from nemo._log import logger
from nemo.errors import NemoError, NemoWarning

#: Sample points interpolated per chunk (bounds the temporary memory to ~100 MB).
_CHUNK_POINTS = 2_000_000


def sample_depths(d_min: float, d_max: float, n_samples: int) -> np.ndarray:
    """The ``n_samples`` depths ``d_min + τ`` (µm), evenly spaced from ``d_min`` to ``d_max``."""
    if n_samples == 1:
        return np.array([float(d_min)])
    return np.linspace(float(d_min), float(d_max), int(n_samples))


def peel(
    volume: np.ndarray,
    spacing: tuple[float, float, float],
    vertices: np.ndarray,
    normals: np.ndarray,
    d_min: float,
    d_max: float,
    n_samples: int = 11,
    reduce: str = "mean",
    interp: str = "linear",
    shift: np.ndarray | None = None,
    return_profile: bool = False,
):
    """Sample a volume along vertex normals and reduce to one intensity per vertex.

    Parameters
    ----------
    volume : ndarray, shape (Z, Y, X)
        Image stack (any real dtype).
    spacing : (dz, dy, dx)
        Voxel size in physical units (µm).
    vertices : ndarray, shape (N, 3)
        Physical x, y, z.
    normals : ndarray, shape (N, 3)
        Direction of increasing depth (outward normals; pass ``-normals`` to peel inward).
        Normalised here.
    d_min, d_max : float
        Depth range along the normal (µm), ``d_min <= d_max``; negative values go against the
        normal.
    n_samples : int
        Number of depths in the range (``1`` samples ``d_min`` only).
    reduce : {"mean", "max"}
        Reduction over the depth samples.
    interp : {"linear", "cubic"}
        Interpolation order 1 or 3 (cubic B-spline, volume prefiltered once as float32).
    shift : ndarray, shape (N,), optional
        Per-vertex offset (µm) added to the whole range (e.g. a fraction of the local
        thickness). NaN shift gives a NaN intensity.
    return_profile : bool
        Also return the samples and their depths.

    Returns
    -------
    intensity : ndarray, shape (N,)
        Reduced intensity (float64), NaN where any sample lies outside the volume.
    profile : ndarray, shape (N, n_samples)
        Only with ``return_profile``: the samples.
    depths : ndarray, shape (n_samples,)
        Only with ``return_profile``: ``d_min + τ`` (without the per-vertex shift).

    Raises
    ------
    NemoError
        Bad shapes, options or range.
    """
    volume = np.asarray(volume)
    if volume.ndim != 3:
        raise NemoError(f"peel needs a 3-D (Z, Y, X) volume, got shape {volume.shape}")
    spacing = np.asarray(spacing, dtype=np.float64)
    if spacing.shape != (3,) or not np.all(spacing > 0):
        raise NemoError(f"spacing must be three positive numbers (dz, dy, dx), got {spacing.tolist()}")
    vertices = np.asarray(vertices, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or normals.shape != vertices.shape:
        raise NemoError(
            f"vertices and normals must both be (N, 3) arrays, got {vertices.shape} and {normals.shape}"
        )
    if not (np.isfinite(d_min) and np.isfinite(d_max)) or d_max < d_min:
        raise NemoError(f"bad depth range [{d_min}, {d_max}]: need finite DMIN <= DMAX")
    if int(n_samples) < 1:
        raise NemoError(f"--samples must be >= 1, got {n_samples}")
    if reduce not in ("mean", "max"):
        raise NemoError(f"unknown reduction {reduce!r}: use 'mean' or 'max'")
    if interp not in ("linear", "cubic"):
        raise NemoError(f"unknown interpolation {interp!r}: use 'linear' or 'cubic'")
    n = len(vertices)
    if shift is not None:
        shift = np.asarray(shift, dtype=np.float64)
        if shift.shape != (n,):
            raise NemoError(f"shift must have one value per vertex ({n}), got shape {shift.shape}")

    norm = np.linalg.norm(normals, axis=1, keepdims=True)
    unit = normals / np.where(norm > 0, norm, np.nan)
    depths = sample_depths(d_min, d_max, n_samples)
    if interp == "cubic":
        order = 3
        data = ndimage.spline_filter(volume.astype(np.float32, copy=False), order=3,
                                     output=np.float32, mode="mirror")
    else:
        order = 1
        data = volume
    upper = np.array(volume.shape, dtype=np.float64) - 1.0
    profile = np.empty((n, len(depths)), dtype=np.float64)
    chunk = max(1, _CHUNK_POINTS // len(depths))
    for start in range(0, n, chunk):
        stop = min(n, start + chunk)
        d = np.broadcast_to(depths, (stop - start, len(depths)))
        if shift is not None:
            d = d + shift[start:stop, None]
        pts = vertices[start:stop, None, :] + d[..., None] * unit[start:stop, None, :]  # (n, s, 3) x,y,z
        idx = pts[..., ::-1] / spacing  # (n, s, 3) voxel z, y, x
        inside = np.all((idx >= 0.0) & (idx <= upper), axis=-1)
        coords = np.where(inside[..., None], idx, 0.0).reshape(-1, 3).T
        vals = ndimage.map_coordinates(data, coords, order=order, mode="nearest",
                                       prefilter=False, output=np.float64)
        vals = vals.reshape(stop - start, len(depths))
        vals[~inside] = np.nan
        profile[start:stop] = vals
    with np.errstate(invalid="ignore"):
        intensity = profile.mean(axis=1) if reduce == "mean" else profile.max(axis=1)
    n_nan = int(np.isnan(intensity).sum())
    if n_nan == n:
        raise NemoError(
            "every sampling segment lies (partly) outside the image: check that the mesh was "
            "made from this image, the spacing/unit, and the --range"
        )
    if n_nan:
        warnings.warn(
            f"{n_nan} of {n} vertices ({100 * n_nan / n:.1f} %) sample outside the image (or have "
            "a NaN shift): their intensity is NaN",
            NemoWarning, stacklevel=2,
        )
    logger.debug("peeled %d vertices x %d depths", n, len(depths))
    if return_profile:
        return intensity, profile, depths
    return intensity
