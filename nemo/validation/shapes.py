"""Analytic shapes of the validation protocol: solids with exactly known curvature and thickness.

Each shape (ellipsoid, torus, concentric shells of spheres or ellipsoids) is written as a
blurred solid from its signed distance, so that its mid-intensity level is the analytic
surface and ``nemo mesh`` reconstructs it exactly like a microscopy stack. The reference
values (mean and Gaussian curvature, wall thickness along the normals) are closed-form.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence

import numpy as np
from scipy.special import erf

from nemo.errors import NemoError
from nemo.synthetic import add_noise, psf_sigmas, snr

SHAPES = ("ellipsoid", "torus", "shells")


def _ellipsoid_sdf(p: np.ndarray, axes: Sequence[float]) -> np.ndarray:
    """First-order signed distance to an ellipsoid (exact zero set; ≈ distance nearby)."""
    a = np.asarray(axes, float)
    q = np.sqrt(((p / a) ** 2).sum(-1))
    grad = np.linalg.norm(p / a**2, axis=-1) / np.maximum(q, 1e-12)
    return (q - 1.0) / np.maximum(grad, 1e-12)


def _torus_sdf(p: np.ndarray, major: float, minor: float) -> np.ndarray:
    rho = np.hypot(p[..., 0], p[..., 1])
    return np.hypot(rho - major, p[..., 2]) - minor


def _extent(spec: dict) -> np.ndarray:
    k = spec["kind"]
    if k == "ellipsoid":
        return np.asarray(spec["axes"], float)
    if k == "torus":
        R, r = spec["major"], spec["minor"]
        return np.array([R + r, R + r, r], float)
    return np.asarray(spec["outer"], float)


def shape_sdf(spec: dict, p: np.ndarray) -> np.ndarray:
    """Signed distance (negative inside the solid) of a shape centred at the origin."""
    k = spec["kind"]
    if k == "ellipsoid":
        return _ellipsoid_sdf(p, spec["axes"])
    if k == "torus":
        return _torus_sdf(p, spec["major"], spec["minor"])
    if k == "shells":
        return np.maximum(_ellipsoid_sdf(p, spec["outer"]), -_ellipsoid_sdf(p, spec["inner"]))
    raise NemoError(f"unknown shape kind {k!r}; choose one of {', '.join(SHAPES)}")


#: Largest stack ``shape_volume`` writes (voxels): 1 GB of uint8, 4 GB while it is rendered.
MAX_SHAPE_VOXELS = 1e9


def _numbers(spec: dict, key: str, count: tuple[int, ...], low: float, strict: bool = True) -> None:
    """``spec[key]`` (when present) is ``count`` finite numbers above ``low`` (≥ if not ``strict``)."""
    if key not in spec or spec[key] is None:
        return
    value = spec[key]
    items = value.tolist() if isinstance(value, np.ndarray) else value
    items = list(items) if isinstance(items, (list, tuple)) else [items]
    ok = (len(items) in count and all(isinstance(v, numbers.Real) and not isinstance(v, (bool, np.bool_))
                                      for v in items)
          and all(math.isfinite(v) and (v > low if strict else v >= low) for v in items))
    if not ok:
        what = " or ".join(f"{c} number{'s' if c > 1 else ''}" for c in count)
        raise NemoError(f"shape {key} must be {what} {'>' if strict else '≥'} {low:g}, got {value!r}")


def _check_spec(spec: dict) -> None:
    """Refuse a shape spec with a wrong kind, missing or out-of-range values (named)."""
    need = {"ellipsoid": ("axes",), "torus": ("major", "minor"), "shells": ("inner", "outer")}
    if spec.get("kind") not in need:
        raise NemoError(f"unknown shape kind {spec.get('kind')!r}; choose one of {', '.join(SHAPES)}")
    missing = [k for k in need[spec["kind"]] if k not in spec]
    if missing:
        raise NemoError(f"shape '{spec['kind']}' needs {', '.join(missing)} (µm)")
    for key in ("axes", "inner", "outer", "spacing"):
        _numbers(spec, key, (3,), 0.0)
    for key in ("major", "minor"):
        _numbers(spec, key, (1,), 0.0)
    _numbers(spec, "blur", (1, 3), 0.0)
    _numbers(spec, "photons", (1,), 0.0)
    for key in ("margin", "noise"):
        _numbers(spec, key, (1,), 0.0, strict=False)
    for key in ("foreground", "background"):
        _numbers(spec, key, (1,), 0.0, strict=False)
    if spec["kind"] == "torus" and spec["minor"] >= spec["major"]:
        raise NemoError(f"torus minor radius {spec['minor']} must be below its major radius {spec['major']}")
    if spec["kind"] == "shells" and not all(i < o for i, o in zip(spec["inner"], spec["outer"])):
        raise NemoError(f"shells: every inner axis must be below the outer one, got {spec['inner']} and {spec['outer']}")
    seed = spec.get("seed", 0)
    if not (isinstance(seed, numbers.Integral) and not isinstance(seed, (bool, np.bool_)) and seed >= 0):
        raise NemoError(f"shape seed must be an integer ≥ 0, got {seed!r}")


def shape_volume(spec: dict, rng: np.random.Generator | int | None = None) -> tuple[np.ndarray, dict]:
    """A blurred solid shape as a uint8 (Z, Y, X) volume and its analytic description.

    Parameters
    ----------
    spec : dict
        ``kind``: ``ellipsoid`` (``axes`` [a, b, c] µm along x, y, z), ``torus`` (``major``,
        ``minor`` µm, axis z) or ``shells`` (solid between the ellipsoids ``inner`` and ``outer``,
        [a, b, c] each; equal axes = concentric spheres); ``spacing`` [dz, dy, dx] µm; optional
        ``blur`` (µm, default one lateral voxel: an error-function edge; three values
        [sz, sy, sx] = an anisotropic Gaussian PSF, the edge blurred with the sigma along the
        surface normal), ``margin`` (µm), ``photons`` (shot noise, photons at the 255 level) and
        ``noise`` (Gaussian std, 0-255 scale), ``foreground``/``background`` intensities.
    rng : Generator or int, optional
        For the noise.

    Returns
    -------
    volume : ndarray of uint8, shape (Z, Y, X)
    truth : dict
        The spec plus ``centre`` (physical x, y, z), ``threshold`` (mid intensity), ``blur_zyx``
        and ``snr`` (``nemo.synthetic.snr``: (foreground − background) / noise std at the
        background; None without noise).
    """
    _check_spec(spec)
    sp = np.asarray(spec.get("spacing", [1.0, 1.0, 1.0]), float)
    sig = np.asarray(psf_sigmas(spec.get("blur", sp[2])))  # (sz, sy, sx)
    blur = float(sig.max())
    fg, bg = float(spec.get("foreground", 200)), float(spec.get("background", 20))
    ext = _extent(spec)
    margin = float(spec.get("margin", 4 * blur + 3 * sp.max()))
    half = ext + margin  # x, y, z
    n = (2 * np.ceil(half / sp[::-1]) + 1).astype(int)  # voxels along x, y, z
    if np.prod(n.astype(float)) > MAX_SHAPE_VOXELS:
        raise NemoError(f"the shape needs {n[2]} x {n[1]} x {n[0]} voxels (Z, Y, X), more than "
                        f"{MAX_SHAPE_VOXELS:.0e}: give smaller axes or margin, or a coarser spacing")
    centre = (n - 1) / 2 * sp[::-1]
    z = np.arange(n[2]) * sp[0] - centre[2]
    y = np.arange(n[1]) * sp[1] - centre[1]
    x = np.arange(n[0]) * sp[2] - centre[0]
    vol = np.empty((n[2], n[1], n[0]), np.float32)
    for i, zi in enumerate(z):  # plane by plane: bounded memory (not a hot path)
        p = np.stack(np.broadcast_arrays(x[None, :], y[:, None], np.full((1, 1), zi)), -1)
        d = shape_sdf(spec, p)
        if sig[0] == sig[1] == sig[2]:
            s = blur
        else:  # the sigma along the edge's normal (the sdf's gradient, central differences)
            h = 0.25 * float(sp.min())
            g = np.stack([(shape_sdf(spec, p + h * e) - shape_sdf(spec, p - h * e)) for e in np.eye(3)], -1)
            g /= np.maximum(np.linalg.norm(g, axis=-1, keepdims=True), 1e-12)
            s = np.sqrt((g**2 * (sig[::-1] ** 2)).sum(-1))  # p, g are (x, y, z); sig is (z, y, x)
            s = np.where(s > 0, s, blur)  # no gradient (a centre): any sigma, far from the edge
        vol[i] = bg + (fg - bg) * 0.5 * (1 - erf(d / (np.sqrt(2) * s)))
    photons, noise = spec.get("photons"), float(spec.get("noise") or 0.0)
    if photons:
        vol = add_noise(vol, float(photons), noise, np.random.default_rng(rng))
    elif noise:
        gen = np.random.default_rng(rng)
        vol += gen.normal(0, noise, vol.shape).astype(np.float32)
    vol = np.clip(np.rint(vol), 0, 255).astype(np.uint8)
    truth = dict(spec)
    truth.update(centre=centre.tolist(), threshold=(fg + bg) / 2, spacing=sp.tolist(),
                 blur_zyx=sig.tolist(), snr=snr(fg, bg, noise, photons))
    return vol, truth


def _project_ellipsoid(p: np.ndarray, axes) -> tuple[np.ndarray, np.ndarray]:
    """Radial projection onto the ellipsoid and its outward unit normal there."""
    a = np.asarray(axes, float)
    q = np.sqrt(((p / a) ** 2).sum(-1, keepdims=True))
    s = p / q
    n = s / a**2
    return s, n / np.linalg.norm(n, axis=-1, keepdims=True)


def ellipsoid_curvature(p: np.ndarray, axes) -> tuple[np.ndarray, np.ndarray]:
    """Analytic mean and Gaussian curvature (outward normal: sphere H = +1/R) at points ``p``
    (N, 3), projected radially onto the ellipsoid x²/a² + y²/b² + z²/c² = 1."""
    a2 = np.asarray(axes, float) ** 2
    s, _ = _project_ellipsoid(p, axes)
    w = (s**2 / a2**2).sum(-1)
    prod = a2.prod()
    K = 1.0 / (prod * w**2)
    H = (a2.sum() - (s**2).sum(-1)) / (2.0 * prod * w**1.5)
    return H, K


def torus_curvature(p: np.ndarray, major: float, minor: float) -> tuple[np.ndarray, np.ndarray]:
    """Analytic H (outward normal) and K of a torus (axis z) at the nearest surface points."""
    rho = np.hypot(p[:, 0], p[:, 1])
    cosv = (rho - major) / np.maximum(np.hypot(rho - major, p[:, 2]), 1e-12)
    den = minor * (major + minor * cosv)
    return (major + 2 * minor * cosv) / (2 * den), cosv / den


def shell_thickness(p: np.ndarray, inner, outer) -> np.ndarray:
    """Exact distance along the inner ellipsoid's outward normal (at the radial projection of
    ``p``) to the outer ellipsoid."""
    s, n = _project_ellipsoid(p, inner)
    A2 = np.asarray(outer, float) ** 2
    qa = (n**2 / A2).sum(-1)
    qb = 2 * (s * n / A2).sum(-1)
    qc = (s**2 / A2).sum(-1) - 1
    return (-qb + np.sqrt(qb**2 - 4 * qa * qc)) / (2 * qa)
