"""Tangential directors: the local fibre orientation of a layer on a surface (method note §5).

For a random subset of centre vertices (paper: 12 000), the patch of vertices within
``patch_radius`` (or the ``patch_k`` nearest) is projected onto the centre's tangent plane
(coordinates ``u = (v − c)·t1``, ``w = (v − c)·t2``) and the layer intensity is interpolated
onto a regular square grid, the *micro-image*. The gradient structure tensor of the micro-image
gives the orientation at its centre; fibres run perpendicular to the dominant gradient, i.e.
along the eigenvector of the **smallest** eigenvalue. The angle θ (from ``t1`` towards ``t2``)
is lifted to the unit director ``n = cos θ t1 + sin θ t2``.

Everything is batched over patches -- no Python loop over patches or vertices:

* neighbours: one ``cKDTree.sparse_distance_matrix`` per chunk of centres;
* micro-images: bilinear splatting of every (patch, vertex) pair into a ``(P, H, W)`` stack
  with ``np.bincount``, then normalised convolution (Gaussian of about one vertex spacing) to
  fill the gaps between vertices -- an interpolation of scattered data onto the grid;
* structure tensor: OrientationPy's recipe (Gaussian-derivative gradients with σ = 1 px,
  products integrated by a Gaussian of ``sigma`` px, ``mode="nearest"``) evaluated at the
  centre pixel only, for the whole stack at once. :func:`structure_tensor_centre` reproduces
  ``orientationpy.computeGradient`` → ``computeStructureTensor`` → ``computeOrientation`` at
  the centre pixel to machine precision (tested), without OrientationPy's per-image calls.

Data up to three pixels beyond the patch rim are gridded so that the gradients at the rim are
not those of an artificial edge; the tensor itself integrates only over the patch
(``|p| <= r``). When the integration window (``sigma``) is narrower than the patch, only what the
centre's tensor reads is gridded (:func:`support_half_width`): the same directors wherever the
layer has data; next to a gap without data (NaN) the empty pixels take the mean of the gridded
samples, so there the cut changes the fill (measured beside an 8 µm NaN band: errors 3.5-12.6°
median either way).
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pandas as pd
import trimesh
from scipy import ndimage
from scipy.spatial import cKDTree

from nemo._log import logger, step
from nemo.errors import NemoError, NemoWarning, ObjectTooSmallError
from nemo.geometry import rotate_between, tangent_frames
from nemo.mesh import mean_edge_length, object_radius

#: Default patch density: patches per patch area (the paper's 12 000 patches of 20 µm on a
#: sphere of R = 200 µm is 30 × 4πR² / (π r²)).
PATCHES_PER_AREA = 30.0

#: Default micro-image pixel as a fraction of the mean edge length (finer than the vertex
#: spacing: the σ = 1 px gradient kernel and the SIGMA_PX integration then measure the field at
#: about one edge, which keeps defect cores sharp; docs/validation.md).
PIXEL_PER_EDGE = 0.25

#: Default pixel is at least patch radius / this (micro-images of at most 195 × 195 pixels).
MAX_HALF_WIDTH_PX = 97

#: Default structure-tensor integration scale (micro-image pixels); the noise-aware default
#: (:func:`noise_aware_sigma`) starts here and widens it on noisy layers.
SIGMA_PX = 4.0

#: Director scatter (median angle between neighbouring directors, degrees: image noise or a sparse
#: texture) the noise-aware scale aims at: below it the directors are measured at :data:`SIGMA_PX`;
#: above it the window widens in proportion, up to :data:`NOISE_SIGMA_MAX_FACTOR` ×
#: (docs/validation.md "The director integration scale from the directors' own noise", session 36).
NOISE_TARGET_DEG = 8.0
#: Widest noise-aware scale, as a factor on :data:`SIGMA_PX`: wider windows pull +½ cores towards
#: their tails on clean textures (measured: 2 × was the best fixed scale on noisy frames, 3 × lost).
NOISE_SIGMA_MAX_FACTOR = 2.0
#: Smallest widening measured again: a window less than 20 % wider would make the angles at most 17 %
#: less noisy, not worth a second pass (and a defect core's place moves by chance with any change of
#: scale: docs/validation.md).
NOISE_MIN_WIDENING = 1.2
#: Neighbouring directors for :func:`director_noise`: centres this many integration scales apart
#: (their windows overlap little; the field itself turns little over so short a distance).
NOISE_PAIR_RANGE = (2.0, 3.5)
#: Fewer neighbouring pairs than this give no noise estimate (the scale stays at SIGMA_PX).
NOISE_MIN_PAIRS = 50
#: Pairs whose normals differ by more than 60° are not neighbours on the surface (the two sides of a
#: thin wall in one mesh, a fold): :func:`director_noise` leaves them out.
NOISE_MIN_NORMAL_COS = 0.5

#: Default patch radius: this fraction of the object radius sqrt(area / 4π) (the paper's 20 µm
#: on R = 200 µm), at least PATCH_MIN_EDGES mean edge lengths.
PATCH_PER_RADIUS, PATCH_MIN_EDGES = 0.1, 8.0

#: Largest micro-image half-width (pixels) accepted from user options (201 × 201 pixels): wider
#: images cost seconds and gigabytes per chunk without resolving more of the layer.
MAX_HALF_WIDTH_LIMIT = 100

#: Smallest pixel accepted, as a fraction of the mean edge length (finer over-resolves the mesh).
MIN_PIXEL_PER_EDGE = 0.1

#: Gaussian-derivative scale of the gradients (pixels), as in OrientationPy.
GRAD_SIGMA = 1.0

#: Extra gridded margin beyond the patch rim (pixels) for the gradient kernel.
_MARGIN_PX = 3

#: Fewer vertices than this in a patch gives no director.
MIN_PATCH_VERTICES = 6

#: Target size (elements) of the temporary arrays of one chunk of patches.
_CHUNK_ELEMENTS = 3_000_000


# ---------------------------------------------------------------------------------------------
# structure tensor (OrientationPy-equivalent, batched)


def _kernel_radius(sigma: float, truncate: float = 4.0) -> int:
    """Taps on each side of scipy's Gaussian kernel of ``sigma`` (its default ``truncate`` 4)."""
    return int(truncate * float(sigma) + 0.5)


def _centre_weights(n: int, sigma: float, truncate: float = 4.0) -> np.ndarray:
    """Weights of scipy's Gaussian filter (``mode="nearest"``) at the centre pixel ``n // 2``.

    ``gaussian_filter(f)[c] = Σ_x k(x) f[clip(c + x)]``, so the centre value of the filtered
    image equals ``Σ_i w[i] f[i]`` with the kernel taps folded onto the clipped indices.
    """
    radius = _kernel_radius(sigma, truncate)
    x = np.arange(-radius, radius + 1)
    k = np.exp(-0.5 * x**2 / float(sigma) ** 2)
    k /= k.sum()
    idx = np.clip(n // 2 + x, 0, n - 1)
    return np.bincount(idx, weights=k, minlength=n)


def _crop_to_reach(images: np.ndarray, mask: np.ndarray | None, reach: int) -> tuple[np.ndarray, np.ndarray | None]:
    """Images (and mask) cut to ``reach`` pixels around the centre pixel where both sides have them.

    The centre's tensor reads the gradients within the window and those the pixels within
    the gradient kernel (``reach`` = both truncated radii): nothing farther changes it.
    """
    index = [slice(None)] * 3
    for axis in (1, 2):
        n = images.shape[axis]
        c = n // 2
        if c - reach > 0 and c + reach < n - 1:
            index[axis] = slice(c - reach, c + reach + 1)
    if mask is not None:  # (P, H, W) or one (H, W) for all
        mask = np.asarray(mask)[tuple(index[-np.ndim(mask):])]
    return images[tuple(index)], mask


def structure_tensor_centre(
    images: np.ndarray,
    sigma: float,
    mask: np.ndarray | None = None,
    grad_sigma: float = GRAD_SIGMA,
) -> np.ndarray:
    """Gradient structure tensor at the centre pixel of each image of a stack.

    Parameters
    ----------
    images : ndarray, shape (P, H, W)
        Micro-images; axis 1 is the second tangent coordinate (rows), axis 2 the first.
    sigma : float
        Integration scale (pixels) of the Gaussian window (OrientationPy's ``sigma``).
    mask : ndarray of bool or float, shape (P, H, W), optional
        Pixel weights multiplying the gradient products before integration (patch disc).
    grad_sigma : float
        Scale of the Gaussian-derivative gradients (pixels); OrientationPy uses 1.

    Returns
    -------
    ndarray, shape (P, 3)
        ``(J_rr, J_rc, J_cc)`` = (row-row, row-column, column-column) components, i.e.
        OrientationPy's flattened 2-D order ``(yy, yx, xx)``.
    """
    images = np.asarray(images)
    if images.dtype != np.float32:
        images = images.astype(np.float64, copy=False)  # float32 stacks stay float32 (speed)
    if images.ndim == 2:
        images = images[None]
    images, mask = _crop_to_reach(images, mask, _kernel_radius(sigma) + _kernel_radius(grad_sigma))
    _, h, w = images.shape
    g_r = ndimage.gaussian_filter(images, grad_sigma, order=(1, 0), mode="nearest", axes=(1, 2))
    g_c = ndimage.gaussian_filter(images, grad_sigma, order=(0, 1), mode="nearest", axes=(1, 2))
    weight = np.outer(_centre_weights(h, sigma), _centre_weights(w, sigma))[None].astype(images.dtype)
    if mask is not None:
        weight = weight * mask
    out = np.empty((len(images), 3))
    wg_r = weight * g_r
    out[:, 0] = np.einsum("pij,pij->p", wg_r, g_r)
    out[:, 1] = np.einsum("pij,pij->p", wg_r, g_c)
    out[:, 2] = np.einsum("pij,pij->p", weight * g_c, g_c)
    return out


def fibre_angle(tensor: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fibre angle and coherency from 2-D structure tensors.

    Parameters
    ----------
    tensor : ndarray, shape (P, 3)
        ``(J_rr, J_rc, J_cc)`` from :func:`structure_tensor_centre`.

    Returns
    -------
    theta : ndarray, shape (P,)
        Angle (radians, in (−π/2, π/2]) of the fibre direction (eigenvector of the smallest
        eigenvalue) measured from the column axis towards the row axis. OrientationPy's 2-D
        ``theta`` (degrees, y axis pointing up the image) is ``−θ`` modulo 180°.
    coherency : ndarray, shape (P,)
        ``(λ1 − λ2) / (λ1 + λ2)`` in [0, 1]; 0 for a flat image.
    """
    j_rr, j_rc, j_cc = tensor[:, 0], tensor[:, 1], tensor[:, 2]
    gradient_angle = 0.5 * np.arctan2(2.0 * j_rc, j_cc - j_rr)  # dominant gradient, from columns
    theta = gradient_angle + np.pi / 2
    theta = np.where(theta > np.pi / 2, theta - np.pi, theta)
    trace = j_rr + j_cc
    with np.errstate(invalid="ignore", divide="ignore"):
        coherency = np.where(trace > 0, np.hypot(j_cc - j_rr, 2.0 * j_rc) / trace, 0.0)
    return theta, coherency


# ---------------------------------------------------------------------------------------------
# micro-images


def micro_images(
    u: np.ndarray,
    w: np.ndarray,
    values: np.ndarray,
    patch: np.ndarray,
    n_patches: int,
    half: int,
    pixel: float,
    smooth: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Grid scattered tangent-plane samples of many patches onto ``(P, 2h+1, 2h+1)`` images.

    Bilinear splatting followed by normalised convolution (Gaussian of ``smooth`` pixels on
    both the weighted sum and the weights), vectorised over all patches with ``np.bincount``.

    Parameters
    ----------
    u, w : ndarray, shape (M,)
        Tangent coordinates (physical) of each (patch, vertex) pair; ``u`` along ``t1``
        (image columns), ``w`` along ``t2`` (image rows).
    values : ndarray, shape (M,)
        Intensities (NaN ignored).
    patch : ndarray of int, shape (M,)
        Patch index of each pair, in ``[0, n_patches)``.
    n_patches, half : int
        Number of images and half-width ``h`` (pixels) of the grid.
    pixel : float
        Grid spacing (physical).
    smooth : float
        Gaussian (pixels) of the normalised convolution; about one vertex spacing.

    Returns
    -------
    images : ndarray of float32, shape (P, 2h+1, 2h+1)
        Interpolated intensity; pixels without data get the patch mean.
    density : ndarray of float32, shape (P, 2h+1, 2h+1)
        Smoothed sample weight per pixel (0 where no data).
    """
    size = 2 * half + 1
    fc = u / pixel + half
    fr = w / pixel + half
    ok = np.isfinite(values) & (fc >= 0) & (fc <= size - 1) & (fr >= 0) & (fr <= size - 1)
    fc, fr, values, patch = fc[ok], fr[ok], values[ok], patch[ok]
    c0 = np.minimum(np.floor(fc).astype(np.int64), size - 2)
    r0 = np.minimum(np.floor(fr).astype(np.int64), size - 2)
    a, b = fr - r0, fc - c0
    base = patch * (size * size) + r0 * size + c0
    flat = np.concatenate([base, base + size, base + 1, base + size + 1])
    wts = np.concatenate([(1 - a) * (1 - b), a * (1 - b), (1 - a) * b, a * b])
    n_pix = n_patches * size * size
    den = np.bincount(flat, weights=wts, minlength=n_pix).reshape(n_patches, size, size)
    num = np.bincount(flat, weights=wts * np.tile(values, 4), minlength=n_pix).reshape(den.shape)
    # float32 from here on: the stack is large and the precision ample
    den = ndimage.gaussian_filter(den.astype(np.float32), smooth, mode="constant", axes=(1, 2))
    num = ndimage.gaussian_filter(num.astype(np.float32), smooth, mode="constant", axes=(1, 2))
    total = den.sum(axis=(1, 2), dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = (num.sum(axis=(1, 2), dtype=np.float64) / total).astype(np.float32)
        filled = den > (1e-3 * total / (size * size)).astype(np.float32)[:, None, None]
        images = np.where(filled, num / np.where(filled, den, np.float32(1.0)), np.nan_to_num(mean)[:, None, None])
    return images, np.where(filled, den, np.float32(0.0))


# ---------------------------------------------------------------------------------------------
# directors on a mesh


def default_patch_radius(mesh: trimesh.Trimesh) -> float:
    """``PATCH_PER_RADIUS`` × the object radius, at least ``PATCH_MIN_EDGES`` mean edge lengths."""
    return max(PATCH_PER_RADIUS * object_radius(mesh), PATCH_MIN_EDGES * mean_edge_length(mesh))


def nominal_radius(mesh: trimesh.Trimesh, patch_k: int) -> float:
    """Radius of the disc holding ``patch_k`` vertices at the mesh's mean vertex density."""
    return float(np.sqrt(float(mesh.area) / len(mesh.vertices)) * np.sqrt(patch_k / np.pi))


def check_patch_size(radius: float, obj_radius: float, name: str = "patch_radius") -> None:
    """Refuse a patch wider than the object: a tangent-plane image of it would not be local.

    The limit is the object radius ``sqrt(area / 4π)`` (the default patch is a tenth of it).
    """
    if radius > obj_radius:
        raise ObjectTooSmallError(
            f"the patch (`{name}`, radius {radius:.4g}) is larger than the object itself (radius "
            f"{obj_radius:.4g} from its area): a patch must be a small, nearly flat piece of the surface. "
            f"Use a `patch_radius` well below {obj_radius:.4g} (the default is {PATCH_PER_RADIUS:g} × that, "
            f"{PATCH_PER_RADIUS * obj_radius:.3g}), or check that the mesh is in the unit of the lengths given"
        )


def default_pixel(edge: float, patch_radius: float) -> float:
    """``PIXEL_PER_EDGE`` × the mean edge length, at least ``patch_radius / MAX_HALF_WIDTH_PX``."""
    return max(PIXEL_PER_EDGE * edge, patch_radius / MAX_HALF_WIDTH_PX)


def default_n_patches(area: float, patch_radius: float, n_vertices: int) -> int:
    """``PATCHES_PER_AREA`` patches per patch area ``π r²`` of the surface, at most ``n_vertices``."""
    return int(min(n_vertices, max(1, round(PATCHES_PER_AREA * area / (np.pi * patch_radius**2)))))


def directors(
    mesh: trimesh.Trimesh,
    intensity: np.ndarray,
    patch_radius: float | None = None,
    patch_k: int | None = None,
    n_patches: int | None = None,
    pixel: float | None = None,
    sigma: float | None = None,
    frames: str = "axis",
    rng: np.random.Generator | int | None = None,
    centres: np.ndarray | None = None,
) -> pd.DataFrame:
    """Fibre directors of a layer at a random subset of vertices.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        NEMO surface (physical x, y, z; outward normals), N vertices.
    intensity : ndarray, shape (N,)
        Layer intensity per vertex (from :func:`nemo.peel.peel`); NaN values are ignored.
    patch_radius : float, optional
        Patch radius (mesh unit, µm): vertices within this 3D distance of the centre. Default
        (when ``patch_k`` is not given either) :func:`default_patch_radius`.
    patch_k : int, optional
        Patch = the ``patch_k`` nearest vertices instead (exclusive with ``patch_radius``).
    n_patches : int, optional
        Number of centres, drawn without replacement. Default :func:`default_n_patches`
        (30 per patch area; the paper's 12 000 for R = 200 µm, r = 20 µm), capped by N.
    pixel : float, optional
        Micro-image pixel (µm); default :func:`default_pixel` (a quarter of the mean edge
        length, at least ``radius / MAX_HALF_WIDTH_PX``). Refused below
        :data:`MIN_PIXEL_PER_EDGE` × the mean edge length or when the gridded micro-image
        would be wider than ``2 MAX_HALF_WIDTH_LIMIT + 1`` pixels.
    sigma : float, optional
        Structure-tensor integration scale in pixels; default :data:`SIGMA_PX`. The micro-images
        are gridded only as far as the centre's tensor reads them (:func:`support_half_width`):
        a patch narrower than the window bounds it; a wider one is cut to it.
    frames : {"axis", "smooth"}
        Tangent frames (see :func:`nemo.geometry.tangent_frames`); the directors in 3D do not
        depend on this choice.
    rng : Generator or int, optional
        Random source for the centres.
    centres : ndarray of int, optional
        Use these centre vertices instead of a random draw.

    Returns
    -------
    DataFrame
        One row per centre with a director: ``vertex``, ``x``, ``y``, ``z`` (centre),
        ``nx``, ``ny``, ``nz`` (unit director, tangent to the surface), ``coherency``
        (``(λ1 − λ2)/(λ1 + λ2)`` of the patch's structure tensor).
    """
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    n_vert = len(vertices)
    intensity = _check_intensity(intensity, n_vert)
    if patch_radius is not None and patch_k is not None:
        raise NemoError("give either a patch radius or a patch size k, not both")
    edge = mean_edge_length(mesh)
    area = float(mesh.area)
    spacing_v = np.sqrt(area / n_vert)  # typical distance between vertices
    patch_radius, patch_k, nominal = _patch_size(mesh, patch_radius, patch_k, n_vert)
    pixel = _check_pixel(pixel, edge, nominal)

    rng = np.random.default_rng(rng)
    centres = _centres(rng, centres, n_patches, area, nominal, n_vert)
    n_c = len(centres)
    tree = cKDTree(vertices)
    radii, grid_radius, half = _patch_radii(tree, vertices, centres, patch_radius, patch_k, nominal, pixel)
    sigma = SIGMA_PX if sigma is None else float(sigma)
    if not sigma > 0:
        raise NemoError(f"sigma must be > 0 pixels, got {sigma}")
    smooth = max(0.5, 0.6 * spacing_v / pixel)
    half = _check_grid(min(half, support_half_width(sigma, smooth)), grid_radius, pixel, edge)

    with step(f"frames ({frames}) for {n_c} patch centres"):
        t1, t2 = tangent_frames(mesh, frames, vertices=centres)

    size = 2 * half + 1
    with step(f"directors: {n_c} patches (r ≈ {grid_radius:.3g}, {size}×{size} px of {pixel:.3g})"):
        theta, coherency = _patch_angles(tree, vertices, intensity, centres, (t1, t2), radii, grid_radius,
                                         half, pixel, sigma, smooth, spacing_v)
    return _director_table(vertices, centres, theta, coherency, t1, t2)


#: Patches of white noise :func:`noise_coherency` measures, and the quantile it returns.
NOISE_PATCHES, NOISE_QUANTILE = 300, 0.9


def noise_coherency(mesh: trimesh.Trimesh, rng: np.random.Generator | int | None = 0,
                    n_patches: int = NOISE_PATCHES, quantile: float = NOISE_QUANTILE, **settings) -> float:
    """Coherency that white noise reaches with these patch settings: the QC's texture floor.

    A layer with no fibres (a wall without texture, a peel at a depth with nothing to see) still
    gives directors, whose coherency is that of its noise through the micro-image gridding and
    the structure tensor: about 0.3 in the median and 0.5 at the 90th percentile at the
    defaults, whatever the image. This runs :func:`directors` on i.i.d. Gaussian intensities at
    ``n_patches`` random vertices with the same ``settings`` (``patch_radius``, ``patch_k``,
    ``pixel``, ``sigma``, ``frames``) and returns the ``quantile`` of their coherency: a layer
    whose median coherency is below it shows no more orientation than noise.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The layer's surface (N vertices).
    rng : Generator or int, optional
        Random source for the noise and the centres.
    n_patches : int
        Patches measured (capped by N).
    quantile : float
        Quantile of the noise's coherency returned, in (0, 1).
    **settings
        Passed to :func:`directors`.

    Returns
    -------
    float
        The coherency quantile (NaN when no patch gave a director).
    """
    rng = np.random.default_rng(rng)
    noise = rng.standard_normal(len(mesh.vertices))
    n_patches = min(int(n_patches), len(mesh.vertices))
    with step(f"texture floor: directors of white noise at {n_patches} patches"):
        coherency = directors(mesh, noise, n_patches=n_patches, rng=rng, **settings)["coherency"].to_numpy()
    coherency = coherency[np.isfinite(coherency)]
    return float(np.quantile(coherency, quantile)) if coherency.size else math.nan


def director_noise(directors_df: pd.DataFrame, scale: float,
                   normals: np.ndarray | None = None) -> tuple[float, int]:
    """Median angle (degrees) between directors whose centres are :data:`NOISE_PAIR_RANGE` × ``scale`` apart.

    Two such directors see nearly the same field through windows that barely overlap, so their
    disagreement is the measurement's own scatter: image noise, and a texture too sparse or too
    irregular for the window (short dashes read 19-35° without any noise); the median ignores
    the few pairs near defects, where the field itself turns. With ``normals`` the second
    director of a pair is parallel-transported to the first's tangent plane
    (:func:`nemo.geometry.rotate_between`), so a curved surface adds nothing (a sphere of
    R = 40 µm adds about 2° to the raw 3D angle at one edge's scale).

    Parameters
    ----------
    directors_df : DataFrame
        Directors table (``x``, ``y``, ``z``, ``nx``, ``ny``, ``nz``), M rows.
    scale : float
        The integration scale the directors were measured at (µm: ``sigma`` × ``pixel``).
    normals : ndarray, shape (M, 3), optional
        Unit surface normals at the directors' centres.

    Returns
    -------
    noise : float
        Median head-tail-symmetric angle in [0, 90] degrees; NaN with fewer than
        :data:`NOISE_MIN_PAIRS` pairs.
    n_pairs : int
    """
    pos = directors_df[["x", "y", "z"]].to_numpy(dtype=np.float64)
    vec = directors_df[["nx", "ny", "nz"]].to_numpy(dtype=np.float64)
    nrm = np.asarray(normals, dtype=np.float64) if normals is not None else None
    ok = np.all(np.isfinite(pos), axis=1) & np.all(np.isfinite(vec), axis=1)
    if nrm is not None:
        ok &= np.all(np.isfinite(nrm), axis=1)
        nrm = nrm[ok]
    pos, vec = pos[ok], vec[ok]
    lo, hi = NOISE_PAIR_RANGE[0] * scale, NOISE_PAIR_RANGE[1] * scale
    pairs = cKDTree(pos).query_pairs(hi, output_type="ndarray") if len(pos) > 1 else np.zeros((0, 2), np.int64)
    pairs = pairs[np.linalg.norm(pos[pairs[:, 0]] - pos[pairs[:, 1]], axis=1) >= lo]
    if nrm is not None:  # not neighbours on the surface: the two sides of a thin wall, a fold
        pairs = pairs[np.einsum("ij,ij->i", nrm[pairs[:, 0]], nrm[pairs[:, 1]]) > NOISE_MIN_NORMAL_COS]
    if len(pairs) < NOISE_MIN_PAIRS:
        return math.nan, int(len(pairs))
    first, second = vec[pairs[:, 0]], vec[pairs[:, 1]]
    if nrm is not None:
        second = rotate_between(second, nrm[pairs[:, 1]], nrm[pairs[:, 0]])
    cos = np.abs(np.einsum("ij,ij->i", first, second))  # unit directors; the rotation keeps their length
    return float(np.degrees(np.median(np.arccos(np.clip(cos, 0.0, 1.0))))), int(len(pairs))


def noise_aware_sigma(noise_deg: float, max_px: float = NOISE_SIGMA_MAX_FACTOR * SIGMA_PX) -> float:
    """Integration scale (pixels) for directors whose scatter at :data:`SIGMA_PX` is ``noise_deg``.

    A structure tensor's angle noise falls about as 1 / σ (the window's area grows as σ²), so the
    scale widens in proportion to the scatter above :data:`NOISE_TARGET_DEG`, up to ``max_px``
    (default :data:`NOISE_SIGMA_MAX_FACTOR` × :data:`SIGMA_PX`: two edges at the default pixel;
    :func:`noise_aware_max_px` for another pixel); a widening below :data:`NOISE_MIN_WIDENING`, or NaN
    (no estimate), keeps SIGMA_PX.
    """
    factor = noise_deg / NOISE_TARGET_DEG if math.isfinite(noise_deg) else 1.0
    if factor < NOISE_MIN_WIDENING or max_px < NOISE_MIN_WIDENING * SIGMA_PX:
        return SIGMA_PX
    return min(SIGMA_PX * factor, max_px)


def noise_aware_max_px(edge: float, pixel: float) -> float:
    """Widest noise-aware scale (pixels of ``pixel``): :data:`NOISE_SIGMA_MAX_FACTOR` × :data:`SIGMA_PX`
    pixels of the default ¼ edge, i.e. two edges whatever the pixel (a coarser pixel given by the
    user already widens the 4 px window in µm; the target is calibrated at the default pixel)."""
    return NOISE_SIGMA_MAX_FACTOR * SIGMA_PX * PIXEL_PER_EDGE * edge / pixel


def support_half_width(sigma: float, smooth: float, grad_sigma: float = GRAD_SIGMA) -> int:
    """Half-width (pixels) of the micro-image that the centre pixel's structure tensor depends on.

    The integration window, the gradient kernel and the normalised-convolution kernel
    (``smooth``) are scipy Gaussians truncated at 4 σ; a sample splats onto the pixel next to
    it. Samples and pixels farther (Chebyshev distance) from the centre than the sum do not
    reach the tensor, so :func:`directors` grids no farther (only the fill of pixels without
    data, the mean of the gridded samples, depends on the width).

    Parameters
    ----------
    sigma, smooth, grad_sigma : float
        Integration scale, normalised-convolution scale and gradient scale (pixels).

    Returns
    -------
    int
        The half-width ``h``: the micro-images need be no wider than ``2 h + 1`` pixels.
    """
    return _kernel_radius(sigma) + _kernel_radius(grad_sigma) + _kernel_radius(smooth) + 1


def _check_grid(half: int, grid_radius: float, pixel: float, edge: float) -> int:
    """The gridded half-width ``half``, refused when wider than ``MAX_HALF_WIDTH_LIMIT`` (cost)."""
    if half > MAX_HALF_WIDTH_LIMIT:
        raise NemoError(
            f"a patch of radius {grid_radius:.3g} with `pixel` {pixel:.3g} needs micro-images of "
            f"{2 * half + 1} × {2 * half + 1} pixels (at most {2 * MAX_HALF_WIDTH_LIMIT + 1}): use "
            f"`pixel` {default_pixel(edge, grid_radius):.3g} (the default) or "
            f"at least {grid_radius / (MAX_HALF_WIDTH_LIMIT - _MARGIN_PX):.3g}, a smaller `sigma`, or a smaller patch"
        )
    return half


def _check_intensity(intensity: np.ndarray, n_vert: int) -> np.ndarray:
    """The layer as float64 (N,), refused when it does not fit the mesh or is NaN everywhere."""
    intensity = np.asarray(intensity, dtype=np.float64)
    if intensity.shape != (n_vert,):
        raise NemoError(
            f"the layer has {intensity.size} values but the mesh has {n_vert} vertices: "
            "peel the layer on this mesh"
        )
    if not np.isfinite(intensity).any():
        raise NemoError("the layer intensity is NaN everywhere: the peel range lies outside the image")
    return intensity


def _patch_size(mesh: trimesh.Trimesh, patch_radius: float | None, patch_k: int | None,
                n_vert: int) -> tuple[float | None, int | None, float]:
    """Checked ``patch_radius`` (default filled in) or ``patch_k``, and the nominal patch radius."""
    if patch_k is not None:
        patch_k = int(patch_k)
        if patch_k < MIN_PATCH_VERTICES or patch_k > n_vert:
            raise NemoError(f"patch k must be between {MIN_PATCH_VERTICES} and the {n_vert} vertices, got {patch_k}")
        nominal = nominal_radius(mesh, patch_k)
    else:
        patch_radius = default_patch_radius(mesh) if patch_radius is None else float(patch_radius)
        if not patch_radius > 0:
            raise NemoError(f"patch radius must be > 0 µm, got {patch_radius}")
        nominal = patch_radius
    check_patch_size(nominal, object_radius(mesh), "patch_radius" if patch_k is None else "patch_k")
    return patch_radius, patch_k, nominal


def _check_pixel(pixel: float | None, edge: float, nominal: float) -> float:
    """The micro-image pixel (default :func:`default_pixel`), refused when too fine or too coarse."""
    if pixel is None:  # finer than the mesh, but at most MAX_HALF_WIDTH_PX across the radius
        pixel = default_pixel(edge, nominal)
    pixel = float(pixel)
    if not pixel > 0:
        raise NemoError(f"pixel size must be > 0 µm, got {pixel}")
    if pixel < MIN_PIXEL_PER_EDGE * edge:
        raise NemoError(
            f"`pixel` {pixel:g} is below {MIN_PIXEL_PER_EDGE:g} × the mean edge length ({edge:.3g}): "
            f"the micro-image would over-resolve the mesh at great cost; use `pixel` "
            f"{PIXEL_PER_EDGE * edge:.3g} (a quarter edge, the default) or at least {MIN_PIXEL_PER_EDGE * edge:.3g}"
        )
    if nominal < 2 * pixel:
        raise NemoError(
            f"the patch (radius ≈ {nominal:.3g}) is smaller than 2 micro-image pixels "
            f"({pixel:.3g}): use a larger patch or a smaller `pixel`"
        )
    return pixel


def _centres(rng: np.random.Generator, centres: np.ndarray | None, n_patches: int | None, area: float,
             nominal: float, n_vert: int) -> np.ndarray:
    """The given centre vertices (checked), else ``n_patches`` (default from the area) drawn at random."""
    if centres is None:
        n = default_n_patches(area, nominal, n_vert) if n_patches is None else int(n_patches)
        if n < 1:
            raise NemoError(f"number of patches must be >= 1, got {n}")
        if n > n_vert:
            warnings.warn(f"{n} patches requested but the mesh has {n_vert} vertices; using all",
                          NemoWarning, stacklevel=3)
            n = n_vert
        return np.sort(rng.choice(n_vert, size=n, replace=False))
    centres = np.asarray(centres, dtype=np.int64)
    if centres.size and (centres.min() < 0 or centres.max() >= n_vert):
        raise NemoError("centre vertices out of range of the mesh")
    return centres


def _patch_radii(tree: cKDTree, vertices: np.ndarray, centres: np.ndarray, patch_radius: float | None,
                 patch_k: int | None, nominal: float, pixel: float) -> tuple[np.ndarray, float, int]:
    """Radius of each patch, the common grid radius and the micro-images' half-width (pixels).

    The grid covers the 99th percentile of the radii (``patch_k`` patches vary); larger patches
    are clipped to it. The half-width covers the grid radius plus ``_MARGIN_PX`` (before the
    cut to the tensor's support, :func:`support_half_width`).
    """
    n_c = len(centres)
    if patch_k is not None:
        dist_k, _ = tree.query(vertices[centres], k=patch_k, workers=-1)
        radii = dist_k[:, -1]
    else:
        radii = np.full(n_c, patch_radius)
    grid_radius = float(np.quantile(radii, 0.99)) if n_c else nominal
    radii = np.minimum(radii, grid_radius)
    return radii, grid_radius, int(np.ceil(grid_radius / pixel)) + _MARGIN_PX


def _patch_angles(tree: cKDTree, vertices: np.ndarray, intensity: np.ndarray, centres: np.ndarray,
                  frames: tuple[np.ndarray, np.ndarray], radii: np.ndarray, grid_radius: float, half: int,
                  pixel: float, sigma: float, smooth: float, spacing_v: float) -> tuple[np.ndarray, np.ndarray]:
    """Fibre angle θ (from ``t1`` towards ``t2``) and coherency of every patch, in chunks of centres.

    Each chunk: the (centre, vertex) pairs the micro-image grids (within the grid radius plus the
    margin, or the grid's corners when ``half`` is cut to the tensor's support), their tangent
    coordinates, the micro-images, the structure tensor at the centre pixel (inside the patch
    only) and its fibre angle. NaN for patches with too few vertices or a flat image.
    """
    t1, t2 = frames
    n_c = len(centres)
    size = 2 * half + 1
    margin = _MARGIN_PX * pixel
    reach = min(grid_radius + margin, np.sqrt(2.0) * half * pixel)  # the patch, or the grid's corners
    finite_tree = cKDTree(vertices[np.isfinite(intensity)])  # counts each whole patch's data
    pairs_per_patch = np.pi * reach**2 / spacing_v**2
    chunk = int(max(1, min(n_c, _CHUNK_ELEMENTS // max(4 * pairs_per_patch, size * size * 4))))
    theta = np.full(n_c, np.nan)
    coherency = np.full(n_c, np.nan)
    rho2 = ((np.arange(size) - half)[:, None] ** 2 + (np.arange(size) - half)[None, :] ** 2) * pixel**2
    for start in range(0, n_c, chunk):
        sl = slice(start, min(n_c, start + chunk))
        cen = centres[sl]
        ctree = cKDTree(vertices[cen])
        pairs = ctree.sparse_distance_matrix(tree, reach, output_type="ndarray")
        pi, vj = pairs["i"].astype(np.int64), pairs["j"].astype(np.int64)
        keep = pairs["v"] <= radii[sl][pi] + margin
        pi, vj = pi[keep], vj[keep]
        d = vertices[vj] - vertices[cen][pi]
        u = np.einsum("ij,ij->i", d, t1[sl][pi])
        w = np.einsum("ij,ij->i", d, t2[sl][pi])
        count = finite_tree.query_ball_point(vertices[cen], radii[sl], return_length=True, workers=-1)
        images, density = micro_images(u, w, intensity[vj], pi, len(cen), half, pixel, smooth)
        mask = (rho2[None] <= radii[sl][:, None, None] ** 2) & (density > 0)
        tensor = structure_tensor_centre(images, sigma, mask)
        th, coh = fibre_angle(tensor)
        good = (count >= MIN_PATCH_VERTICES) & (tensor[:, 0] + tensor[:, 2] > 0)
        theta[sl] = np.where(good, th, np.nan)
        coherency[sl] = np.where(good, coh, np.nan)
        logger.debug("directors chunk %d-%d: %d pairs", sl.start, sl.stop, len(vj))
    return theta, coherency


def _director_table(vertices: np.ndarray, centres: np.ndarray, theta: np.ndarray, coherency: np.ndarray,
                    t1: np.ndarray, t2: np.ndarray) -> pd.DataFrame:
    """The directors table: θ lifted to 3D, patches without a director dropped (with a warning)."""
    n_c = len(centres)
    n3 = np.cos(theta)[:, None] * t1 + np.sin(theta)[:, None] * t2
    ok = np.isfinite(theta)
    if not ok.all():
        warnings.warn(
            f"{int((~ok).sum())} of {n_c} patches gave no director (fewer than "
            f"{MIN_PATCH_VERTICES} vertices with intensity, or a flat patch)",
            NemoWarning, stacklevel=3,
        )
    pos = vertices[centres]
    return pd.DataFrame({
        "vertex": centres[ok].astype(np.int64),
        "x": pos[ok, 0], "y": pos[ok, 1], "z": pos[ok, 2],
        "nx": n3[ok, 0], "ny": n3[ok, 1], "nz": n3[ok, 2],
        "coherency": coherency[ok],
    })
