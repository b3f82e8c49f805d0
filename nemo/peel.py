"""Peeling: project an intensity layer of a 3D image onto a surface (method note §4).

For every vertex ``v`` with unit normal ``N`` the volume is sampled along

    x_s = v + (d_min + shift + τ) N,   τ ∈ [0, d_max − d_min]  (``n_samples`` values),

in physical units, and the samples are reduced to one value per vertex (mean or max). The
physical point ``(x, y, z)`` is the voxel index ``(z/dz, y/dy, x/dx)`` exactly, so anisotropic
voxels need no resampling. Interpolation is SciPy's ``map_coordinates`` (linear, or cubic
B-spline with the part of the volume the samples reach prefiltered once, mirror boundaries).
Samples outside the volume are NaN and a vertex whose segment leaves the volume gets NaN
(never a partial, biased value); NaN voxels give NaN too, counted apart in the warning.

The mesh must live in the image's physical space: :func:`check_mesh_image` compares its unit
and the spacing recorded at reconstruction with the image's, and :func:`peel` refuses a mesh
with more than :data:`MAX_OUTSIDE_FRACTION` of its vertices outside the image box.
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy import ndimage

from nemo._log import logger
from nemo.errors import NemoError, NemoWarning
from nemo.geometry import unit_vectors
from nemo.io import check_spacing

#: Sample points interpolated per chunk (bounds the temporary memory to ~100 MB).
_CHUNK_POINTS = 2_000_000

#: A mesh with more than this fraction of its vertices outside the image box was not made from
#: this image (or at another spacing): peeling it is refused.
MAX_OUTSIDE_FRACTION = 0.05

#: Samples closer than this fraction of the smallest voxel add nothing to the layer.
_MIN_SAMPLE_STEP_VOXELS = 0.05

#: Extra voxels around the sampled region kept for the cubic B-spline prefilter (its influence
#: decays as 0.27^k: 8 voxels leave < 3e-5 of the boundary condition at the samples).
_CUBIC_MARGIN = 8

_UM = {"um", "µm", "μm", "micron", "microns", "micrometer", "micrometre"}


def sample_depths(d_min: float, d_max: float, n_samples: int) -> np.ndarray:
    """The ``n_samples`` depths ``d_min + τ`` (µm), evenly spaced from ``d_min`` to ``d_max``."""
    if n_samples == 1:
        return np.array([float(d_min)])
    return np.linspace(float(d_min), float(d_max), int(n_samples))


def max_samples(d_min: float, d_max: float, spacing) -> int:
    """Most useful samples over a range: 1/20 of the smallest voxel apart (at least 101)."""
    step = _MIN_SAMPLE_STEP_VOXELS * min(check_spacing(spacing))
    return max(101, int(np.ceil((float(d_max) - float(d_min)) / step)) + 1)


def _same_unit(a: str | None, b: str | None) -> bool:
    a, b = (a or "um").strip().lower(), (b or "um").strip().lower()
    return a == b or (a in _UM and b in _UM)


def check_mesh_image(mesh, spacing, unit: str, mesh_name: str = "the mesh", image_name: str = "the image") -> None:
    """Raise :class:`NemoError` unless a mesh lives in the physical space of an image.

    The mesh's unit (``mesh.units``) must be the image's, and the spacing recorded when the
    mesh was reconstructed (``mesh.metadata["spacing"]``, a PLY header comment written by
    ``nemo mesh``) must equal the image's. Meshes without a recorded spacing (made elsewhere)
    are only checked for the unit; :func:`peel` then checks that they lie inside the image.

    Parameters
    ----------
    mesh : trimesh.Trimesh
    spacing : (dz, dy, dx)
        The image's voxel size (after any ``--spacing`` override).
    unit : str
        The image's unit.
    """
    sp = np.asarray(check_spacing(spacing))
    mesh_unit = getattr(mesh, "units", None) or "um"
    if not _same_unit(mesh_unit, unit):
        raise NemoError(
            f"{mesh_name} is in unit '{mesh_unit}' but {image_name} is in '{unit}' (spacing "
            f"{' '.join(f'{v:g}' for v in sp)}): make the mesh from this image with the same "
            "`spacing`, or give the image the `spacing` the mesh was made with"
        )
    made = mesh.metadata.get("spacing") if hasattr(mesh, "metadata") else None
    if made is not None and not np.allclose(np.asarray(made, dtype=np.float64), sp, rtol=1e-5, atol=0.0):
        raise NemoError(
            f"{mesh_name} was made from an image with spacing (dz, dy, dx) = "
            f"({', '.join(f'{v:g}' for v in made)}) but {image_name} has "
            f"({', '.join(f'{v:g}' for v in sp)}): pass `spacing` {' '.join(f'{v:g}' for v in made)} "
            "(as for 'nemo mesh'), or remake the mesh from this image"
        )


#: A foreign mesh whose extent differs from the bright object's by more than this factor
#: (either way) is probably in another unit or scaled: a warning says so.
MAX_EXTENT_RATIO = 1.6

#: At most this many voxels are looked at to find the bright object's extent.
_EXTENT_VOXELS = 2_000_000


def mesh_object_extent_ratio(mesh, volume: np.ndarray, spacing) -> float:
    """Extent of the mesh over the extent of the image's bright object (geometric mean of x, y, z).

    The object is the voxels above Otsu's threshold (on at most ``_EXTENT_VOXELS`` voxels); both
    extents run from the 1st to the 99th percentile of the coordinates, so specks do not count.
    Near 1 for a surface of the object; near 0.5 or 1000 for a mesh scaled or in another unit.
    """
    from skimage.filters import threshold_otsu

    stride = max(1, int(np.ceil((volume.size / _EXTENT_VOXELS) ** (1 / 3))))
    sub = np.asarray(volume[::stride, ::stride, ::stride], dtype=np.float64)
    finite = np.isfinite(sub)
    if finite.sum() < 2 or np.ptp(sub[finite]) == 0:
        return float("nan")
    zyx = np.argwhere(finite & (sub > threshold_otsu(sub[finite])))
    xyz_object = zyx[:, ::-1] * stride * np.asarray(check_spacing(spacing))[::-1]
    lo, hi = np.percentile(xyz_object, [1, 99], axis=0)
    mlo, mhi = np.percentile(np.asarray(mesh.vertices, dtype=np.float64), [1, 99], axis=0)
    step = stride * np.asarray(check_spacing(spacing))[::-1]
    ratios = (mhi - mlo + step) / (hi - lo + step)
    return float(np.exp(np.mean(np.log(ratios))))


def warn_if_mesh_off_object(mesh, volume: np.ndarray, spacing, mesh_name: str = "the mesh") -> None:
    """Warn when a mesh made elsewhere (no NEMO metadata) does not match the bright object's size."""
    ratio = mesh_object_extent_ratio(mesh, volume, spacing)
    if np.isfinite(ratio) and not 1 / MAX_EXTENT_RATIO <= ratio <= MAX_EXTENT_RATIO:
        warnings.warn(
            f"{mesh_name} spans {ratio:.2g} × the extent of the image's bright object: a mesh made "
            "elsewhere may be in another unit (nm, mm) or scaled. NEMO needs the mesh in the image's "
            "physical unit and frame (x = column, y = row, z = plane); check it before trusting the layer",
            NemoWarning, stacklevel=2,
        )


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
        Normalised here; a zero or NaN normal gives a NaN intensity.
    d_min, d_max : float
        Depth range along the normal (µm), ``d_min <= d_max``; negative values go against the
        normal.
    n_samples : int
        Number of depths in the range (``1`` samples ``d_min`` only); at most
        :func:`max_samples` (samples 1/20 voxel apart).
    reduce : {"mean", "max"}
        Reduction over the depth samples.
    interp : {"linear", "cubic"}
        Interpolation order 1 or 3 (cubic B-spline, prefiltered once as float32 on the part of
        the volume the samples reach, mirror boundaries).
    shift : ndarray, shape (N,), optional
        Per-vertex offset (µm) added to the whole range (e.g. a fraction of the local
        thickness). NaN shift gives a NaN intensity.
    return_profile : bool
        Also return the samples and their depths (an (N, n_samples) array is then kept).

    Returns
    -------
    intensity : ndarray, shape (N,)
        Reduced intensity (float64), NaN where any sample lies outside the volume or on a NaN
        voxel.
    profile : ndarray, shape (N, n_samples)
        Only with ``return_profile``: the samples.
    depths : ndarray, shape (n_samples,)
        Only with ``return_profile``: ``d_min + τ`` (without the per-vertex shift).

    Raises
    ------
    NemoError
        Bad shapes, options or range; more than :data:`MAX_OUTSIDE_FRACTION` of the vertices
        outside the image box ``[0, (n − 1) d]`` (a mesh from another image or spacing).
    """
    volume, spacing, vertices, normals, shift = _check_peel_args(
        volume, spacing, vertices, normals, d_min, d_max, n_samples, reduce, interp, shift)
    n = len(vertices)
    upper = np.array(volume.shape, dtype=np.float64) - 1.0
    _check_inside(vertices, upper[::-1] * spacing[::-1], spacing)

    unit = unit_vectors(normals)  # a zero or NaN normal: NaN
    no_normal = ~np.isfinite(unit).all(axis=1)
    depths = sample_depths(d_min, d_max, n_samples)
    offset = np.zeros(3)
    if interp == "cubic":
        order = 3
        data, offset = _cubic_coefficients(volume, vertices, depths, shift, spacing)
    else:
        order = 1
        data = volume
    intensity, profile, n_outside, n_nan_voxel = _sample_segments(
        data, order, offset, upper, spacing, vertices, unit, no_normal, depths, shift, reduce, return_profile)
    _report_nan(intensity, n_outside, n_nan_voxel, shift, no_normal)
    logger.debug("peeled %d vertices x %d depths", n, len(depths))
    if return_profile:
        return intensity, profile, depths
    return intensity


def leaves_image(shape: tuple[int, int, int], spacing: tuple[float, float, float], vertices: np.ndarray,
                 normals: np.ndarray, depths: np.ndarray, shift: np.ndarray | None = None) -> np.ndarray:
    """Which vertices' sampling segments of :func:`peel` leave the image.

    The image box is convex, so a segment stays inside it when its first and last samples do;
    they are computed and tested as :func:`peel` does (voxel indices within ``[0, n − 1]``), so a
    vertex on the box's face reads the same in both.

    Parameters
    ----------
    shape : (Z, Y, X)
        The image's shape.
    spacing : (dz, dy, dx)
    vertices, normals : ndarray, shape (N, 3)
        Physical x, y, z and the direction of increasing depth, as given to :func:`peel`.
    depths : ndarray, shape (S,)
        The sampled depths (:func:`sample_depths`); ``shift`` (N,) the per-vertex offset, as in :func:`peel`.

    Returns
    -------
    ndarray of bool, shape (N,)
        False also where a normal or the shift is not finite (no segment).
    """
    upper = np.asarray(shape, dtype=np.float64) - 1.0
    sp = np.asarray(spacing, dtype=np.float64)
    unit = unit_vectors(np.asarray(normals, dtype=np.float64))
    offset = np.zeros(len(vertices)) if shift is None else np.asarray(shift, dtype=np.float64)
    depths = np.asarray(depths, dtype=np.float64)
    out = np.zeros(len(vertices), dtype=bool)
    for depth in (depths[0], depths[-1]):
        idx = (np.asarray(vertices, dtype=np.float64) + (depth + offset)[:, None] * unit)[:, ::-1] / sp
        with np.errstate(invalid="ignore"):
            out |= ~np.all((idx >= 0.0) & (idx <= upper), axis=1)
    return out & np.isfinite(unit).all(axis=1) & np.isfinite(offset)


def _check_peel_args(volume, spacing, vertices, normals, d_min, d_max, n_samples, reduce, interp, shift):
    """The arrays of :func:`peel` as float64 (volume as given), refused when shapes or options are bad.

    Returns
    -------
    volume, spacing, vertices, normals, shift
    """
    volume = np.asarray(volume)
    if volume.ndim != 3:
        raise NemoError(f"peel needs a 3-D (Z, Y, X) volume, got shape {volume.shape}")
    spacing = np.asarray(check_spacing(spacing), dtype=np.float64)
    vertices = np.asarray(vertices, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or normals.shape != vertices.shape:
        raise NemoError(
            f"vertices and normals must both be (N, 3) arrays, got {vertices.shape} and {normals.shape}"
        )
    if not (np.isfinite(d_min) and np.isfinite(d_max)) or d_max < d_min:
        raise NemoError(f"bad depth range [{d_min}, {d_max}]: need finite DMIN <= DMAX")
    if int(n_samples) < 1:
        raise NemoError(f"`n_samples` must be >= 1, got {n_samples}")
    cap = max_samples(d_min, d_max, spacing)
    if int(n_samples) > cap:
        raise NemoError(
            f"`n_samples` {n_samples} puts samples closer than 1/20 of a voxel over [{d_min:g}, {d_max:g}]: "
            f"use at most {cap} (the default 11 is plenty for a layer a few voxels deep)"
        )
    if reduce not in ("mean", "max"):
        raise NemoError(f"unknown reduction {reduce!r}: use 'mean' or 'max'")
    if interp not in ("linear", "cubic"):
        raise NemoError(f"unknown interpolation {interp!r}: use 'linear' or 'cubic'")
    n = len(vertices)
    if shift is not None:
        shift = np.asarray(shift, dtype=np.float64)
        if shift.shape != (n,):
            raise NemoError(f"shift must have one value per vertex ({n}), got shape {shift.shape}")
    return volume, spacing, vertices, normals, shift


def _sample_segments(data, order, offset, upper, spacing, vertices, unit, no_normal, depths, shift, reduce,
                     return_profile):
    """Interpolate ``data`` along every vertex's segment, in chunks of vertices, and reduce.

    ``data`` is the volume (linear) or the cubic coefficients of its part starting at voxel
    ``offset``; ``upper`` is the last voxel index (z, y, x) of the whole volume.

    Returns
    -------
    intensity : ndarray, shape (N,)
    profile : ndarray, shape (N, n_samples) or None
    n_outside, n_nan_voxel : int
        Vertices with a segment leaving the image, or on NaN voxels (for the warning).
    """
    n = len(vertices)
    crop_upper = np.array(data.shape, dtype=np.float64) - 1.0
    intensity = np.empty(n, dtype=np.float64)
    profile = np.empty((n, len(depths)), dtype=np.float64) if return_profile else None
    n_outside = n_nan_voxel = 0
    chunk = max(1, _CHUNK_POINTS // len(depths))
    for start in range(0, n, chunk):
        stop = min(n, start + chunk)
        d = np.broadcast_to(depths, (stop - start, len(depths)))
        if shift is not None:
            d = d + shift[start:stop, None]
        pts = vertices[start:stop, None, :] + d[..., None] * unit[start:stop, None, :]  # (n, s, 3) x,y,z
        idx = pts[..., ::-1] / spacing  # (n, s, 3) voxel z, y, x
        inside = np.all((idx >= 0.0) & (idx <= upper), axis=-1)
        local = idx - offset
        coords = np.where(inside[..., None], np.clip(local, 0.0, crop_upper), 0.0).reshape(-1, 3).T
        vals = ndimage.map_coordinates(data, coords, order=order, mode="mirror",
                                       prefilter=False, output=np.float64)
        vals = vals.reshape(stop - start, len(depths))
        nan_voxel = inside & np.isnan(vals)
        vals[~inside] = np.nan
        n_outside += int((~inside.all(axis=1) & np.isfinite(d).all(axis=1) & ~no_normal[start:stop]).sum())
        n_nan_voxel += int((nan_voxel.any(axis=1) & inside.all(axis=1)).sum())
        with np.errstate(invalid="ignore"):
            intensity[start:stop] = vals.mean(axis=1) if reduce == "mean" else vals.max(axis=1)
        if profile is not None:
            profile[start:stop] = vals
    return intensity, profile, n_outside, n_nan_voxel


def _report_nan(intensity: np.ndarray, n_outside: int, n_nan_voxel: int, shift: np.ndarray | None,
                no_normal: np.ndarray) -> None:
    """Refuse a layer that is NaN everywhere; warn (at the caller of :func:`peel`) with the causes
    of the NaN vertices otherwise."""
    n = len(intensity)
    n_nan = int(np.isnan(intensity).sum())
    if n_nan == n:
        raise NemoError(
            "every sampling segment lies (partly) outside the image or on NaN voxels: check that the "
            "mesh was made from this image, the spacing/unit, and the depth range (`d_min`, `d_max`)"
        )
    if n_nan:
        n_shift = int(np.isnan(shift).sum()) if shift is not None else 0
        parts = [f"{k} {what}" for k, what in (
            (n_outside, "sample outside the image"), (n_nan_voxel, "sample NaN voxels"),
            (n_shift, "have a NaN shift"), (int(no_normal.sum()), "have no normal (zero-area faces only)"),
        ) if k]
        warnings.warn(
            f"{n_nan} of {n} vertices ({100 * n_nan / n:.1f} %) have a NaN intensity: "
            + ", ".join(parts),
            NemoWarning, stacklevel=3,
        )


def _check_inside(vertices: np.ndarray, box: np.ndarray, spacing: np.ndarray) -> None:
    """Refuse a mesh with more than MAX_OUTSIDE_FRACTION of its vertices outside the image box."""
    tol = 0.5 * spacing[::-1]  # x, y, z
    outside = np.any((vertices < -tol) | (vertices > box + tol), axis=1)
    frac = float(outside.mean()) if len(vertices) else 0.0
    if frac > MAX_OUTSIDE_FRACTION:
        lo, hi = vertices.min(axis=0), vertices.max(axis=0)
        raise NemoError(
            f"{100 * frac:.0f} % of the mesh's vertices lie outside the image (mesh x, y, z from "
            f"({lo[0]:.4g}, {lo[1]:.4g}, {lo[2]:.4g}) to ({hi[0]:.4g}, {hi[1]:.4g}, {hi[2]:.4g}), image "
            f"box (0, 0, 0) to ({box[0]:.4g}, {box[1]:.4g}, {box[2]:.4g})): the mesh was not made "
            "from this image or at this spacing/unit; use the image and `spacing` the mesh was made with"
        )


def _cubic_coefficients(volume, vertices, depths, shift, spacing):
    """Cubic B-spline coefficients (float32) of the part of the volume the samples reach.

    Returns the coefficients and the voxel offset (z, y, x) of their first element.
    """
    reach = max(abs(float(depths[0])), abs(float(depths[-1])))
    if shift is not None and np.isfinite(shift).any():
        reach += float(np.nanmax(np.abs(shift)))
    lo_xyz = vertices.min(axis=0) - reach
    hi_xyz = vertices.max(axis=0) + reach
    shape = np.array(volume.shape)
    lo = np.clip(np.floor(lo_xyz[::-1] / spacing).astype(np.int64) - _CUBIC_MARGIN, 0, shape - 1)
    hi = np.clip(np.ceil(hi_xyz[::-1] / spacing).astype(np.int64) + _CUBIC_MARGIN + 1, lo + 1, shape)
    sub = volume[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]].astype(np.float32, copy=False)
    coeff = ndimage.spline_filter(sub, order=3, output=np.float32, mode="mirror")
    return coeff, lo.astype(np.float64)


#: Vertices sampled for a layer's texture profile (:func:`texture_profile`), and the neighbours
#: whose mean each sample's intensity is compared with.
TEXTURE_VERTICES, TEXTURE_NEIGHBOURS = 4000, 24
#: A texture peak outside a layer's range that is this many times the strongest texture inside it,
#: and at least :data:`TEXTURE_MIN_CONTRAST` × the range of the mean intensity over the depths (a
#: structure, not a wall's edge or noise), is reported: the layer probably misses what it is meant
#: to peel.
TEXTURE_OUTSIDE_RATIO, TEXTURE_MIN_CONTRAST = 1.5, 0.1


def texture_profile(volume: np.ndarray, spacing, vertices: np.ndarray, normals: np.ndarray, d_min: float,
                    d_max: float, rng: int = 0) -> dict:
    """Where along the normals the image has texture, around a layer's depth range.

    At depths from ``d_min − w`` to ``d_max + w`` (w = the range's width, at least 2 of the
    largest voxel; steps of half the smallest voxel, at most ¼ of w, at most 121 depths) the image is sampled
    at up to :data:`TEXTURE_VERTICES` vertices; the texture at a depth is the RMS over them of
    each sample minus the mean of its :data:`TEXTURE_NEIGHBOURS` nearest (a high-pass along the
    surface: fibres and spots stand out, a smooth wall and the PSF's orientation dependence do
    not). A fibre layer peeled at the wrong depth shows as a peak outside the range.

    Parameters
    ----------
    volume : ndarray, shape (Z, Y, X)
    spacing : (dz, dy, dx)
    vertices, normals : ndarray, shape (N, 3)
        Physical x, y, z; the normals the layer is peeled along (unit length).
    d_min, d_max : float
        The layer's depth range.
    rng : int
        Seed of the vertex sample.

    Returns
    -------
    dict
        ``depths`` and ``texture`` (lists), ``peak_depth``, ``peak`` (the strongest texture),
        ``inside`` (the strongest within the range) and ``outside`` (True when the peak lies out
        of the range, exceeds :data:`TEXTURE_OUTSIDE_RATIO` × ``inside`` and is a structure:
        :data:`TEXTURE_MIN_CONTRAST`).
    """
    from scipy.spatial import cKDTree

    sp = np.asarray(check_spacing(spacing), dtype=np.float64)
    width = max(d_max - d_min, 2.0 * float(sp.max()))
    step = max(min(0.5 * float(sp.min()), 0.25 * width), (d_max - d_min + 2 * width) / 120)
    depths = np.arange(d_min - width, d_max + width + 0.5 * step, step)
    pick = np.random.default_rng(rng).permutation(len(vertices))[:TEXTURE_VERTICES]
    v, n = np.asarray(vertices, dtype=np.float64)[pick], np.asarray(normals, dtype=np.float64)[pick]
    ok = np.isfinite(n).all(axis=1)
    v, n = v[ok], n[ok]
    if len(v) <= TEXTURE_NEIGHBOURS:
        return {"depths": [], "texture": [], "peak_depth": None, "peak": None, "inside": None, "outside": False}
    _, near = cKDTree(v).query(v, k=TEXTURE_NEIGHBOURS)
    points = v[None] + depths[:, None, None] * n[None]  # (D, P, 3), x y z
    zyx = (points[..., ::-1] / sp).reshape(-1, 3).T
    values = ndimage.map_coordinates(volume, zyx, order=1, mode="nearest", output=np.float32)  # no copy of the stack
    values = values.reshape(len(depths), len(v))
    texture = np.sqrt(np.mean((values - values[:, near].mean(axis=2)) ** 2, axis=1))
    within = (depths >= d_min - 1e-9) & (depths <= d_max + 1e-9)
    k = int(np.argmax(texture))
    inside = float(texture[within].max()) if within.any() else 0.0
    mean = values.mean(axis=1)
    strong = texture[k] >= TEXTURE_MIN_CONTRAST * float(mean.max() - mean.min())
    return {"depths": np.round(depths, 6).tolist(), "texture": texture.tolist(), "peak_depth": float(depths[k]),
            "peak": float(texture[k]), "inside": inside,
            "outside": bool(not within[k] and texture[k] > TEXTURE_OUTSIDE_RATIO * inside and strong)}
