"""Synthetic nematic vesicles with known defects: the ground truth for NEMO's validation.

A sphere of radius ``R`` carries a tangential nematic film of fibres. The director field is the
paper's construction (method note §8, paper "Synthetic image generation"): map the unit sphere
to the complex plane by stereographic projection from the south pole, ``w = (x + iy)/(1 + z)``,
take the planar angle ``psi(w) = phase + sum_k m_k arg(w - w_k)`` for defects at ``w_k`` with
charges ``m_k`` (the paper: four ``+1/2``), and lift the planar direction back onto the tangent
plane with the differential of the (conformal) inverse projection.

Projection pole
---------------
The formula needs every defect to sit at a finite ``w_k``, i.e. away from the projection pole,
and it is numerically best when the pole is far from all defects. :func:`director_field`
therefore rotates the sphere internally so that the projection pole is the point *farthest from
all defects* (:func:`projection_pole`) unless a pole is given. Near the projection pole (where
``|w|`` is huge) the field is evaluated in the second chart ``w~ = 1/w = (x - iy)/(1 - z)``,
with the angle transformed exactly by the holomorphic change of chart
(``psi~ = psi + arg(-1/w^2) = phase + pi + sum_k m_k arg(1 - w_k w~)``), so the field is smooth
there too: with ``sum m_k = 2`` the pole is a regular point.

Because the field is the direction field of the quadratic differential
``prod_k (w - w_k)^(-2 m_k) dw^2``, which is unique up to a constant complex factor, the choice
of projection pole (and of the internal rotation) changes the field only by a *constant*
rotation of every director in its tangent plane -- the same as changing ``phase``. Defect
positions and charges never depend on it. The pole and phase used are stored in the truth so
that :func:`truth_directors` reproduces the exact analytic field of a generated image.

Images
------
:func:`vesicle` traces bidirectional streamlines of the field as fibres (vectorised over all
seeds, RK2 on the sphere), rasterises them at the physical voxel size (anisotropic allowed) on a
sphere of radius ``R + depth`` (a *layer*), adds a constant background in the shell
``R <= r <= R + shell_thickness`` (blurred analytically, so its inner edge sits exactly at ``R``
at half the background level), blurs with a Gaussian of ``blur`` µm (one sigma, or
``(sigma_z, sigma_y, sigma_x)`` for a confocal-like PSF elongated along z), scales to 0-255,
adds optional shot noise (Poisson, ``photons`` at the 255 level) and Gaussian noise, optionally
cuts the stack above the centre (``cut_top``: an open surface) and stores uint8
``(T, Z, C, Y, X)``. :func:`write_vesicle` writes an ImageJ hyperstack plus a sidecar
``NAME.truth.json``.

Signal-to-noise ratio
---------------------
One definition throughout (:func:`snr`, recorded in the truth): ``SNR = (signal - background) /
sigma(background)`` on the 0-255 scale, where ``sigma(I)^2 = noise^2 + 255 I / photons`` is the
noise std at intensity ``I`` (Poisson variance of ``I / 255 * photons`` counts, rescaled). For a
vesicle the signal is the peak of an isolated fibre in its dimmest orientation,
``255 * (background + fibre_intensity)``, standing on the shell background ``255 * background``;
``snr_wall`` is the shell against the empty inside (``255 * background / noise``).
"""

from __future__ import annotations

import json
import os
import warnings
from collections.abc import Sequence
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy import ndimage
from scipy.spatial.transform import Rotation
from scipy.special import erf

from nemo import atomic
from nemo._log import logger, step
from nemo.errors import NemoError, NemoWarning
from nemo.geometry import axis_frames
from nemo.io import check_spacing

__all__ = [
    "PRESETS",
    "check_defects",
    "director_field",
    "nematic_angle",
    "parse_defects",
    "preset_defects",
    "projection_pole",
    "add_noise",
    "psf_sigmas",
    "read_truth",
    "snr",
    "trace_fibres",
    "truth_directors",
    "truth_path",
    "vesicle",
    "write_vesicle",
]

_S3 = 1.0 / np.sqrt(3.0)
#: Named defect sets (unit directions, charges), each with total charge 2.
PRESETS: dict[str, tuple[np.ndarray, np.ndarray]] = {
    # the paper: four +1/2 at the vertices of a regular tetrahedron (alternate cube corners)
    "tetrahedron": (
        np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float) * _S3,
        np.full(4, 0.5),
    ),
    # five +1/2 and one -1/2 on the vertices of an octahedron (-1/2 at the north pole)
    "five-one": (
        np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0], [0, 0, -1]], float),
        np.array([-0.5, 0.5, 0.5, 0.5, 0.5, 0.5]),
    ),
    # two +1 at opposite poles
    "two-plus-one": (np.array([[0, 0, 1], [0, 0, -1]], float), np.array([1.0, 1.0])),
}


# --------------------------------------------------------------------------------------------
# defects
# --------------------------------------------------------------------------------------------
def preset_defects(name: str) -> tuple[np.ndarray, np.ndarray]:
    """Return ``(directions (K, 3), charges (K,))`` of a named defect set (see :data:`PRESETS`)."""
    try:
        d, m = PRESETS[name]
    except KeyError:
        raise NemoError(
            f"unknown defect preset {name!r}; choose one of {', '.join(PRESETS)}"
        ) from None
    return d.copy(), m.copy()


def parse_defects(text: str) -> tuple[np.ndarray, np.ndarray]:
    """Parse ``"x,y,z:charge;x,y,z:charge;..."`` (directions from the centre; charges like
    ``0.5``, ``-1/2`` or ``1``) into ``(directions (K, 3), charges (K,))``."""
    dirs, charges = [], []
    for item in (s.strip() for s in text.split(";")):
        if not item:
            continue
        try:
            pos, charge = item.split(":")
            xyz = [float(v) for v in pos.split(",")]
            q = float(Fraction(charge.strip()))
        except (ValueError, ZeroDivisionError):
            raise NemoError(
                f"cannot read defect {item!r}: write each defect as x,y,z:charge, separated by "
                "';', e.g. \"1,1,1:0.5;1,-1,-1:1/2;-1,1,-1:0.5;-1,-1,1:0.5\""
            ) from None
        if len(xyz) != 3:
            raise NemoError(f"defect {item!r} needs three coordinates x,y,z before ':'")
        dirs.append(xyz)
        charges.append(q)
    if not dirs:
        raise NemoError("no defects given: write them as \"x,y,z:charge;...\" (charges summing to 2)")
    return check_defects(np.array(dirs, float), np.array(charges, float))


def check_defects(defect_dirs: ArrayLike, charges: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Validate a defect set on the sphere and return unit directions and charges.

    Parameters
    ----------
    defect_dirs : array_like, shape (K, 3)
        Directions of the defects from the centre (normalised here).
    charges : array_like, shape (K,)
        Charges, non-zero multiples of 1/2, summing to 2 (the Euler characteristic of the
        sphere, Poincaré-Hopf).

    Returns
    -------
    dirs : ndarray, shape (K, 3)
    charges : ndarray, shape (K,)

    Raises
    ------
    NemoError
        Wrong shapes, zero or non-finite directions, coincident defects, charges that are not
        multiples of 1/2 or do not sum to 2.
    """
    d = np.asarray(defect_dirs, dtype=float)
    m = np.asarray(charges, dtype=float).reshape(-1)
    if d.ndim != 2 or d.shape[1] != 3 or d.shape[0] == 0:
        raise NemoError(f"defect directions must have shape (K, 3), got {d.shape}")
    if m.shape[0] != d.shape[0]:
        raise NemoError(f"{d.shape[0]} defect positions but {m.shape[0]} charges: give one charge per defect")
    if not (np.all(np.isfinite(d)) and np.all(np.isfinite(m))):
        raise NemoError("defect positions and charges must be finite numbers")
    norm = np.linalg.norm(d, axis=1)
    if np.any(norm < 1e-12):
        raise NemoError("a defect direction is (0, 0, 0): give directions from the sphere's centre")
    d = d / norm[:, None]
    twice = 2.0 * m
    if np.any(np.abs(twice - np.round(twice)) > 1e-9) or np.any(np.round(twice) == 0):
        raise NemoError(
            f"defect charges {m.tolist()} must be non-zero multiples of 1/2 (nematic defects)"
        )
    if abs(m.sum() - 2.0) > 1e-9:
        raise NemoError(
            f"defect charges sum to {m.sum():g}, but on a sphere they must sum to 2 "
            "(Poincaré-Hopf); e.g. 4 x +1/2, 5 x +1/2 + 1 x -1/2, or 2 x +1"
        )
    if d.shape[0] > 1:
        cos = d @ d.T
        np.fill_diagonal(cos, -1.0)
        if cos.max() > np.cos(1e-6):
            raise NemoError("two defects are at the same position: give distinct positions")
    return d, np.round(twice) / 2.0


def _fibonacci_sphere(n: int) -> np.ndarray:
    """``n`` points spread evenly on the unit sphere (golden-angle spiral), shape (n, 3)."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = np.pi * (1.0 + np.sqrt(5.0)) * i
    s = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    return np.column_stack([s * np.cos(phi), s * np.sin(phi), z])


def projection_pole(defect_dirs: ArrayLike) -> np.ndarray:
    """The point of the unit sphere farthest from all defects (max of the min angular distance).

    Deterministic: the best of 20 000 evenly spread candidates, refined by a local search.

    Parameters
    ----------
    defect_dirs : array_like, shape (K, 3)

    Returns
    -------
    pole : ndarray, shape (3,)
    """
    d = np.asarray(defect_dirs, float)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    cand = _fibonacci_sphere(20000)
    best = cand[np.argmin((cand @ d.T).max(axis=1))]
    # refine on a shrinking local grid around the best candidate (tiny, fixed cost)
    t1 = np.cross(best, [1.0, 0, 0] if abs(best[0]) < 0.9 else [0, 1.0, 0])
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(best, t1)
    g = np.linspace(-1, 1, 21)
    a, b = np.meshgrid(g, g)
    for scale in (0.02, 2e-3, 2e-4, 2e-5, 2e-6, 2e-7):
        p = best + scale * (a.reshape(-1, 1) * t1 + b.reshape(-1, 1) * t2)
        p /= np.linalg.norm(p, axis=1, keepdims=True)
        best = p[np.argmin((p @ d.T).max(axis=1))]
    return best / np.linalg.norm(best)


def _rotation_to_south(pole: np.ndarray) -> np.ndarray:
    """Rotation matrix ``M`` with ``M @ pole = (0, 0, -1)`` (the smallest such rotation)."""
    s = np.asarray(pole, float) / np.linalg.norm(pole)
    target = np.array([0.0, 0.0, -1.0])
    axis = np.cross(s, target)
    sin = np.linalg.norm(axis)
    cos = float(s @ target)
    if sin < 1e-12:
        return np.eye(3) if cos > 0 else np.diag([1.0, -1.0, -1.0])
    return Rotation.from_rotvec(axis / sin * np.arctan2(sin, cos)).as_matrix()


# --------------------------------------------------------------------------------------------
# the analytic director field
# --------------------------------------------------------------------------------------------
def director_field(
    points: ArrayLike,
    defect_dirs: ArrayLike,
    charges: ArrayLike,
    *,
    pole: ArrayLike | None = None,
    phase: float = 0.0,
) -> np.ndarray:
    """Unit tangent directors of the analytic nematic field on the unit sphere.

    Stereographic construction of the paper: ``w = (x + iy)/(1 + z)`` in a frame where the
    projection pole is the south pole, ``psi = phase + sum_k m_k arg(w - w_k)``, lifted with the
    analytic derivative of the inverse projection, ``n = cos(psi) e_u + sin(psi) e_v``. Points
    in the southern hemisphere of that frame use the chart ``1/w`` (exact change of chart), so
    the field is smooth everywhere except at the defects. See the module docstring for the
    projection pole.

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Points on the unit sphere (normalised here; any non-zero vectors from the centre).
    defect_dirs : array_like, shape (K, 3)
        Defect directions from the centre.
    charges : array_like, shape (K,)
        Defect charges, multiples of 1/2 summing to 2.
    pole : array_like, shape (3,), optional
        Projection pole; default :func:`projection_pole` (farthest from all defects).
    phase : float
        Constant angle (radians) added to ``psi``: rotates every director by ``phase`` in its
        tangent plane (``pi/2`` gives the orthogonal field).

    Returns
    -------
    n : ndarray, shape (N, 3)
        Unit directors, tangent to the sphere (``n . p = 0``). The sign is arbitrary (nematic);
        at a defect core the value is finite but meaningless.
    """
    d, m = check_defects(defect_dirs, charges)
    p = np.asarray(points, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3:
        raise NemoError(f"points must have shape (N, 3), got {p.shape}")
    s = projection_pole(d) if pole is None else np.asarray(pole, float)
    if s.shape != (3,) or not np.linalg.norm(s) > 0:
        raise NemoError(f"pole must be a non-zero 3-vector, got {pole!r}")
    s = s / np.linalg.norm(s)
    if (d @ s).max() > np.cos(1e-3):
        raise NemoError("the projection pole coincides with a defect; leave pole=None")
    return _director_kernel(p / np.linalg.norm(p, axis=1, keepdims=True), d, m,
                            _rotation_to_south(s), phase)


def _director_kernel(p: np.ndarray, d: np.ndarray, m: np.ndarray, rot: np.ndarray,
                     phase: float) -> np.ndarray:
    """Director at unit points ``p`` (N,3); ``rot`` maps the pole to the south pole."""
    q = p @ rot.T
    dk = d @ rot.T
    wk = (dk[:, 0] + 1j * dk[:, 1]) / (1.0 + dk[:, 2])  # finite: pole is away from defects
    x, y, z = q[:, 0], q[:, 1], q[:, 2]
    north = z >= 0.0
    e1 = np.empty_like(q)
    e2 = np.empty_like(q)
    psi = np.empty(len(q))

    # chart A (projection from the south pole): w = (x + iy)/(1 + z)
    xa, ya, za = x[north], y[north], z[north]
    w = (xa + 1j * ya) / (1.0 + za)
    psi[north] = phase + (np.angle(w[:, None] - wk[None, :]) * m).sum(axis=1)
    opz = 1.0 + za
    e1[north] = np.column_stack([opz / 2 + (ya**2 - xa**2) / (2 * opz), -xa * ya / opz, -xa])
    e2[north] = np.column_stack([-xa * ya / opz, opz / 2 + (xa**2 - ya**2) / (2 * opz), -ya])

    # chart B (projection from the north pole): w~ = 1/w = (x - iy)/(1 - z)
    sb = ~north
    xb, yb, zb = x[sb], y[sb], z[sb]
    wt = (xb - 1j * yb) / (1.0 - zb)
    psi[sb] = phase + np.pi + (np.angle(1.0 - wk[None, :] * wt[:, None]) * m).sum(axis=1)
    omz = 1.0 - zb
    e1[sb] = np.column_stack([omz / 2 + (yb**2 - xb**2) / (2 * omz), -xb * yb / omz, xb])
    e2[sb] = np.column_stack([xb * yb / omz, -omz / 2 - (xb**2 - yb**2) / (2 * omz), -yb])

    n = np.cos(psi)[:, None] * e1 + np.sin(psi)[:, None] * e2
    n /= np.linalg.norm(n, axis=1, keepdims=True)  # |e1| = |e2| = 1 analytically; remove rounding
    return n @ rot  # back to the original frame (rot is orthogonal)


def nematic_angle(
    points: ArrayLike,
    defect_dirs: ArrayLike,
    charges: ArrayLike,
    t1: ArrayLike | None = None,
    t2: ArrayLike | None = None,
    *,
    pole: ArrayLike | None = None,
    phase: float = 0.0,
) -> np.ndarray:
    """Angle of the analytic director in a tangent basis, in ``[0, pi)``.

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Points on the unit sphere (or vectors from the centre).
    defect_dirs, charges, pole, phase
        As in :func:`director_field`.
    t1, t2 : array_like, shape (N, 3), optional
        Tangent basis at each point. Default: :func:`nemo.geometry.axis_frames` of the outward
        normal ``N`` (``t1 = N x x^``, ``N x y^`` when ``N`` is nearly parallel to ``x^``), the
        frames NEMO measures angles in, so that angles compare directly.

    Returns
    -------
    theta : ndarray, shape (N,)
        ``atan2(n . t2, n . t1)`` modulo ``pi``: the director is ``cos(theta) t1 + sin(theta) t2``.
    """
    p = np.asarray(points, float)
    n = director_field(p, defect_dirs, charges, pole=pole, phase=phase)
    if t1 is None or t2 is None:
        t1, t2 = axis_frames(p / np.linalg.norm(p, axis=1, keepdims=True))
    t1 = np.asarray(t1, float)
    t2 = np.asarray(t2, float)
    return np.mod(np.arctan2(np.einsum("ij,ij->i", n, t2), np.einsum("ij,ij->i", n, t1)), np.pi)


# --------------------------------------------------------------------------------------------
# fibres
# --------------------------------------------------------------------------------------------
def trace_fibres(
    defect_dirs: ArrayLike,
    charges: ArrayLike,
    n_seeds: int,
    length: float,
    step_size: float,
    *,
    pole: ArrayLike | None = None,
    phase: float = 0.0,
    core: float | None = None,
    max_turn: float = np.deg2rad(30.0),
    rng: np.random.Generator | int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Trace bidirectional streamlines of the director field on the unit sphere.

    Seeds are spread evenly (a golden-angle lattice under a random rotation); from each seed
    two walkers go ``length/2`` forward and backward with midpoint (RK2) steps on the sphere
    (renormalised), all walkers advanced together (vectorised). The director's sign is chosen
    at each evaluation to agree with the walker's previous direction (head-tail consistency).
    A walker stops when it comes within ``core`` of a defect or turns by more than
    ``max_turn`` in one step (a defect core).

    Parameters
    ----------
    defect_dirs, charges, pole, phase
        As in :func:`director_field`.
    n_seeds : int
        Number of fibres.
    length : float
        Fibre length in radians (arc length on the unit sphere).
    step_size : float
        Step in radians.
    core : float, optional
        Angular radius around each defect where fibres stop (default ``step_size``).
    max_turn : float
        Largest turn per step (radians) before a walker stops.
    rng : Generator, int or None
        Randomness of the seed lattice's rotation.

    Returns
    -------
    points : ndarray, shape (M, 3)
        Unit vectors of all fibre points, spaced ``step_size`` along each fibre.
    tangents : ndarray, shape (M, 3)
        The (unit) step direction at each point (seed points: the director).
    """
    d, m = check_defects(defect_dirs, charges)
    s = projection_pole(d) if pole is None else np.asarray(pole, float) / np.linalg.norm(pole)
    rot = _rotation_to_south(s)
    rng = np.random.default_rng(rng)
    n_seeds = max(int(n_seeds), 1)
    seeds = _fibonacci_sphere(n_seeds) @ Rotation.random(random_state=rng).as_matrix().T
    core = step_size if core is None else core
    cos_core = np.cos(core)
    cos_turn = np.cos(max_turn)

    def field(p):
        return _director_kernel(p, d, m, rot, phase)

    n0 = field(seeds)
    pts = [seeds]
    tans = [n0]
    p = np.concatenate([seeds, seeds])
    prev = np.concatenate([n0, -n0])
    alive = (p @ d.T).max(axis=1) < cos_core
    n_steps = int(np.ceil(0.5 * length / step_size))
    h = step_size
    for _ in range(n_steps):  # loop over steps; every walker advances at once
        k1 = field(p)
        k1 *= np.sign(np.einsum("ij,ij->i", k1, prev) + 1e-300)[:, None]
        pm = p + 0.5 * h * k1
        pm /= np.linalg.norm(pm, axis=1, keepdims=True)
        k2 = field(pm)
        k2 *= np.sign(np.einsum("ij,ij->i", k2, k1) + 1e-300)[:, None]
        pn = p + h * k2
        pn /= np.linalg.norm(pn, axis=1, keepdims=True)
        alive &= (np.einsum("ij,ij->i", k2, prev) > cos_turn) & ((pn @ d.T).max(axis=1) < cos_core)
        if not alive.any():
            break
        chord = pn - p
        chord /= np.linalg.norm(chord, axis=1, keepdims=True)
        pts.append(pn[alive])
        tans.append(chord[alive])
        p, prev = pn, k2
    return np.concatenate(pts), np.concatenate(tans)


def _splat(
    points_xyz: np.ndarray, weights: float, shape: tuple[int, int, int],
    spacing: tuple[float, float, float], out: np.ndarray,
) -> None:
    """Trilinear splatting of weighted physical points into ``out`` (Z, Y, X) float32, in place.

    Points whose 8 neighbouring voxels are not all inside the volume are dropped (the caller
    keeps the vesicle away from the border).
    """
    v = points_xyz[:, ::-1] / np.asarray(spacing, float)  # voxel coordinates (z, y, x)
    i0 = np.floor(v).astype(np.int64)
    inside = np.all((i0 >= 0) & (i0 < np.asarray(shape) - 1), axis=1)
    i0, f = i0[inside], (v[inside] - i0[inside]).astype(np.float32)
    strides = np.array([shape[1] * shape[2], shape[2], 1], np.int64)
    base = i0 @ strides
    g = 1.0 - f
    flat = out.reshape(-1)
    w = np.float32(weights)
    for a in (0, 1):  # 8 corners: 8 vectorised scatter-adds
        wa = (f[:, 0] if a else g[:, 0]) * w
        for b in (0, 1):
            wab = wa * (f[:, 1] if b else g[:, 1])
            for c in (0, 1):
                np.add.at(flat, base + (a * strides[0] + b * strides[1] + c),
                          wab * (f[:, 2] if c else g[:, 2]))


def _ball_blur(r: np.ndarray, a: float, s: float) -> np.ndarray:
    """Indicator of a ball of radius ``a`` blurred by an isotropic Gaussian of std ``s``, at
    distance ``r`` from its centre (exact: CDF of the non-central chi distribution, 3 dof)."""
    if a <= 0:
        return np.zeros_like(r)
    if s <= 0:
        return (r <= a).astype(float)
    r = np.maximum(r, 1e-9)
    k = np.sqrt(2.0) * s
    return 0.5 * (erf((a - r) / k) + erf((a + r) / k)) + s / (r * np.sqrt(2 * np.pi)) * (
        np.exp(-((a + r) ** 2) / (2 * s * s)) - np.exp(-((a - r) ** 2) / (2 * s * s))
    )


def _ball_blur_along(r: np.ndarray, a: float, s: np.ndarray) -> np.ndarray:
    """:func:`_ball_blur` with a per-point std ``s`` (> 0): a ball blurred by an anisotropic
    Gaussian, using at each point the std along its radial direction (the edge's normal). Exact
    for a plane edge; the error of the curved edge is O(sigma^2 / a)."""
    r = np.maximum(r, 1e-9)
    k = np.sqrt(2.0) * s
    return 0.5 * (erf((a - r) / k) + erf((a + r) / k)) + s / (r * np.sqrt(2 * np.pi)) * (
        np.exp(-((a + r) ** 2) / (2 * s * s)) - np.exp(-((a - r) ** 2) / (2 * s * s))
    )


def psf_sigmas(blur: float | Sequence[float]) -> tuple[float, float, float]:
    """The Gaussian PSF's ``(sigma_z, sigma_y, sigma_x)`` (µm) from one sigma or three.

    Raises
    ------
    NemoError
        Not one or three finite numbers >= 0.
    """
    b = np.atleast_1d(np.asarray(blur, dtype=float)).reshape(-1)
    if b.size == 1:
        b = np.repeat(b, 3)
    if b.size != 3 or not np.all(np.isfinite(b)) or np.any(b < 0):
        raise NemoError(f"blur must be one sigma or three (sigma_z, sigma_y, sigma_x) >= 0 µm, got {blur!r}")
    return float(b[0]), float(b[1]), float(b[2])


def snr(signal: float, background: float, noise: float = 0.0, photons: float | None = None) -> float | None:
    """Signal-to-noise ratio of NEMO's synthetic images: ``(signal - background) / sigma(background)``.

    Parameters
    ----------
    signal, background : float
        Intensities on the 0-255 scale (noise-free).
    noise : float
        Std of the additive Gaussian noise (0-255 scale).
    photons : float, optional
        Photons at the 255 level: Poisson noise of variance ``255 I / photons`` at intensity ``I``.

    Returns
    -------
    float or None
        None without noise (infinite SNR).
    """
    var = float(noise) ** 2 + (255.0 * max(float(background), 0.0) / float(photons) if photons else 0.0)
    return None if var <= 0 else (float(signal) - float(background)) / float(np.sqrt(var))


def add_noise(img: np.ndarray, photons: float | None, noise: float, rng: np.random.Generator) -> np.ndarray:
    """Shot noise then Gaussian noise on a float32 image (0-255 scale).

    ``photons`` at the 255 level: the image becomes ``Poisson(I / 255 * photons) * 255 / photons``
    (mean ``I``, variance ``255 I / photons``); then ``noise`` (std) is added. Returns the noisy
    image (a new array with shot noise, else ``img`` changed in place). Not clipped.
    """
    if photons:
        lam = np.clip(img, 0.0, None).astype(np.float64) * (float(photons) / 255.0)
        img = (rng.poisson(lam) * (255.0 / float(photons))).astype(np.float32)
    if noise > 0:
        img += np.float32(noise) * rng.standard_normal(img.shape, dtype=np.float32)
    return img


# --------------------------------------------------------------------------------------------
# vesicle
# --------------------------------------------------------------------------------------------
def _available_memory() -> int | None:
    """Bytes of memory available to a new allocation (Linux MemAvailable, else total RAM)."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return None


def _rotation_matrix(axis: ArrayLike, angle_deg: float) -> np.ndarray:
    a = np.asarray(axis, float)
    if a.shape != (3,) or not np.linalg.norm(a) > 0:
        raise NemoError(f"rotation axis must be a non-zero vector x y z, got {axis!r}")
    return Rotation.from_rotvec(a / np.linalg.norm(a) * np.deg2rad(angle_deg)).as_matrix()


def _layer_specs(
    layers: Sequence[dict] | None, layer_depth: float, second_layer_depth: float | None,
    second_layer_rotation: float, second_layer_channel: int,
    second_layer_defects: ArrayLike | None, second_layer_charges: ArrayLike | None,
    phase: float,
) -> list[dict]:
    if layers is None:
        layers = [{"depth": layer_depth, "channel": 0, "rotation": 0.0}]
        if second_layer_depth is not None:
            layers.append({
                "depth": second_layer_depth, "channel": second_layer_channel,
                "rotation": second_layer_rotation,
                "defects": second_layer_defects, "charges": second_layer_charges,
            })
    specs = []
    for i, spec in enumerate(layers):
        unknown = set(spec) - {"depth", "channel", "rotation", "defects", "charges"}
        if unknown:
            raise NemoError(f"layer {i}: unknown keys {sorted(unknown)} (use depth, channel, rotation, defects, charges)")
        depth = float(spec.get("depth", layer_depth))
        if not np.isfinite(depth) or depth < 0:
            raise NemoError(f"layer {i}: depth must be >= 0 µm (outward from the inner surface), got {depth}")
        ch = spec.get("channel", 0)
        if not isinstance(ch, (int, np.integer)) or ch < 0:
            raise NemoError(f"layer {i}: channel must be an integer >= 0, got {ch!r}")
        specs.append({
            "depth": depth, "channel": int(ch),
            "rotation": float(spec.get("rotation", 0.0) or 0.0),
            "defects": spec.get("defects"), "charges": spec.get("charges"),
            "phase": phase + np.deg2rad(float(spec.get("rotation", 0.0) or 0.0)),
        })
    return specs


def vesicle(
    radius: float = 200.0,
    spacing: Sequence[float] = (1.0, 1.0, 1.0),
    *,
    defects: ArrayLike | str | None = None,
    charges: ArrayLike | None = None,
    rotate: ArrayLike | int | None = None,
    fibre_spacing: float = 5.0,
    fibre_length: float | None = None,
    step_size: float | None = None,
    shell_thickness: float = 10.0,
    background: float = 0.25,
    fibre_intensity: float = 0.6,
    blur: float | Sequence[float] = 1.0,
    noise: float = 0.0,
    photons: float | None = None,
    cut_top: float | None = None,
    layer_depth: float = 3.0,
    second_layer_depth: float | None = None,
    second_layer_rotation: float = 90.0,
    second_layer_channel: int = 0,
    second_layer_defects: ArrayLike | None = None,
    second_layer_charges: ArrayLike | None = None,
    layers: Sequence[dict] | None = None,
    frames: int = 1,
    frame_rotation: float = 0.0,
    frame_axis: Sequence[float] = (0.0, 1.0, 0.0),
    channels: int | None = None,
    size: int | Sequence[int] | None = None,
    margin: float | None = None,
    phase: float = 0.0,
    seed: int | None = 0,
) -> tuple[np.ndarray, dict[str, Any]]:
    """Generate a synthetic nematic vesicle and its ground truth.

    The default reproduces the paper's Fig. 2 vesicle: R = 200 µm, 1 µm voxels, four +1/2
    defects at the vertices of a regular tetrahedron, one fibre layer 3 µm outside the inner
    surface (inside the [0, 5] µm peel range; deep enough that the blurred fibres do not move
    the inner edge), fibres 5 µm apart and 100 µm long, a 10 µm shell of constant background,
    1 µm blur, a 450^3 volume.

    Parameters
    ----------
    radius : float
        Inner radius R of the vesicle (µm).
    spacing : (dz, dy, dx)
        Voxel size in µm (anisotropic allowed).
    defects : array_like (K, 3) or str, optional
        Defect directions from the centre, or a preset name (:data:`PRESETS`); default the
        tetrahedron.
    charges : array_like (K,), optional
        Charges for ``defects`` given as directions (default ``+1/2`` each); must sum to 2.
    rotate : (3, 3) matrix or int, optional
        Rotation applied to the defect set (all layers): a matrix, or a seed for a uniformly
        random rotation.
    fibre_spacing : float
        Mean distance (µm) between neighbouring fibres: the number of fibres per layer is
        ``area / (fibre_spacing * fibre_length)``, so a line across the layer meets one fibre
        every ``fibre_spacing`` µm on average.
    fibre_length : float, optional
        Length (µm) of each fibre (shorter where it runs into a defect core); default ``R / 2``
        (100 µm for the paper's vesicle: long fibres give clean stripes in 20 µm patches).
    step_size : float, optional
        Tracing step (µm); default ``min(spacing)/2`` capped at 0.5 µm.
    shell_thickness : float
        The constant-background shell spans ``R <= r <= R + shell_thickness`` (µm).
    background : float
        Shell intensity (fraction of 255 before clipping).
    fibre_intensity : float
        Peak intensity of an isolated blurred fibre (fraction of 255); overlapping fibres add
        up and the total is clipped at 255.
    blur : float or (sigma_z, sigma_y, sigma_x)
        Gaussian PSF sigma in µm: one value (isotropic in physical space) or three (a
        confocal-like PSF, e.g. ``(2.5, 1, 1)``); per-axis sigma in voxels follows the spacing.
        0 = no blur. With an anisotropic PSF ``fibre_intensity`` is the peak of a fibre in its
        dimmest orientation (normalised by the two largest sigmas; fibres along the sharpest
        axis are brighter, as in a microscope), and the shell's edge is blurred with the sigma
        along its normal.
    noise : float
        Standard deviation of additive Gaussian noise on the 0-255 scale.
    photons : float, optional
        Shot noise before the Gaussian noise: Poisson noise with ``photons`` photons at the 255
        level (variance ``255 I / photons`` at intensity ``I``). The truth records the
        resulting :func:`snr`.
    cut_top : float, optional
        Cut the stack this many µm above the centre (the top of the field of view): an open
        vesicle. The truth marks the defects above the cut ``in_view: false``.
    layer_depth : float
        Depth (µm) of the (first) fibre layer outside the inner surface: fibres lie on the
        sphere of radius ``R + layer_depth``.
    second_layer_depth : float, optional
        Adds a second fibre layer at this depth.
    second_layer_rotation : float
        Angle (degrees) by which the second layer's directors are rotated in the tangent plane
        (90 = orthogonal field, 0 = parallel).
    second_layer_channel : int
        Channel of the second layer (0 = the same channel as the first).
    second_layer_defects, second_layer_charges : array_like, optional
        Own defect set of the second layer (default: the first layer's).
    layers : list of dict, optional
        Full control instead of the ``layer_depth``/``second_layer_*`` shortcuts: one dict per
        layer with keys ``depth`` (µm), ``channel``, ``rotation`` (deg), ``defects`` (K, 3 or
        preset name), ``charges``.
    frames : int
        Number of time points.
    frame_rotation : float
        Rotation (degrees) of the whole nematic texture (defects and fibres) per frame about
        ``frame_axis`` through the centre.
    frame_axis : (3,)
        Axis of the per-frame rotation.
    channels : int, optional
        Number of channels (default: enough for the layers' channels). Every channel has the
        shell background; a channel holds the fibres of the layers assigned to it.
    size : int or (nz, ny, nx), optional
        Volume size in voxels; default ``2 (R + max(shell, deepest layer) + margin) / spacing``.
    margin : float, optional
        Free space (µm) around the shell; default ``max(0.075 R, 4 blur + 3 max(spacing))``.
    phase : float
        Constant director angle (radians) added to every layer's field.
    seed : int or None
        Seed for fibre placement and noise.

    Returns
    -------
    data : ndarray, shape (T, Z, C, Y, X), uint8
    truth : dict
        JSON-serialisable ground truth: ``radius``, ``centre`` (x, y, z), ``spacing``,
        ``unit``, ``shape``, ``shell_thickness``, ``layers`` (depth, radius, channel, field
        parameters), ``frames`` (rotation matrix per frame), ``defects`` (one record per frame,
        layer and defect: ``t``, ``layer``, ``channel``, ``charge``, ``x, y, z`` on the inner
        surface R, ``x_layer, y_layer, z_layer`` on the layer radius, unit direction
        ``ux, uy, uz``) and ``parameters``.

    Raises
    ------
    NemoError
        Invalid defects (charges not summing to 2, ...), spacing, sizes, or a vesicle that does
        not fit in the requested volume.
    """
    params = {k: v for k, v in locals().items()}
    R, fibre_length, sp, frames = _check_vesicle_numbers(
        radius, spacing, fibre_spacing, fibre_length, shell_thickness, background, fibre_intensity, blur,
        noise, frames, photons, cut_top)
    sigmas = psf_sigmas(blur)
    iso = sigmas[0] == sigmas[1] == sigmas[2]
    blur_max = max(sigmas)
    d0, m0, g = _defect_set(defects, charges, rotate)
    specs = _layer_specs(layers, layer_depth, second_layer_depth, second_layer_rotation,
                         second_layer_channel, second_layer_defects, second_layer_charges, phase)
    _place_layer_defects(specs, d0, m0, g)
    channels = _check_channels(specs, channels)
    shape, centre_zyx, margin = _volume_shape(R, specs, shell_thickness, blur_max, sp, margin, size)
    _check_memory(shape, frames, channels)
    centre = centre_zyx[::-1].copy()  # physical (x, y, z)

    step_um = min(0.5, min(sp) / 2) if step_size is None else float(step_size)
    if not step_um > 0:
        raise NemoError(f"step_size must be > 0 µm, got {step_size!r}")
    frame_rot = [_rotation_matrix(frame_axis, t * frame_rotation) for t in range(frames)]
    root = np.random.SeedSequence(seed)
    fibre_ss, noise_ss = root.spawn(2)
    layer_rngs = [np.random.default_rng(s) for s in fibre_ss.spawn(len(specs))]
    traced = _trace_layers(specs, R, fibre_spacing, fibre_length, step_um, layer_rngs)

    # isotropic PSF: the exact blurred shell, tabulated; anisotropic: evaluated per voxel
    shell_prof = (_shell_profile(shape, sp, R, shell_thickness, sigmas[0], background) if iso
                  else (R, shell_thickness, sigmas, background))
    noise_rngs = [np.random.default_rng(s) for s in noise_ss.spawn(frames * channels)]
    data = _rasterise(traced, specs, frame_rot, centre, centre_zyx, shape, sp, channels, step_um,
                      sigmas[0] if iso else sigmas, fibre_intensity, noise, shell_prof, noise_rngs,
                      photons)
    z_max = None
    if cut_top is not None:
        z_max = centre_zyx[0] + float(cut_top)
        keep = int(np.floor(z_max / sp[0] + 1e-9)) + 1
        if not 2 <= keep <= shape[0]:
            raise NemoError(f"cut_top {cut_top:g} µm leaves {keep} of the {shape[0]} slices: "
                            f"give a height between {-centre_zyx[0] + sp[0]:g} and {centre_zyx[0]:g} µm")
        data = np.ascontiguousarray(data[:, :keep])
        shape = (keep, shape[1], shape[2])
        z_max = (keep - 1) * sp[0]

    params.update(fibre_length=fibre_length, step_size=step_um, margin=margin, size=list(shape),
                  channels=channels, frames=frames)
    truth = _make_truth(R, centre, sp, shape, frames, channels, specs, frame_rot, g,
                        shell_thickness, params)
    level = 255.0 * background
    truth["psf"] = {"sigma_zyx": list(sigmas), "unit": "um",
                    "model": "Gaussian" + ("" if iso else " (anisotropic: shell edge blurred with "
                                                          "the sigma along its normal)")}
    truth["noise"] = {
        "photons": None if not photons else float(photons), "gaussian_std": float(noise),
        "shell_level": level, "fibre_peak": level + 255.0 * fibre_intensity,
        "noise_std_shell": float(np.sqrt(noise**2 + (255.0 * level / photons if photons else 0.0))),
        "snr": snr(level + 255.0 * fibre_intensity, level, noise, photons),
        "snr_wall": snr(level, 0.0, noise, photons),
        "definition": "SNR = (signal - background) / sigma(background), sigma(I)^2 = gaussian_std^2 "
                      "+ 255 I / photons (0-255 scale); snr: the peak of an isolated fibre in its "
                      "dimmest orientation on the shell; snr_wall: the shell on the empty inside",
    }
    if z_max is not None:
        truth["field_of_view"] = {"z_max": z_max, "cut_top": float(cut_top), "open": True}
        for rec in truth["defects"]:
            rec["in_view"] = bool(rec["z"] <= z_max)
    return data, truth


def _check_vesicle_numbers(radius, spacing, fibre_spacing, fibre_length, shell_thickness, background,
                           fibre_intensity, blur, noise, frames, photons=None, cut_top=None):
    """Checked radius R, fibre length (default R / 2), spacing and number of frames."""
    R = float(radius)
    if not np.isfinite(R) or R <= 0:
        raise NemoError(f"radius must be a positive number of µm, got {radius!r}")
    if fibre_length is None:
        fibre_length = 0.5 * R
    sp = check_spacing(spacing)
    for name, val in (("fibre_spacing", fibre_spacing), ("fibre_length", fibre_length)):
        if not (np.isfinite(val) and val > 0):
            raise NemoError(f"{name} must be > 0 µm, got {val!r}")
    for name, val in (("shell_thickness", shell_thickness), ("background", background),
                      ("fibre_intensity", fibre_intensity), ("noise", noise)):
        if not (np.isfinite(val) and val >= 0):
            raise NemoError(f"{name} must be >= 0, got {val!r}")
    psf_sigmas(blur)
    if photons is not None and not (np.isfinite(photons) and photons > 0):
        raise NemoError(f"photons must be > 0 (photons at the 255 level), got {photons!r}")
    if cut_top is not None and not np.isfinite(cut_top):
        raise NemoError(f"cut_top must be a number of µm above the centre, got {cut_top!r}")
    if int(frames) != frames or frames < 1:
        raise NemoError(f"frames must be an integer >= 1, got {frames!r}")
    return R, fibre_length, sp, int(frames)


def _defect_set(defects, charges, rotate) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The first layer's defect directions (K, 3) and charges (K,), and the rotation ``g`` (3, 3)
    applied to every layer's defect set."""
    if defects is None or isinstance(defects, str):
        if charges is not None and defects is None:
            raise NemoError("charges given without defect positions: pass defects=(K, 3) too")
        d0, m0 = preset_defects(defects or "tetrahedron")
    else:
        d0 = np.asarray(defects, float)
        m0 = np.full(len(d0), 0.5) if charges is None else charges
    d0, m0 = check_defects(d0, m0)
    if rotate is None:
        g = np.eye(3)
    elif np.ndim(rotate) == 0:
        g = Rotation.random(random_state=int(rotate)).as_matrix()
    else:
        g = np.asarray(rotate, float)
        if g.shape != (3, 3) or not np.allclose(g @ g.T, np.eye(3), atol=1e-6) or np.linalg.det(g) < 0:
            raise NemoError("rotate must be a 3 x 3 rotation matrix or an integer seed")
    return d0, m0, g


def _place_layer_defects(specs: list[dict], d0: np.ndarray, m0: np.ndarray, g: np.ndarray) -> None:
    """Give every layer spec its rotated defect directions ``dirs``, ``charges_`` and projection ``pole``
    (its own defects, a preset, or the first layer's ``d0, m0``)."""
    for spec in specs:
        if spec["defects"] is None:
            d, m = d0, m0
        elif isinstance(spec["defects"], str):
            d, m = preset_defects(spec["defects"])
        else:
            d = np.asarray(spec["defects"], float)
            m = np.full(len(d), 0.5) if spec["charges"] is None else spec["charges"]
        d, m = check_defects(d, m)
        spec["dirs"] = d @ g.T
        spec["charges_"] = m
        spec["pole"] = projection_pole(spec["dirs"])


def _check_channels(specs: list[dict], channels: int | None) -> int:
    """Number of channels: enough for the layers' channels by default, refused when too few."""
    n_ch = max(s["channel"] for s in specs) + 1
    if channels is None:
        channels = n_ch
    if int(channels) != channels or channels < 1:
        raise NemoError(f"channels must be an integer >= 1, got {channels!r}")
    channels = int(channels)
    if n_ch > channels:
        raise NemoError(
            f"a layer is assigned to channel {n_ch - 1} but the image has {channels} channel(s): "
            "raise channels or change the layer's channel"
        )
    return channels


def _volume_shape(R, specs, shell_thickness, blur, sp, margin, size):
    """Volume shape (Z, Y, X), centre (z, y, x, µm) and margin; refused when the vesicle does not fit.

    Warns (at the caller of :func:`vesicle`) about layers outside the background shell.
    """
    deepest = max(s["depth"] for s in specs)
    outer = R + max(shell_thickness, deepest)
    for s in specs:
        if s["depth"] > shell_thickness:
            warnings.warn(
                f"a fibre layer at depth {s['depth']:g} µm lies outside the {shell_thickness:g} µm "
                "background shell", NemoWarning, stacklevel=3)
    if margin is None:
        margin = max(0.075 * R, 4 * blur + 3 * max(sp))
    if size is None:
        shape = tuple(int(np.ceil(2 * (outer + margin) / d)) for d in sp)
    else:
        shape = (int(size),) * 3 if np.ndim(size) == 0 else tuple(int(v) for v in size)
        if len(shape) != 3 or min(shape) < 2:
            raise NemoError(f"size must be one integer or three (NZ NY NX) >= 2, got {size!r}")
    centre_zyx = np.array([(n - 1) / 2 * d for n, d in zip(shape, sp)])
    half = centre_zyx.min()
    need = outer + 2 * blur + max(sp)
    if need > half:
        raise NemoError(
            f"the vesicle (radius {R:g} µm + {max(shell_thickness, deepest):g} µm shell/layers "
            f"+ blur) needs {need:.1f} µm from the centre but the volume {shape[::-1]} (X, Y, Z) "
            f"voxels of {sp[::-1]} µm gives only {half:.1f} µm: increase size or decrease radius"
        )
    return shape, centre_zyx, margin


def _check_memory(shape: tuple[int, int, int], frames: int, channels: int) -> None:
    """Refuse an image that would not fit in the available memory."""
    n_vox = int(np.prod(shape)) * frames * channels
    need = n_vox + 8 * int(np.prod(shape))  # uint8 result + the float32 working volume (+ filter)
    avail = _available_memory()
    if avail is not None and need > avail:
        raise NemoError(
            f"the requested image ({shape[2]} x {shape[1]} x {shape[0]} voxels x {frames} frame(s) x "
            f"{channels} channel(s)) needs about {need / 1e9:.3g} GB of memory but {avail / 1e9:.3g} GB "
            "are available: reduce the size (`size`, `spacing`, `radius`), frames or channels"
        )


def _trace_layers(specs, R, fibre_spacing, fibre_length, step_um, layer_rngs) -> list[np.ndarray]:
    """Fibre points (µm, about the centre) of every layer, traced once for frame 0.

    Frames rotate the traced fibres rigidly. Sets ``spec["n_fibres"]``.
    """
    traced = []
    for i, spec in enumerate(specs):
        rl = R + spec["depth"]
        n_seeds = int(np.ceil(4 * np.pi * rl**2 / (fibre_spacing * fibre_length)))
        with step(f"tracing {n_seeds} fibres of layer {i} (radius {rl:g} µm)"):
            pts, _ = trace_fibres(
                spec["dirs"], spec["charges_"], n_seeds, fibre_length / rl, step_um / rl,
                pole=spec["pole"], phase=spec["phase"], core=max(step_um, 0.5) / rl,
                rng=layer_rngs[i],
            )
        traced.append(pts * rl)
        spec["n_fibres"] = n_seeds
    return traced


#: Radial grid step (µm) of the tabulated shell profile; linear-interpolation error < 1e-6.
_SHELL_DR = 0.005


def _shell_profile(shape, sp, R, shell_thickness, blur, background) -> np.ndarray:
    """Blurred background shell (0-255, float32) on a radial grid of :data:`_SHELL_DR` µm.

    The exact blurred-ball formula, tabulated out to the volume's diagonal and interpolated
    linearly by :func:`_rasterise`.
    """
    r_max = float(np.linalg.norm(np.array(shape) * np.array(sp))) + 1.0
    dr = _SHELL_DR
    r_grid = np.arange(0.0, r_max + 2 * dr, dr)
    shell_prof = (_ball_blur(r_grid, R + shell_thickness, blur) - _ball_blur(r_grid, R, blur))
    return (255.0 * background * shell_prof).astype(np.float32)


def _rasterise(traced, specs, frame_rot, centre, centre_zyx, shape, sp, channels, step_um, blur,
               fibre_intensity, noise, shell_prof, noise_rngs, photons=None) -> np.ndarray:
    """The uint8 image (T, Z, C, Y, X): per frame and channel, the channel's fibres splatted and
    blurred, plus the shell profile and noise, slab by slab.

    ``blur`` is one sigma (``shell_prof`` the tabulated radial profile) or ``(sz, sy, sx)``
    (``shell_prof`` = ``(R, shell_thickness, sigmas, background)``, evaluated per voxel)."""
    if np.ndim(blur):
        return _rasterise_aniso(traced, specs, frame_rot, centre, centre_zyx, shape, sp, channels, step_um,
                                blur, fibre_intensity, noise, shell_prof, noise_rngs, photons)
    # trilinear splatting already spreads a fibre by a hat kernel of variance d^2/6 per axis:
    # blur by the rest so that the total is the requested isotropic physical sigma
    sigma_vox = tuple(np.sqrt(max(blur**2 - d * d / 6.0, 0.0)) / d for d in sp)
    norm = 2 * np.pi * blur**2 if blur > 0 else float(np.prod(sp)) ** (2.0 / 3.0)
    inv_dr = np.float32(1.0 / _SHELL_DR)
    zz = np.arange(shape[0]) * sp[0] - centre_zyx[0]
    yy = (np.arange(shape[1]) * sp[1] - centre_zyx[1])[:, None]
    xx = (np.arange(shape[2]) * sp[2] - centre_zyx[2])[None, :]
    rho2 = (yy**2 + xx**2).astype(np.float32)

    def shell_slab(z: int) -> np.ndarray:  # the tabulated radial profile, interpolated
        r = np.sqrt(rho2 + np.float32(zz[z] ** 2)) * inv_dr  # radial grid index
        i = np.minimum(r.astype(np.int32), len(shell_prof) - 2)
        fr = r - i
        return shell_prof[i] * (1 - fr) + shell_prof[i + 1] * fr

    return _fill_frames(traced, specs, frame_rot, centre, shape, sp, channels, step_um / float(np.prod(sp)),
                        sigma_vox, np.float32(255.0 * fibre_intensity * norm), noise, photons, noise_rngs, shell_slab)


def _rasterise_aniso(traced, specs, frame_rot, centre, centre_zyx, shape, sp, channels, step_um, sigmas,
                     fibre_intensity, noise, shell, noise_rngs, photons) -> np.ndarray:
    """:func:`_rasterise` with an anisotropic Gaussian PSF ``sigmas`` = (sz, sy, sx) µm."""
    R, thick, _, background = shell
    s = np.asarray(sigmas, float)
    sigma_vox = tuple(np.sqrt(max(b * b - d * d / 6.0, 0.0)) / d for b, d in zip(s, sp))
    s1, s2 = np.sort(s)[::-1][:2]  # a fibre's peak: 1 / (2 pi s_a s_b) over its normal plane
    norm = 2 * np.pi * s1 * s2 if s2 > 0 else float(np.prod(sp)) ** (2.0 / 3.0)
    zz = np.arange(shape[0]) * sp[0] - centre_zyx[0]
    yy = (np.arange(shape[1]) * sp[1] - centre_zyx[1])[:, None]
    xx = (np.arange(shape[2]) * sp[2] - centre_zyx[2])[None, :]
    rho2 = yy**2 + xx**2
    ys2 = (s[1] ** 2 * yy**2 + s[2] ** 2 * xx**2)
    tiny = 1e-6 * max(float(s.max()), 1e-3)
    shell_slabs = []
    for z in range(shape[0]):  # the shell, once: each voxel blurred with the sigma along its normal
        r = np.sqrt(rho2 + zz[z] ** 2)
        sn = np.sqrt((ys2 + s[0] ** 2 * zz[z] ** 2) / np.maximum(r * r, 1e-18))
        sn = np.maximum(sn, tiny)
        shell_slabs.append((255.0 * background * (_ball_blur_along(r, R + thick, sn)
                                                  - _ball_blur_along(r, R, sn))).astype(np.float32))
    return _fill_frames(traced, specs, frame_rot, centre, shape, sp, channels, step_um / float(np.prod(sp)),
                        sigma_vox, np.float32(255.0 * fibre_intensity * norm), noise, photons, noise_rngs,
                        lambda z: shell_slabs[z].copy())


def _fill_frames(traced, specs, frame_rot, centre, shape, sp, channels, weight, sigma_vox, scale, noise, photons,
                 noise_rngs, shell_slab) -> np.ndarray:
    """The uint8 image (T, Z, C, Y, X) of :func:`_rasterise`: per frame and channel the channel's
    fibres (splatted with ``weight`` µm per µm³, blurred by ``sigma_vox``, times ``scale``) on
    ``shell_slab(z)``, with noise, slab by slab."""
    frames = len(frame_rot)
    data = np.zeros((frames, shape[0], channels, shape[1], shape[2]), np.uint8)
    vol = np.zeros(shape, np.float32) if any(spec["channel"] < channels for spec in specs) else None
    for t in range(frames):
        for c in range(channels):
            mine = [i for i, spec in enumerate(specs) if spec["channel"] == c]
            with step(f"frame {t + 1}/{frames} channel {c + 1}/{channels}: rasterising {len(mine)} layer(s)"):
                if mine:
                    vol[...] = 0.0
                    for i in mine:
                        _splat(traced[i] @ frame_rot[t].T + centre, weight, shape, sp, vol)
                    if max(sigma_vox) > 0:
                        ndimage.gaussian_filter(vol, sigma_vox, output=vol, mode="constant", truncate=4.0)
                    vol *= scale
                nrng = noise_rngs[t * channels + c]
                for z in range(shape[0]):  # slab loop: each slab is vectorised
                    img = shell_slab(z)
                    if mine:
                        img += vol[z]
                    img = add_noise(img, photons, noise, nrng)
                    np.clip(img, 0.0, 255.0, out=img)
                    data[t, z, c] = np.rint(img).astype(np.uint8)
    return data


def _jsonable(v):
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if isinstance(v, dict):
        return {k: _jsonable(x) for k, x in v.items()}
    return v


def _make_truth(R, centre, sp, shape, frames, channels, specs, frame_rot, g, shell, params):
    layers_out = []
    for i, s in enumerate(specs):
        layers_out.append({
            "layer": i, "name": f"layer{i}", "depth": s["depth"], "radius": R + s["depth"],
            "channel": s["channel"], "rotation_deg": s["rotation"], "phase": s["phase"],
            "defect_dirs": s["dirs"].tolist(), "charges": s["charges_"].tolist(),
            "pole": s["pole"].tolist(), "n_fibres": s["n_fibres"],
        })
    records = []
    frames_out = []
    for t in range(frames):
        fl = []
        for i, s in enumerate(specs):
            u = s["dirs"] @ frame_rot[t].T
            inner = centre + R * u
            lay = centre + (R + s["depth"]) * u
            defs = []
            for k in range(len(u)):
                rec = {
                    "t": t, "layer": i, "channel": s["channel"], "charge": float(s["charges_"][k]),
                    "x": inner[k, 0], "y": inner[k, 1], "z": inner[k, 2],
                    "x_layer": lay[k, 0], "y_layer": lay[k, 1], "z_layer": lay[k, 2],
                    "ux": u[k, 0], "uy": u[k, 1], "uz": u[k, 2],
                }
                records.append(rec)
                defs.append(rec)
            fl.append({"layer": i, "defects": defs})
        frames_out.append({"t": t, "rotation": frame_rot[t].tolist(), "layers": fl})
    p = dict(params)
    p["spacing"] = list(sp)
    if isinstance(p.get("defects"), str) or p.get("defects") is None:
        p["defects"] = p.get("defects") or "tetrahedron"
    for k in ("layers", "second_layer_defects", "second_layer_charges", "charges", "rotate"):
        if p.get(k) is not None and not isinstance(p.get(k), (str, int)):
            p[k] = _jsonable(p[k])
    p["defects"] = _jsonable(p["defects"])
    return _jsonable({
        "kind": "nemo.synthetic.vesicle",
        "radius": R, "centre": centre, "spacing": list(sp), "unit": "um",
        "shape": {"T": frames, "C": channels, "Z": shape[0], "Y": shape[1], "X": shape[2]},
        "axes": "TZCYX", "shell_thickness": shell, "defect_set_rotation": g,
        "layers": layers_out, "frames": frames_out, "defects": records, "parameters": p,
        "field": "stereographic: psi(w) = phase + sum_k m_k arg(w - w_k), w = (x+iy)/(1+z) "
                 "in the frame rotating 'pole' to the south pole; frame t rotates frame 0 by "
                 "frames[t].rotation about the centre (see nemo.synthetic.truth_directors)",
    })


def truth_path(path: str | os.PathLike) -> Path:
    """Sidecar of an image: ``vesicle.tif`` -> ``vesicle.truth.json``."""
    path = Path(path)
    if path.name.endswith(".truth.json"):
        return path
    if path.suffix.lower() in (".tif", ".tiff"):
        return path.with_suffix(".truth.json")
    return path.with_name(path.name + ".truth.json")


def write_vesicle(path: str | os.PathLike, **kwargs) -> dict[str, Any]:
    """Generate a vesicle (:func:`vesicle` keyword arguments) and write it.

    Writes an ImageJ TZCYX hyperstack with calibration (``nemo.io.write_hyperstack``) and the
    ground truth as ``NAME.truth.json`` beside it (atomically).

    Parameters
    ----------
    path : path-like
        Output ``.tif``.
    **kwargs
        Passed to :func:`vesicle`.

    Returns
    -------
    truth : dict
        Also written to :func:`truth_path` ``(path)``, with ``image`` set to the file name.
    """
    from nemo.io import write_hyperstack

    path = Path(path)
    if path.suffix.lower() not in (".tif", ".tiff"):
        raise NemoError(f"output {path} should end in .tif")
    if path.parent and not path.parent.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
    data, truth = vesicle(**kwargs)
    truth["image"] = path.name
    with step(f"writing {path} ({data.nbytes / 1e6:.0f} MB)"):
        write_hyperstack(
            path, data, truth["spacing"], unit="um", axes="TZCYX",
            metadata={"nemo": "synthetic vesicle", "radius": truth["radius"],
                      "centre": truth["centre"], "truth": truth_path(path).name},
        )
    tp = truth_path(path)
    atomic.write_json(tp, truth, indent=1)
    logger.info("ground truth written to %s", tp)
    return truth


def read_truth(path: str | os.PathLike) -> dict[str, Any]:
    """Load a vesicle's ground truth from its image path or its ``.truth.json``."""
    tp = truth_path(path)
    if not tp.exists():
        raise NemoError(f"no ground truth {tp} (written by 'nemo synth' beside the image)")
    try:
        return json.loads(tp.read_text())
    except json.JSONDecodeError as exc:
        raise NemoError(f"{tp} is not valid JSON ({exc})") from None


def truth_directors(
    truth: dict[str, Any], points: ArrayLike, t: int = 0, layer: int = 0
) -> np.ndarray:
    """The exact analytic director of a generated vesicle at physical points.

    Parameters
    ----------
    truth : dict
        From :func:`vesicle` / :func:`read_truth`.
    points : array_like, shape (N, 3)
        Physical x, y, z (projected radially onto the sphere about ``truth["centre"]``).
    t, layer : int
        Frame and layer.

    Returns
    -------
    n : ndarray, shape (N, 3)
        Unit tangent directors (sign arbitrary).
    """
    lay = truth["layers"][layer]
    rot = np.asarray(truth["frames"][t]["rotation"], float)
    p = np.asarray(points, float) - np.asarray(truth["centre"], float)
    n0 = director_field(p @ rot, lay["defect_dirs"], lay["charges"], pole=lay["pole"],
                        phase=lay["phase"])
    return n0 @ rot.T
