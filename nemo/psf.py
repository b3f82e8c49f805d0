"""The microscope's point spread function: undoing its blur before the analysis.

A confocal or light-sheet PSF is longer along the optical axis (z) than across it: σz is 2-3
times σxy. On a curved surface that blur is *anisotropic in the tangent plane* wherever the
normal is oblique: fibres running across the projected z axis are smeared out, the structure
tensor then reads whatever texture is left, and near a defect core whole sectors of directors
turn 30-90° (docs/validation.md, "Defect localisation under a z-elongated PSF"). The light of a
bright layer blurred along z also pulls the walls towards it at the poles and thickens a shell.

Given the PSF as Gaussian standard deviations (σz, σy, σx) in the image's unit, the stack is
deconvolved by Richardson-Lucy (:data:`DECONVOLVE_ITERATIONS` iterations) before meshing and
peeling. Measured on z-blurred vesicles (docs/validation.md, "Deconvolving a known PSF"):
deconvolving the whole PSF localises defects better than deconvolving only its extra z blur
(median 1.6 against 2.0 µm), and 30 iterations better than 10. A PSF below a quarter of a
voxel on every axis needs nothing and the stack is returned unchanged. The price: Richardson-Lucy
moves a sharpened edge towards its bright side (0.3 µm for σ 2.5 µm), so a thick, clean shell,
unbiased without it, reads 0.3 µm thinner; thin, noisy or z-blurred walls gain far more.

Without a measured PSF, ``psf: auto`` (the default) estimates the blur along z beyond the lateral
blur from the image's own autocovariance (:func:`estimate_z_blur`) and deconvolves that alone
(:func:`estimate_psf`): it is what turns the directors where the normal is oblique (docs/validation.md,
"The PSF's z blur estimated from the image"); where the image gives no estimate, or one below half a
plane, nothing is deconvolved. ``psf: none`` (or None) deconvolves nothing.
"""

from __future__ import annotations

import time

import numpy as np
from scipy import ndimage as ndi

from nemo._log import logger
from nemo.errors import NemoError

#: Richardson-Lucy iterations (measured on z-blurred vesicles at SNR ∞-5: docs/validation.md,
#: "Deconvolving a known PSF").
DECONVOLVE_ITERATIONS = 30

#: A PSF narrower than this fraction of the voxel on every axis is not deconvolved.
MIN_PSF_PER_VOXEL = 0.25

#: The ``psf`` value that estimates the PSF's z blur from the image (:func:`estimate_psf`): the default.
AUTO = "auto"

#: The ``psf`` value (as null) that deconvolves nothing.
NONE = "none"

#: :func:`estimate_z_blur`'s high-pass, in voxels along the longest axis: it removes the object's
#: large shapes (walls, whose orientations are not balanced in a cut or elongated object) and keeps
#: the texture the PSF blurs.
ESTIMATE_HIGHPASS_VOXELS = 1.5

#: Above this relative misfit the image's autocovariance is not that of an isotropic object
#: blurred along z (measured: closed and cut vesicles 0.02-0.06, a flat textured sheet 0.7):
#: no estimate.
ESTIMATE_MAX_MISFIT = 0.2

#: Above this share of the high-passed image's variance (its lag 0) the fitted white noise leaves too
#: little texture to read a blur from (images whose noise is twice their texture: 0.99, estimates
#: 20-45 % off; vesicles at SNR 3: 0.92-0.97, within 11 %; session 35).
ESTIMATE_MAX_NOISE_SHARE = 0.98

#: Above this excess of the background's correlation between neighbouring planes over that between
#: neighbouring columns (:func:`_z_noise_excess`) the noise is correlated between planes and reads as a
#: z blur: no estimate (measured, session 35: white noise under any PSF -0.02 to 0.01 on 70 images of
#: three generators; noise smoothed over 0.7-1.5 planes 0.34-0.82).
ESTIMATE_MAX_Z_NOISE = 0.1

#: ... read only where the background correlates between neighbouring columns at most this much beyond
#: white noise (a noise-dominated background: -0.05 to 0.2 with or without noise correlated in z).
ESTIMATE_Z_NOISE_MAX_LATERAL = 0.25

#: At most this many planes (rows) are used for the lateral (axial) lags, each high-passed on its
#: own (no full-size copy: 1 s for 450³ voxels on one core, where the whole stack high-passed took 12 s).
ESTIMATE_MAX_SLICES = 64

#: ... and at most about this many voxels in all (fewer, larger slices on large stacks; at least 4 slices).
ESTIMATE_MAX_VOXELS = 4_200_000

#: At most this many lags per axis, evenly spread to three high-passes (finely sampled stacks: 45 lateral lags at
#: 0.2 µm pixels and 2 µm planes).
ESTIMATE_MAX_LAGS = 16

#: The share of the object's large-scale gradient energy along z (:func:`z_facing_share`) within
#: which an object faces every way as the estimate assumes. Measured with the z blur found taken out
#: (session 35, docs/validation.md): whole vesicles of three generators 0.33-0.35, one cut at its
#: centre 0.33; shells 1.25 / 1.5 / 2 times longer along z 0.28-0.30 / 0.25-0.27 / 0.21 (read as a
#: z blur of 1.0-1.3 µm where there is none, or +15-30 %), a shell 0.8 times as tall 0.39-0.40
#: (-13 %), a vesicle cut 50 µm above its centre 0.24; earlier (session 34's review) a disc
#: standing on edge 0.14, a columnar slab 0.91.
ESTIMATE_Z_SHARE = (0.31, 0.37)

#: An extra z blur below this fraction of the plane spacing is not deconvolved: sampling in planes
#: itself blurs by 0.29 dz, and deconvolving less than that amplified noise and cost a defect on
#: a stack sampled three times coarser than its PSF (docs/validation.md).
ESTIMATE_MIN_Z_BLUR_PER_PLANE = 0.5

#: At most about this many block averages in :func:`z_facing_share`: the blocks, a third of the scale the
#: share is read at, grow on large stacks (450³ voxels: 8.9 s with blocks of one voxel, 0.6 s).
ESTIMATE_SHARE_VOXELS = 2_000_000


def is_none(psf) -> bool:
    """Whether a ``psf`` value deconvolves nothing: None (null) or ``"none"``."""
    return psf is None or (isinstance(psf, str) and psf == NONE)


def is_auto(psf) -> bool:
    """Whether a ``psf`` value is ``"auto"`` (a string, not a PSF: arrays compare element-wise)."""
    return isinstance(psf, str) and psf == AUTO


def recorded_psf(record: dict) -> list[float] | str | None:
    """The PSF a deconvolution record (:func:`deconvolve`'s) was made with, as a step is given it:
    ``"auto"`` where it was estimated, else its numbers (None: none)."""
    return AUTO if record.get("estimated") else record.get("psf")


def meshes_deconvolved(psf, edge: str) -> bool:
    """Whether the mesh step meshes the image deconvolved by ``psf`` under ``mesh.edge: edge``: not for
    none, nor for ``auto`` under ``profile`` (its blurred boxes fit the image's own walls)."""
    psf = check_psf(psf)
    return psf is not None and not (is_auto(psf) and edge == "profile")


def is_per_channel(spec) -> bool:
    """Whether a ``psf`` setting lists one PSF per channel (a list of PSFs or nulls), not one PSF."""
    return isinstance(spec, (list, tuple)) and len(spec) > 0 and all(
        is_none(item) or is_auto(item) or isinstance(item, (list, tuple)) for item in spec)


def check_psf_spec(spec, name: str = "psf"):
    """A ``psf`` setting: None, one PSF for every channel (σz, σy, σx) or ``"auto"``, or one per channel.

    Parameters
    ----------
    spec : None, "none", "auto", sequence of 3 numbers, or sequence of (3 numbers, "auto" or None)
        The last form gives channel c the PSF ``spec[c]`` (None or "none": that channel is not
        deconvolved); ``"auto"`` estimates it from the image (:func:`estimate_psf`).
    name : str
        The config key or option, for the message.

    Returns
    -------
    None, "auto", tuple of 3 floats, or list of (tuple of 3 floats, "auto" or None)
    """
    if not is_per_channel(spec):
        return check_psf(spec, name)
    return [check_psf(item, f"{name}[{c}]") for c, item in enumerate(spec)]


def channel_psf(spec, c: int, name: str = "psf") -> tuple[float, float, float] | str | None:
    """The PSF of channel ``c`` under a ``psf`` setting (:func:`check_psf_spec`).

    Raises
    ------
    NemoError
        A per-channel list without an entry for channel ``c`` (the message names the fix).
    """
    spec = check_psf_spec(spec, name)
    if not isinstance(spec, list):
        return spec
    if not 0 <= c < len(spec):
        raise NemoError(f"{name} lists a PSF for channels 0 to {len(spec) - 1}, not for channel {c}: give one "
                        f"per channel, in channel order (null for a channel not to deconvolve)")
    return spec[c]


def check_psf(psf, name: str = "psf") -> tuple[float, float, float] | str | None:
    """``psf`` as three non-negative floats (σz, σy, σx), ``"auto"`` or None; a wrong value is named.

    Parameters
    ----------
    psf : sequence of 3 numbers, "auto", "none" or None (None and "none": not deconvolved)
    name : str
        What the caller calls it (a config key or an option), for the message.
    """
    if is_none(psf):
        return None
    if is_auto(psf):
        return psf
    try:
        values = tuple(float(v) for v in psf)
    except (TypeError, ValueError):
        raise NemoError(f"{name} must be three numbers σz σy σx (the PSF's standard deviations in the "
                        f"image's unit), auto (estimated from the image) or none, got {psf!r}") from None
    if len(values) != 3 or not all(np.isfinite(values)) or min(values) < 0:
        raise NemoError(f"{name} must be three numbers σz σy σx ≥ 0 (the PSF's standard deviations in the "
                        f"image's unit), got {psf!r}")
    return values


def _kept_slices(shape: tuple[int, ...], axis: int) -> np.ndarray:
    """Evenly spaced slices along ``axis`` for the lag covariances: :data:`ESTIMATE_MAX_SLICES`, fewer
    where they would hold more than :data:`ESTIMATE_MAX_VOXELS` voxels (at least 4)."""
    per_slice = int(np.prod(shape)) // shape[axis]
    count = min(ESTIMATE_MAX_SLICES, max(4, ESTIMATE_MAX_VOXELS // max(per_slice, 1)), shape[axis])
    return np.unique(np.linspace(0, shape[axis] - 1, count).astype(int))


def _gaussian_taps(sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Offsets and normalised weights of scipy's Gaussian kernel of σ voxels (truncated at 4 σ)."""
    radius = int(4 * sigma + 0.5)  # scipy's default truncation
    offsets = np.arange(-radius, radius + 1)
    kernel = np.exp(-0.5 * (offsets / max(sigma, 1e-9)) ** 2)
    return offsets, kernel / kernel.sum()


def _highpassed_slices(volume: np.ndarray, sigma_vox: tuple[float, float, float], axis: int,
                       keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``volume`` minus its Gaussian blur (σ in voxels, edges repeated), at the slices ``keep`` along
    ``axis`` only, and that blur: the blur along ``axis`` is summed over each kept slice's
    neighbours, so no full-size copy of the stack is made (the cost bound on large stacks)."""
    offsets, kernel = _gaussian_taps(sigma_vox[axis])
    n = volume.shape[axis]
    sub = np.take(volume, keep, axis=axis).astype(np.float32)
    low = np.zeros_like(sub)
    for offset, weight in zip(offsets, kernel):  # a loop over the kernel's taps (≤ 4σ each side)
        low += weight * np.take(volume, np.clip(keep + offset, 0, n - 1), axis=axis).astype(np.float32)
    others = tuple(0.0 if a == axis else s for a, s in enumerate(sigma_vox))
    low = ndi.gaussian_filter(low, others, mode="nearest")
    sub -= low
    return sub - sub.mean(), low


def _z_noise_excess(planes: tuple[np.ndarray, np.ndarray], rows: tuple[np.ndarray, np.ndarray],
                    noise: np.ndarray) -> float | None:
    """How much more the background's high-passed image correlates between neighbouring planes than
    between neighbouring columns, beyond what white noise does (``noise``: :func:`_highpassed_noise` at
    the lateral lags 0, 1 and the axial lag 1): ~0 for white noise whatever the PSF (the PSF blurs the
    object, not the noise), 0.3-0.8 for noise correlated between planes (a denoised or z-resampled
    stack). The background: voxels whose blur is below a tenth of the way from the 20th to the 99.5th
    percentile; None where fewer than 1000 pairs of it, or where it correlates between columns more
    than white noise by :data:`ESTIMATE_Z_NOISE_MAX_LATERAL` (no noise there to read: the object's
    blurred halo at high SNR read 0.44-0.91, and its difference along z could reach the limit)."""
    (hp_p, low_p), (hp_r, low_r) = planes, rows
    lo, hi = np.percentile(low_p, [20, 99.5])
    level = lo + 0.1 * (hi - lo)
    in_p, in_r = low_p < level, low_r < level
    along_x, along_z = in_p[:, :, :-1] & in_p[:, :, 1:], in_r[:-1] & in_r[1:]
    if along_x.sum() < 1000 or along_z.sum() < 1000:
        return None

    def correlation(a: np.ndarray, b: np.ndarray) -> float:
        return float(np.sum(a * b) / max(np.sqrt(np.sum(a * a) * np.sum(b * b)), 1e-30))

    excess_x = correlation(hp_p[:, :, :-1][along_x], hp_p[:, :, 1:][along_x]) - noise[1] / noise[0]
    excess_z = correlation(hp_r[:-1][along_z], hp_r[1:][along_z]) - noise[2] / noise[0]
    if not np.isfinite(excess_z - excess_x) or excess_x > ESTIMATE_Z_NOISE_MAX_LATERAL:
        return None  # the background is not noise: the object's blurred halo, or a noise-free image
    return float(excess_z - excess_x)


def _lags(n: int) -> np.ndarray:
    """At most :data:`ESTIMATE_MAX_LAGS` lags, evenly spread over 1 … ``n`` voxels."""
    return np.unique(np.round(np.linspace(1, n, min(n, ESTIMATE_MAX_LAGS))).astype(int))


def _lag_covariances(hp: np.ndarray, axis: int, lags: np.ndarray) -> np.ndarray:
    """Covariance of ``hp`` (zero mean) with itself shifted by each of ``lags`` voxels along ``axis``."""
    n = hp.shape[axis]

    def part(start: int, stop: int) -> np.ndarray:
        index = [slice(None)] * hp.ndim
        index[axis] = slice(start, stop)
        return hp[tuple(index)]  # a view

    return np.array([np.mean(part(0, n - k) * part(k, n)) for k in lags])


def _highpassed_noise(sigma_vox: tuple[float, float, float], lat_lags: np.ndarray, ax_lags: np.ndarray) -> np.ndarray:
    """White noise's covariance (per unit variance) at the lateral (x, y averaged) and axial lags, in
    voxels, after the high-pass ``n − G * n`` by scipy's Gaussian kernels of σ ``sigma_vox``:
    δ − 2 G + G * G (1 − 2 G(0) + G * G(0) at lag 0, negative at a voxel and more)."""
    kernels = [(g, np.convolve(g, g)) for g in (_gaussian_taps(s)[1] for s in sigma_vox)]

    def at(kernel: np.ndarray, shift: int) -> float:
        centre = len(kernel) // 2
        return float(kernel[centre + shift]) if abs(shift) <= centre else 0.0

    def along(axis: int, lag: int) -> float:
        once, twice = (np.prod([at(pair[i], lag if a == axis else 0) for a, pair in enumerate(kernels)]) for i in (0, 1))
        return float(lag == 0) - 2 * once + twice

    return np.array([(along(2, k) + along(1, k)) / 2 for k in lat_lags] + [along(0, k) for k in ax_lags])


def _z_blur_fit(beta: float, lateral: np.ndarray, axial: np.ndarray, widths: np.ndarray, noise: np.ndarray,
                cov: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, float]:
    """Weighted residual, and the noise's share of the lag 0, of the least-squares fit of an isotropic
    autocovariance Σ a_j exp(−r² / 2 w_j²)
    (a_j ≥ 0), blurred along z by a Gaussian of variance 2 β, plus high-passed white noise's (``noise``,
    its amplitude ≥ 0), to the measured lateral and axial lag covariances."""
    from scipy.optimize import nnls

    w2 = widths**2
    factor = np.sqrt(w2 / (w2 + 2 * beta))  # the z blur's share of each component's peak
    model = np.hstack([np.vstack([factor * np.exp(-lateral[:, None] ** 2 / (2 * w2)),
                                  factor * np.exp(-axial[:, None] ** 2 / (2 * (w2 + 2 * beta)))]), noise[:, None]])
    amplitudes, _ = nnls(model * weights[:, None], cov * weights)
    return (model @ amplitudes - cov) * weights, float(amplitudes[-1] * noise[0] / max(model[0] @ amplitudes, 1e-12))


def z_facing_share(volume: np.ndarray, spacing, scale: float, z_blur: float = 0.0) -> float:
    """Share of the image's gradient energy along z, Σ (∂I/∂z)² / Σ |∇I|², at ``scale`` (the image
    block-averaged to about scale / 3 and blurred by ``scale``, in the image's unit, each axis to the
    same total with its blocks): 1/3 for an object that faces every way, less for one longer along z
    or cut by the stack's top or bottom, more for one wider than tall. ``z_blur`` (β, the image's
    unit squared) is added to the lateral axes' blur, so that an object blurred along z by β beyond
    the lateral reads as it would without it."""
    from skimage.measure import block_reduce

    volume = np.asarray(volume)
    extent = float(np.prod([n * float(d) for n, d in zip(volume.shape, spacing)]))
    block = max(scale / 3, (extent / ESTIMATE_SHARE_VOXELS) ** (1 / 3))  # the cost bound on large stacks
    blocks = tuple(max(1, int(block / float(d))) for d in spacing)
    whole = tuple(slice(0, n - n % b) for n, b in zip(volume.shape, blocks))  # block_reduce pads with zeros: an edge
    reduce = np.nanmean if volume.dtype.kind == "f" and np.isnan(volume).any() else np.mean
    coarse = block_reduce(volume[whole], blocks, reduce).astype(np.float32)  # no full-size copy
    step = [float(d) * b for d, b in zip(spacing, blocks)]
    # a block of width w blurs its axis by w² / 12: each axis blurred to the same total
    extra = [0.0, z_blur, z_blur]
    sigma = [np.sqrt(scale**2 + e + (max(step) ** 2 - s**2) / 12) / s for s, e in zip(step, extra)]
    smooth = ndi.gaussian_filter(coarse, sigma, mode="nearest")
    grads = np.gradient(smooth, *step) if min(smooth.shape) > 1 else [np.zeros(1)] * 3
    energy = [float(np.sum(g.astype(np.float64) ** 2)) for g in grads]
    return energy[0] / sum(energy) if sum(energy) > 0 else float("nan")


def estimate_z_blur(volume: np.ndarray, spacing) -> dict:
    """The PSF's blur along z beyond its lateral blur, β = σz² − σxy², from the image itself.

    The image's autocovariance is fitted as that of an object whose own autocovariance is
    isotropic (a closed or cut vesicle, an organoid: its walls and texture face every way),
    Σ a_j exp(−r² / 2 w_j²) with a_j ≥ 0, blurred along z by a Gaussian of variance 2 β, plus the
    image's white noise (:func:`_highpassed_noise`: its share, ``noise_share``, set by the lag 0;
    the misfit is read at the lags of one voxel and more); β is the best fit's on a grid to
    (3 dz)². The image is high-passed first (:data:`ESTIMATE_HIGHPASS_VOXELS`). Noise above
    :data:`ESTIMATE_MAX_NOISE_SHARE` of the variance leaves too little texture, and noise correlated
    between planes (:data:`ESTIMATE_MAX_Z_NOISE`) reads as a z blur: no estimate. An object whose
    autocovariance is not isotropic gives no estimate: a flat sheet misfits; an object longer along
    z, or cut by the stack's top or bottom, fits as well as a z blur would, so the share of its
    large-scale gradients along z (:func:`z_facing_share`, at three times the blur found and at
    least twice the high-pass) must lie within :data:`ESTIMATE_Z_SHARE`; a best fit at the top of
    the grid is refused too.

    Parameters
    ----------
    volume : ndarray, shape (Z, Y, X)
    spacing : (dz, dy, dx)

    Returns
    -------
    dict
        ``beta`` (µm², None without an estimate), ``misfit`` (relative), ``noise_share``,
        ``z_share`` (:func:`z_facing_share`), ``z_noise`` (:func:`_z_noise_excess`), ``reason``
        (None, or why there is no estimate).
    """
    dz, dy, dx = (float(v) for v in spacing)
    volume = np.asarray(volume)
    low, high = (float(volume.min()), float(volume.max())) if volume.size else (0.0, 0.0)  # no full-size copy
    if volume.dtype.kind == "f" and not (np.isfinite(low) and np.isfinite(high)):
        finite = np.isfinite(volume)
        volume = np.where(finite, volume, volume[finite].mean() if finite.any() else 0.0)
        low, high = (float(volume.min()), float(volume.max()))
    peak = max(abs(low), abs(high))
    if volume.dtype.kind == "f" and (peak > 1e15 or 0 < peak < 1e-15):  # beyond float32's comfortable range
        volume = volume / peak
    highpass = ESTIMATE_HIGHPASS_VOXELS * max(dz, dy, dx)
    none = {"beta": None, "misfit": None, "noise_share": None, "z_share": None, "z_noise": None}
    if min(volume.shape) < 8:
        return {**none, "reason": f"the stack is too small ({volume.shape}) to estimate a PSF"}
    sigma_vox = (highpass / dz, highpass / dy, highpass / dx)
    planes = _highpassed_slices(volume, sigma_vox, 0, _kept_slices(volume.shape, 0))
    rows = _highpassed_slices(volume, sigma_vox, 1, _kept_slices(volume.shape, 1))
    lat_lags = np.concatenate([[0], _lags(min(int(np.ceil(3 * highpass / min(dx, dy))), volume.shape[2] // 2,
                                              volume.shape[1] // 2))])  # lag 0: the noise's own variance
    ax_lags = _lags(min(max(3, int(np.ceil(3 * highpass / dz))), volume.shape[0] // 2))
    n_lat, n_ax = len(lat_lags), len(ax_lags)
    lateral, axial = lat_lags * (dx + dy) / 2, ax_lags * dz
    z_noise = _z_noise_excess(planes, rows, _highpassed_noise(sigma_vox, np.array([0, 1]), np.array([1])))
    none["z_noise"] = None if z_noise is None else round(z_noise, 4)
    cov = np.concatenate([(_lag_covariances(planes[0], 2, lat_lags) + _lag_covariances(planes[0], 1, lat_lags)) / 2,
                          _lag_covariances(rows[0], 0, ax_lags)])
    del planes, rows
    if z_noise is not None and z_noise > ESTIMATE_MAX_Z_NOISE:
        return {**none, "reason": f"the background's noise is correlated between planes ({z_noise:.3f} more than "
                                  f"between columns, above {ESTIMATE_MAX_Z_NOISE}): a denoised or z-resampled stack "
                                  "reads as a z blur; give the PSF, datasets.NAME.psf, or none"}
    if not np.isfinite(cov).all() or cov[1:].max() <= 0:  # no covariance beyond the noise's own variance
        return {**none, "reason": "the image has no texture to estimate a PSF from"}
    cov = cov / cov.max()
    weights = np.concatenate([np.ones(n_lat), np.full(n_ax, np.sqrt((n_lat - 1) / n_ax))])  # each axis alike
    widths = np.geomspace(0.5 * min(dx, dy), 3 * highpass, 10)
    betas = np.linspace(0.0, (3 * dz) ** 2, 301)
    noise = _highpassed_noise(sigma_vox, lat_lags, ax_lags)
    # the fit takes the noise's share from the lag 0; the misfit is read at the lags of a voxel and more
    fits = [_z_blur_fit(b, lateral, axial, widths, noise, cov, weights) for b in betas]
    misfits = [np.linalg.norm(residual[1:]) for residual, _ in fits]
    best = int(np.argmin(misfits))
    noise_share = fits[best][1]
    misfit = float(misfits[best] / np.linalg.norm((cov * weights)[1:]))
    out = {**none, "misfit": round(misfit, 4), "noise_share": round(noise_share, 4)}
    if noise_share > ESTIMATE_MAX_NOISE_SHARE:
        return {**out, "reason": f"the noise is {100 * noise_share:.1f} % of the high-passed image's variance: too "
                                 "little texture to read a blur from"}
    if misfit > ESTIMATE_MAX_MISFIT:
        return {**out, "reason": f"the image's autocovariance is not that of an isotropic object blurred along z "
                                 f"(misfit {misfit:.2f} > {ESTIMATE_MAX_MISFIT}: a flat sheet, or too little texture "
                                 f"for the noise)"}
    if best == len(betas) - 1:
        return {**out, "reason": "the best fit is at the search's limit, a z blur of 3 planes (an object longer "
                                 "along z, or a stack sampled finely in z: give the PSF, datasets.NAME.psf)"}
    share = z_facing_share(volume, spacing, max(2 * highpass, 3 * np.sqrt(betas[best])), z_blur=float(betas[best]))
    out["z_share"] = round(share, 4)
    low, high = ESTIMATE_Z_SHARE
    if not low <= share <= high:
        why = "longer along z than across, or cut by the stack's top or bottom?" if share < low else (
            "wider than tall, or cut by the stack's sides?")
        return {**out, "reason": f"the object does not face every way: {share:.2f} of its gradients run along z, "
                                 f"outside [{low}, {high}] ({why})"}
    return {**out, "beta": float(f"{betas[best]:.6g}"), "reason": None}  # any unit: six digits


def estimate_psf(volume: np.ndarray, spacing) -> tuple[tuple[float, float, float] | None, dict]:
    """The PSF ``psf: auto`` deconvolves by: the z blur beyond the lateral blur, from the image.

    σz = √β with β from :func:`estimate_z_blur`, and no lateral blur (which the object's own
    texture hides). None where there is no estimate, or where √β is below
    :data:`ESTIMATE_MIN_Z_BLUR_PER_PLANE` × dz (nothing worth deconvolving).

    Returns
    -------
    psf : (σz, 0, 0) in the image's unit, or None (not deconvolved)
    estimate : dict
        :func:`estimate_z_blur`'s record; ``reason`` says why the PSF is None.
    """
    dz = float(spacing[0])
    estimate = estimate_z_blur(volume, spacing)
    if estimate["beta"] is None:
        return None, estimate
    sigma_z = float(np.sqrt(estimate["beta"]))
    if sigma_z < ESTIMATE_MIN_Z_BLUR_PER_PLANE * dz:
        return None, {**estimate, "reason": f"the z blur beyond the lateral, {sigma_z:.3g}, is below "
                                            f"{ESTIMATE_MIN_Z_BLUR_PER_PLANE} × the planes' {dz:g}: nothing to deconvolve"}
    return (float(f"{sigma_z:.6g}"), 0.0, 0.0), estimate


def richardson_lucy_gaussian(volume: np.ndarray, sigma_vox: tuple[float, float, float],
                             iterations: int = DECONVOLVE_ITERATIONS) -> np.ndarray:
    """Richardson-Lucy deconvolution of a non-negative stack by a Gaussian PSF.

    Hand-written rather than ``skimage.restoration.richardson_lucy``: that one convolves with a
    dense kernel array by FFT, while a Gaussian PSF is separable; ``ndimage``'s separable filter
    needs no kernel array and is faster (30 iterations on 4 M voxels: 6.2 against 8.1 s).

    Parameters
    ----------
    volume : ndarray, shape (Z, Y, X)
        Non-negative intensities.
    sigma_vox : (float, float, float)
        The PSF's standard deviations in voxels along (z, y, x); 0 = no blur on that axis.
    iterations : int

    Returns
    -------
    ndarray of float32, shape (Z, Y, X)
        The estimate, in the intensity units of ``volume``.
    """
    observed = np.asarray(volume, dtype=np.float32)
    tiny = np.float32(1e-6 * max(float(observed.max()), 1e-30))
    estimate = observed.copy()
    for _ in range(iterations):  # the PSF is symmetric: its mirror is itself
        blurred = ndi.gaussian_filter(estimate, sigma_vox, mode="nearest")
        ratio = observed / np.maximum(blurred, tiny)
        estimate *= ndi.gaussian_filter(ratio, sigma_vox, mode="nearest")
    return estimate


def _prepared(volume: np.ndarray) -> tuple[np.ndarray, float, np.ndarray | None]:
    """A float32 copy for the deconvolution, the factor it was divided by, the non-finite voxels.

    NaN or infinite voxels (no data) take the value of the nearest finite voxel for the
    deconvolution and are put back as NaN after it; values beyond float32's range are scaled as
    the mesh step scales them (:func:`nemo.surface._float32_safe`; the deconvolution is linear in
    the intensities).
    """
    from nemo.surface import _float32_safe

    vol = np.asarray(volume)
    missing = None
    if np.issubdtype(vol.dtype, np.inexact):
        finite = np.isfinite(vol)
        if not finite.any():
            raise NemoError("the image has no finite voxel (all NaN or infinite): nothing to deconvolve; "
                            "check the file, the time point and the channel")
        if not finite.all():
            missing = ~finite
            vol = vol[tuple(ndi.distance_transform_edt(missing, return_distances=False, return_indices=True))]
    if vol.min() == vol.max():  # constant: nothing to scale (and nothing to sharpen)
        return vol.astype(np.float32), 1.0, missing
    vol, scale = _float32_safe(vol)
    return np.asarray(vol, dtype=np.float32), scale, missing


def deconvolve(volume: np.ndarray, spacing, psf, iterations: int = DECONVOLVE_ITERATIONS) -> tuple[np.ndarray, dict]:
    """The stack deconvolved by a Gaussian PSF (module docstring).

    Parameters
    ----------
    volume : ndarray, shape (Z, Y, X)
        One channel of one time point.
    spacing : (float, float, float)
        Voxel size (dz, dy, dx) in the image's unit.
    psf : (float, float, float), "auto", "none" or None
        The PSF's standard deviations (σz, σy, σx) in the image's unit; ``"auto"`` (the workflow's
        default) estimates its z blur from ``volume`` (:func:`estimate_psf`); None or ``"none"``:
        nothing deconvolved.
    iterations : int
        Richardson-Lucy iterations.

    Returns
    -------
    volume : ndarray, shape (Z, Y, X)
        Float32 where deconvolved (NaN where ``volume`` was not finite); ``volume`` itself where
        nothing was to be done.
    record : dict
        ``psf``, ``sigma_voxels`` (the PSF in voxels), ``estimated`` (``psf`` was ``"auto"``) and
        ``estimate`` (:func:`estimate_psf`'s record, or None), ``iterations`` (0 if none), ``seconds``.
    """
    psf, estimate = check_psf(psf), None
    estimated = is_auto(psf)
    if estimated:
        psf, estimate = estimate_psf(volume, spacing)
        logger.info("psf: auto: %s", f"z blur {psf[0]:g} estimated" if psf else estimate["reason"])
    if psf is None:
        return volume, {"psf": None, "sigma_voxels": None, "estimated": estimated, "estimate": estimate,
                        "iterations": 0, "seconds": 0.0}
    if not (isinstance(iterations, (int, np.integer)) and not isinstance(iterations, bool) and iterations >= 1):
        raise NemoError(f"iterations must be a whole number ≥ 1, got {iterations!r}")
    sigma_vox = tuple(float(s) / float(d) for s, d in zip(psf, spacing))
    for axis, sv, n, s in zip("zyx", sigma_vox, np.shape(volume), psf):
        if sv > n / 2:
            raise NemoError(f"psf σ{axis} {s:g} is {sv:.3g} voxels, more than half the stack's {n} along {axis}: "
                            "give the PSF's standard deviations in the image's unit (FWHM / 2.355), e.g. µm")
    record = {"psf": list(psf), "sigma_voxels": list(sigma_vox), "estimated": estimated, "estimate": estimate,
              "iterations": 0, "seconds": 0.0}
    if max(sigma_vox) < MIN_PSF_PER_VOXEL:
        logger.info("PSF σ %s is below %.2g voxel on every axis: nothing to deconvolve", psf, MIN_PSF_PER_VOXEL)
        return volume, record
    start = time.perf_counter()
    vol, scale, missing = _prepared(volume)
    low = float(vol.min())
    out = richardson_lucy_gaussian(vol - low if low < 0 else vol, sigma_vox, iterations)  # needs data ≥ 0
    if low < 0:
        out += low
    if scale != 1.0:
        out *= np.float32(scale)
    if missing is not None:
        out[missing] = np.nan  # no data there, as before: peel leaves those vertices NaN
    record.update(iterations=int(iterations), seconds=round(time.perf_counter() - start, 3))
    logger.info("deconvolved by the PSF σ %s (%s voxels), %d Richardson-Lucy iterations, %.1f s", psf,
                " ".join(f"{v:.3g}" for v in sigma_vox), iterations, record["seconds"])
    return out, record


#: Format tag of a deconvolved stack written by :func:`write_deconvolved`.
DECONVOLVED_FORMAT = "nemo-deconvolved/1"


def write_deconvolved(path, deconvolved: np.ndarray, record: dict, source: np.ndarray,
                      spacing, t: int, c: int, image: str) -> None:
    """Write one channel's deconvolution (:func:`deconvolve`) for the mesh and peel steps to reuse.

    A float32 TIFF whose description holds the record, the spacing, the frame and the source
    stack's shape. When nothing was deconvolved (``record["iterations"]`` 0: no PSF, or one
    below :data:`MIN_PSF_PER_VOXEL`), only the record is written and the readers use the image
    itself, as :func:`deconvolve` returns it. Written atomically.

    Parameters
    ----------
    path : path-like
        Output ``.tif``.
    deconvolved : ndarray, shape (Z, Y, X)
    record : dict
        :func:`deconvolve`'s record.
    source : ndarray, shape (Z, Y, X)
        The stack that was deconvolved (its shape and a digest of its voxels are checked on reading).
    spacing : (dz, dy, dx)
    t, c : int
    image : str
        The image file, for the messages.
    """
    import json

    import tifffile

    from nemo.atomic import atomic_path

    data = np.asarray(deconvolved, dtype=np.float32) if record["iterations"] else np.zeros((1, 1, 1), np.float32)
    meta = {"format": DECONVOLVED_FORMAT, "record": record, "shape": [int(n) for n in np.shape(source)],
            "spacing": [float(v) for v in spacing], "t": int(t), "c": int(c), "image": str(image),
            "source": _fingerprint(source)}
    with atomic_path(path, keep_suffix=True) as tmp:
        tifffile.imwrite(tmp, data, description=json.dumps(meta), metadata=None)


def _fingerprint(volume: np.ndarray) -> str:
    """BLAKE2b digest of a stack's dtype, shape and voxels: tells another image of the same shape
    from this one, exactly and on any machine (a float sum could differ between CPUs)."""
    import hashlib

    vol = np.asarray(volume)
    digest = hashlib.blake2b(f"{vol.dtype.str}{vol.shape}".encode(), digest_size=16)
    for plane in vol:  # plane by plane: no copy of the stack
        digest.update(np.ascontiguousarray(plane).tobytes())
    return digest.hexdigest()


def read_deconvolved(path, volume: np.ndarray, spacing, psf, t: int, c: int) -> tuple[np.ndarray, dict]:
    """The deconvolution :func:`write_deconvolved` wrote for this stack, checked against it.

    Parameters
    ----------
    path : path-like
    volume : ndarray, shape (Z, Y, X)
        The stack read from the image (returned when the file records no deconvolution).
    spacing : (dz, dy, dx)
    psf : (σz, σy, σx) or "auto"
        The PSF the caller was given: it must be the file's (``"auto"``: the file's was estimated).
    t, c : int
        The frame the caller analyses: it must be the file's.

    Returns
    -------
    (ndarray, dict)
        The deconvolved stack, shape (Z, Y, X), and its record, as :func:`deconvolve` returns them.

    Raises
    ------
    NemoError
        Not such a file, or made for another frame, shape, spacing, PSF or image (the message names it).
    """
    import json

    import tifffile

    try:
        with tifffile.TiffFile(path) as tif:
            try:
                meta = json.loads(tif.pages[0].description or "{}")
            except ValueError:  # another TIFF's description (ImageJ's, OME-XML)
                meta = {}
    except (OSError, ValueError, tifffile.TiffFileError) as exc:
        raise NemoError(f"cannot read the deconvolved stack {path}: {exc}; make it with nemo deconvolve") from None
    if not (isinstance(meta, dict) and meta.get("format") == DECONVOLVED_FORMAT):
        raise NemoError(f"{path} is not a deconvolved stack written by nemo deconvolve: make it with nemo deconvolve")
    given = check_psf(psf)
    made = {"the frame": ([meta["t"], meta["c"]], [int(t), int(c)]),
            "the PSF": (recorded_psf(meta["record"]), given if given is None or is_auto(given) else list(given)),
            "the stack's shape": (meta["shape"], [int(n) for n in np.shape(volume)]),
            "the spacing": (meta["spacing"], [float(v) for v in spacing])}
    fix = "run nemo deconvolve again with this step's image, --t, --c, --spacing and --psf"
    for what, (theirs, ours) in made.items():
        if theirs != ours:
            raise NemoError(f"the deconvolved stack {path} was made for {what} {theirs}, this step has {ours}: {fix}")
    if meta.get("source") != _fingerprint(volume):
        raise NemoError(f"the deconvolved stack {path} was made from another image ({meta['image']}): its voxels "
                        f"differ from this step's: {fix}")
    if not meta["record"]["iterations"]:
        return volume, meta["record"]
    return tifffile.imread(path), meta["record"]  # read once the description says it is this frame's
