"""Morphology of a surface: curvature, inter-surface thickness, area, volume, topology.

Method note §3, paper methods "Morphological analysis".

* :func:`curvature` -- mean and Gaussian curvature (and principal curvatures/directions) from a
  least-squares quadric fitted to the neighbours within a physical radius of a random subset of
  vertices, inverse-distance interpolated to every vertex (paper eq. ``mesh-interpolation``),
  then averaged over the surface by a debiased diffusion of width ``smooth`` × radius (0 = the
  paper's values; :func:`smooth_on_surface`). On an open surface (cut by the image border) a
  vertex within the radius of the rim is fitted at the largest smaller radius whose ball stays
  off the rim (a fit reaching the rim would see the surface on one side only), down to
  :data:`RIM_MIN_EDGES` edges and half the radius; closer vertices are NaN. ``fit_radius``
  records each radius.
* :func:`default_radius` -- the fitting radius from the surface itself: where the curvature of
  pilot fits changes least with the radius (past the wall's roughness, short of the shape's
  change), between 4 and 32 mean edges, at most 0.6 × the size √(A/4π) of a closed surface's
  largest piece; on an open surface at most half the largest distance to the rim, and then at
  most the median one (half the vertices keep a fit).
* :func:`thickness` -- distance along the vertex normal from one surface to another, by ray
  casting (Embree through trimesh when available); NaN where the ray finds nothing.
* :func:`measure` -- area, enclosed volume, Euler characteristic, genus, components, discrete
  ∫K dA with its Gauss–Bonnet check, area-weighted mean curvature.
* :func:`vertex_areas` -- barycentric vertex areas (they sum to the mesh area); the shared
  :func:`nemo.mesh.vertex_areas`, re-exported here.

Sign conventions: vertex normals point outward, and a sphere of radius R has H = +1/R,
K = +1/R². Thickness is the signed distance d = (V* − V)·N of the paper: positive when the other
surface lies on the outer side (+N), negative when it lies inside.

Choice of the fitted surface
----------------------------
The paper fits z ≈ aξ² + bη² + cξη in the frame of the vertex normal (``fit="quadric"``). Two
errors limit it: a tilted vertex normal leaks into a, b, c, and the neglected 4th-order terms
bias the curvature upward by ~r²/4R² (r: fitting radius, R: radius of curvature). So:

* ``"quadratic"`` adds linear and constant terms, z ≈ aξ² + bη² + cξη + dξ + eη + f, and takes
  the curvature of that graph exactly (metric g = I + ∇h∇hᵀ, curvature tensor
  C = −∇²h / √(1 + |∇h|²)): independent of normal errors and of the vertex's own offset;
* ``"quartic"`` fits every term up to 4th order (15 terms, an osculating jet): no r²/R² bias,
  so a larger radius can average more vertices, but it needs ~60+ neighbours (samples with
  fewer than :data:`QUARTIC_MIN_NEIGHBOURS` use the quadratic fit);
* ``"auto"`` (default) takes quartic when the median sample has at least
  :data:`AUTO_QUARTIC_NEIGHBOURS` neighbours within the radius, else quadratic.

Without the bias, the quartic fit can use a larger radius and so average over more vertices:
it is the most accurate at the radii the default picks, the quadratic one at radii too small
for a quartic. On noisy meshes (staircase left by a thresholded, little-blurred volume) every
fit needs a larger radius, and the quartic fit at the largest radius the shape allows is the
most accurate. The errors against analytic shapes are measured in ``tests/test_morphology.py``
and ``docs/validation.md``.
"""

from __future__ import annotations

import math
import numbers
import warnings
from typing import Literal

import numpy as np
import pandas as pd
import trimesh
from scipy import special
from scipy.sparse import coo_matrix, csr_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from nemo._log import logger, pretty_unit, step
from nemo.errors import NemoError, NemoWarning
from nemo.geometry import axis_frames, edge_graph, project_tangent, rim, unit_vectors
from nemo.mesh import (
    check_mesh,
    face_normals_areas,
    mean_edge_length,
    merge_coincident_vertices,
    object_radius,
    signed_volume,
    vertex_areas,
    vertex_normals,
)

#: Fewest neighbours (besides the vertex itself) a quadric fit accepts.
MIN_NEIGHBOURS = 6
#: Default number of sampled vertices is at least this many (or all vertices if fewer) ...
MIN_DEFAULT_SAMPLES = 20_000
#: ... unless their fits would hold more (sample, neighbour) pairs than this: at a large radius
#: the discs overlap so much that fewer samples (still ≥ 8 per disc) cost less for the same map.
DEFAULT_PAIR_BUDGET = 4_000_000
#: The quartic fit needs at least this many neighbours, else that sample uses the quadratic fit.
QUARTIC_MIN_NEIGHBOURS = 30
#: ``fit="auto"`` picks the quartic fit when the median sample has at least this many neighbours.
AUTO_QUARTIC_NEIGHBOURS = 60
#: radius × median |k1| above this (or a radius above a quarter of the bounding-box diagonal)
#: warns that the fits average over too much of the surface (the quadric/quadratic fits are
#: biased by ~(r k)²/4 there; the quartic fit, without that bias, is warned at twice the value).
LARGE_RADIUS_RK = 0.5
#: Default fitting radius (:func:`default_radius`): at least this many mean edge lengths
#: (~60 neighbours: enough for a quartic fit), whatever the curvature ...
DEFAULT_MIN_EDGES = 4.0
#: ... at most this many (~3000-4000 neighbours per fit: bounds the pilot's cost; on the
#: validation's noisy shapes the best radius lay at 25 edges or less, docs/validation.md) ...
MAX_RADIUS_EDGES = 32.0
#: ... and on a closed surface at most this fraction of its size √(A/4π) (the quartic fit of a
#: sphere is biased by −0.4 / −1 / −2 % at r = 0.5 / 0.6 / 0.7 R).
DEFAULT_FRACTION = 0.6
#: The most curved (most changing) quarter of the surface sets the radius: the pilot compares
#: radii by this upper quantile of the change of the curvature, and reports R_c as this quantile
#: of 1/|k|max (robust to noise and outliers, unlike the extremes).
DEFAULT_CURVATURE_QUANTILE = 0.25
#: Vertices fitted by the pilot of :func:`default_radius` ...
PILOT_SAMPLES = 2000
#: ... fewer (at least :data:`PILOT_MIN_SAMPLES`) when their fits at the largest radius would
#: hold more (vertex, neighbour) pairs than this (a quantile needs no more; with 200, a paper
#: frame's ladder takes ~1.1 s per wall, 1.85 s with 500).
PILOT_PAIR_BUDGET, PILOT_MIN_SAMPLES = 1_000_000, 200
#: The ladder's top is lowered until at least this many vertices keep a fit off the rim there.
LADDER_MIN_PROBES = 50
#: The climb stops early once the change has grown for two pairs past its smallest to at least
#: this multiple of it: the shape's change grows at least as the radius squared (× 2 per rung),
#: while a rough wall's change can rise by 1.2–1.6 × over a few rungs and then fall (the SNR-3
#: vesicles' walls, whose bumps are a few µm wide; docs/validation.md "The climb's early stop").
CLIMB_STOP_GROWTH = 2.0
#: Width (σ) of the averaging of H and K over the surface after the fits, as a fraction of the
#: fitting radius (a debiased diffusion, :func:`smooth_on_surface`). On the validation's noisy
#: shapes it brings the SNR-10 ellipsoid from 2.4 to 1.3 % (H) at the default radius, and it
#: does not raise the noise-free errors (docs/validation.md, "Averaging the fits").
DEFAULT_SMOOTH = 0.35
#: ... values beyond this many robust standard deviations of their residual from a first
#: average are clipped before the second (a few wild fits on a rough wall: SNR-5 balls' median
#: K error 30 → 10 %).
OUTLIER_CLIP = 3.0
#: ... and at most this many radii (a width beyond the radius averages the shape away).
MAX_SMOOTH = 2.0
#: Adaptive averaging (``curvature(adaptive=True)``): the width per vertex and per quantity is
#: the widest of ``smooth × radius × 2^(j/2)`` for these j (narrow to wide) whose average agrees
#: with every narrower one's within :data:`ADAPT_AGREEMENT` × their noise (the intersection of
#: confidence intervals, Katkovnik's LPA-ICI): a peak of curvature (an ellipsoid's tip) keeps a
#: narrower width. Never wider than ``smooth × radius``: a wider step (j = 1) helped the protocol's
#: torus and noisy ellipsoids but flattened a sharp-tipped one (docs/validation.md "Curvature at
#: the most curved tips").
ADAPT_STEPS = (-2, -1, 0)
#: ... agreement within this many noise standard deviations of each width's average.
ADAPT_AGREEMENT = 2.0
#: ``curvature(local_fraction=f)``: a fitting radius per vertex of at most f × its radius of
#: curvature 1/|k|max (from the fits at the radius): a more curved vertex is refitted at the
#: largest radius × 2^(−k/4) below that, down to the rim band's floor (:data:`RIM_MIN_EDGES` mean
#: edges and :data:`RIM_MIN_FRACTION` × the radius). The quartic fit of a circle whose radius is
#: close to the fitting radius reads it 4.5 % flat (a torus's tube, an elongated object's poles).
#: Off by default: on a rough wall (a small ball at SNR 5) the fits' noise calls for smaller fits
#: where none is needed, and those are noise (docs/validation.md, "Curvature at the most curved
#: tips", which measures f = 0.65).
DEFAULT_LOCAL_FRACTION = 0.0
#: The walk's heat kernel is one Chebyshev series up to this mean number of steps, a product
#: of shorter ones beyond (the series agrees with the steps within 1e-5 up to ~700).
SERIES_MAX_STEPS = 350.0
#: Near an open rim, a vertex whose ball of the fitting radius holds a rim vertex is fitted at
#: the largest radius of the ladder radius × 2^(−k/4) whose ball stays off the rim, down to
#: this many mean edge lengths (closer vertices stay NaN): a full, smaller neighbourhood
#: instead of a one-sided one (:func:`_rim_band_fits`).
RIM_MIN_EDGES = 6.0
#: ... and down to this fraction of the radius (on a noisy wall, where the radius grew with the
#: noise, much smaller fits are noise: K biased negative, fake saddles along the rim) ...
RIM_MIN_FRACTION = 0.5
#: ... fitted at this many vertices per fitting disc of their radius (interpolated between; the
#: band is narrower than the interior's interpolation reaches: 8 per disc erred by 5 %).
RIM_SAMPLES_PER_DISC = 128.0
#: Pairs (sample, neighbour) processed at once; bounds the memory of the fit (~120 MB for the quartic fit).
_PAIRS_PER_CHUNK = 200_000

FitKind = Literal["auto", "quadric", "quadratic", "quartic"]


# --------------------------------------------------------------------------------------------
# small helpers
# --------------------------------------------------------------------------------------------


def _as_rng(rng: np.random.Generator | int | None) -> np.random.Generator:
    return rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)


def _unit_name(mesh: trimesh.Trimesh) -> str:
    return getattr(mesh, "units", None) or "um"


# --------------------------------------------------------------------------------------------
# curvature
# --------------------------------------------------------------------------------------------


def default_n_samples(n_vertices: int, area: float, radius: float) -> int:
    """Default number of sampled vertices for :func:`curvature`.

    About eight samples per fitting disc (π r²), so the samples are ~0.6 r apart and the
    k-nearest interpolation blurs no more than the fit itself; at least
    :data:`MIN_DEFAULT_SAMPLES` (fewer when their fits would exceed
    :data:`DEFAULT_PAIR_BUDGET` neighbour pairs, but never fewer than eight per disc), at most
    every vertex.
    """
    disc = math.pi * radius**2
    per_disc = math.ceil(8.0 * area / disc)
    neighbours = max(1.0, n_vertices * disc / area) if area > 0 else 1.0
    floor = min(MIN_DEFAULT_SAMPLES, math.ceil(DEFAULT_PAIR_BUDGET / neighbours))
    return int(min(n_vertices, max(floor, per_disc)))


def _neighbour_pairs(
    tree: cKDTree, points: np.ndarray, radius: float
) -> tuple[np.ndarray, np.ndarray]:
    """All (i, j) with |points[i] − tree.data[j]| ≤ radius, as flat index arrays."""
    lists = tree.query_ball_point(points, radius, return_sorted=False)
    counts = np.fromiter((len(x) for x in lists), dtype=np.int64, count=len(lists))
    if counts.sum() == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    j = np.concatenate([np.asarray(x, dtype=np.int64) for x in lists if len(x)])
    i = np.repeat(np.arange(len(points), dtype=np.int64), counts)
    return i, j


def smooth_on_surface(mesh: trimesh.Trimesh, values: np.ndarray, sigma: float, debias: bool = False,
                      normals: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """Average per-vertex values over the surface: a diffusion along the mesh's edges, width σ.

    A step of a random walk on the mesh graph moves a value to a vertex or one of its edge
    neighbours (:func:`_surface_walk`); the steps have no mean in the tangent plane, so the walk
    follows the surface without drifting towards denser vertices (which would shift a sloped
    field). A step spreads by s²/2 per tangent axis, s² its mean squared length, so τ =
    σ² / (s²/2) steps on average give a Gaussian-like kernel G_σ (within ~10 % of σ on an
    irregular marching-cubes mesh) that never reaches across a thin wall or to another object.
    NaN values take no part (the same kernel on the values and on their weights, then divided)
    and stay NaN. The products run in float32 (twice as fast; sums of a few hundred terms).

    Parameters
    ----------
    mesh : trimesh.Trimesh
        Surface, vertices in physical units.
    values : ndarray, shape (N,) or (N, C)
        Per-vertex values.
    sigma : float
        Width of the kernel in the mesh's unit (set from the mesh's mean step: where edge
        lengths vary, it scales with the local edge); 0 returns the values unchanged; at most
        twice the object's radius sqrt(area / 4π), where the kernel is already uniform.
    debias : bool
        Return 2 G_σ f − G_√2σ f instead of G_σ f (Richardson extrapolation: the σ² term of the
        Gaussian average, (σ²/2) Δf, cancels, so a peak of f is not flattened; a longer series).
    normals : ndarray, shape (N, 3), optional
        Unit vertex normals (default: :func:`vertex_normals`).

    Returns
    -------
    smoothed : ndarray, the shape of ``values``
    products : int
        Number of products with the walk's transition matrix (0: nothing to average).
    """
    values = np.asarray(values, dtype=np.float64)
    n = len(mesh.vertices)
    if not (math.isfinite(sigma) and sigma >= 0):
        raise NemoError(f"the averaging width must be a length ≥ 0, got {sigma}")
    if values.shape[:1] != (n,) or values.ndim > 2:
        raise NemoError(f"values must have one row per vertex, shape ({n},) or ({n}, C); got {values.shape}")
    if normals is not None and np.shape(normals) != (n, 3):
        raise NemoError(f"normals must have shape ({n}, 3), got {np.shape(normals)}")
    if sigma == 0:
        return values.copy(), 0
    walk = _surface_walk(mesh, vertex_normals(mesh) if normals is None else normals)
    return _diffuse(walk, values, _capped_width(mesh, sigma), debias)


def _capped_width(mesh: trimesh.Trimesh, sigma: float) -> float:
    """``sigma``, at most twice the object's radius sqrt(area / 4π): there the kernel is already
    uniform over the object (a sphere's l = 1 mode keeps e^-4), and a wider one only costs time
    (7 minutes for σ = 400 µm on a 10 µm sphere)."""
    return min(float(sigma), 2.0 * object_radius(mesh))


def _diffuse(walk: tuple[csr_matrix, float], values: np.ndarray, sigma: float,
             debias: bool) -> tuple[np.ndarray, int]:
    """:func:`smooth_on_surface` with the walk (:func:`_surface_walk`) given.

    The kernel G_σ is the walk's heat kernel exp(−τ (I − P)) (a Poisson number of steps of mean
    τ = σ² / (s²/2)), summed as Chebyshev series in P (:func:`_heat_series`): ~6 √τ products
    instead of τ steps. Beyond :data:`SERIES_MAX_STEPS` it is a product of shorter kernels (the
    series of a non-reversible walk grows like ρ^k, ρ ≈ 1.08, and would lose its precision).
    Values and weights are divided per kernel, then 2 G_σ − G_√2σ is formed.

    Parameters
    ----------
    walk : (csr_matrix (N, N), float)
        Transition matrix and mean squared step.
    values : ndarray, shape (N,) or (N, C)
    sigma : float
    debias : bool

    Returns
    -------
    smoothed : ndarray, the shape of ``values``
    products : int
        Products with the transition matrix.
    """
    if walk[1] == 0.0:
        return values.copy(), 0
    tau = sigma**2 / (0.5 * walk[1])
    flat = values.reshape(len(values), -1)
    ratios, products = _kernel_averages(walk, flat, (tau, 2.0 * tau) if debias else (tau,),
                                        SERIES_MAX_STEPS * (2.0 if debias else 1.0))  # G_√2σ = G_σ G_σ
    smoothed = 2.0 * ratios[0] - ratios[1] if debias else ratios[0]
    return np.where(np.isfinite(flat), smoothed, np.nan).reshape(values.shape), products


def _kernel_averages(walk: tuple[csr_matrix, float], values: np.ndarray, taus: tuple[float, ...],
                     longest: float) -> tuple[list[np.ndarray], int]:
    """G_τ f (N, C) for each τ of ``taus`` (ascending; NaN takes no part: the same kernel on the
    values and on their weights, then divided) and the number of products: one Chebyshev series
    with an accumulator per τ when the last is at most ``longest`` steps, else a chain (G_τ' =
    G_(τ'−τ) G_τ, each a product of series of at most :data:`SERIES_MAX_STEPS` steps)."""
    transition = walk[0]
    c = values.shape[1]
    usable = np.isfinite(values)
    state = np.concatenate([np.where(usable, values, 0.0), usable], axis=1).astype(np.float32)  # values, weights
    if taus[-1] <= longest:
        kernels, products = _heat_series(transition, state, tuple(taus))
    else:
        kernels, products, done = [], 0, 0.0
        for tau in taus:  # a handful of widths
            n = math.ceil((tau - done) / SERIES_MAX_STEPS)
            for _ in range(n):
                (state,), k = _heat_series(transition, state, ((tau - done) / n,))
                products += k
            kernels.append(state)
            done = tau
    with np.errstate(invalid="ignore", divide="ignore"):
        return [kernel[:, :c].astype(np.float64) / kernel[:, c:] for kernel in kernels], products


def _heat_series(transition: csr_matrix, state: np.ndarray, taus: tuple[float, ...]) -> tuple[list, int]:
    """exp(−τ (I − P)) ``state`` for each τ of ``taus``, from one Chebyshev sequence T_k(P) state.

    The coefficients are (2 − δ_k0) e^−τ I_k(τ) (scipy.special.ive), cut below 1e-7 of their
    largest; returns the (N, K) results, one per τ, and the number of products.
    """
    order = np.arange(int(12.0 * math.sqrt(max(taus)) + 20.0))  # e^−τ I_k(τ) < 1e-30 beyond
    coefficients = np.stack([special.ive(order, t) for t in taus])
    coefficients[:, 1:] *= 2.0
    keep = np.abs(coefficients) > 1e-7 * np.abs(coefficients).max(axis=1, keepdims=True)
    n_terms = max(2, int(np.flatnonzero(keep.any(axis=0)).max()) + 1)
    coefficients = coefficients[:, :n_terms].astype(np.float32)
    previous, current = state, transition @ state
    totals = [a[0] * previous + a[1] * current for a in coefficients]
    for k in range(2, n_terms):  # T_k+1 = 2 P T_k − T_k−1
        previous, current = current, 2.0 * (transition @ current) - previous
        for total, a in zip(totals, coefficients):
            total += a[k] * current
    return totals, n_terms - 1


def _surface_walk(mesh: trimesh.Trimesh, normals: np.ndarray) -> tuple[csr_matrix, float]:
    """One step of :func:`smooth_on_surface`: transition matrix (N, N) float32 and E|Δ|².

    Each vertex moves to itself or an edge neighbour, with probability 1 / (degree + 1) tilted
    by (1 − λ·Δ) (Δ: the move in the vertex's tangent plane, λ solving Σ p Δ = 0 by least
    squares, negative ones clipped): the walk is then unbiased for a linear field (a plain
    1 / (degree + 1) walk drifts by a third of a step's length on a marching-cubes mesh; the cotangent
    Laplacian, also unbiased, needs ~30 × the explicit steps on its slivers or a 4 s
    factorisation at 190 k vertices).
    """
    n = len(mesh.vertices)
    graph = edge_graph(mesh).tocoo()  # both directions of every edge
    i, j = graph.row.astype(np.int64), graph.col.astype(np.int64)
    base = 1.0 / (np.bincount(i, minlength=n) + 1.0)
    move = np.asarray(mesh.vertices)[j] - np.asarray(mesh.vertices)[i]
    t1, t2 = axis_frames(np.nan_to_num(normals))
    u, v = np.einsum("ij,ij->i", move, t1[i]), np.einsum("ij,ij->i", move, t2[i])
    p = base[i]
    mu_u, mu_v = np.bincount(i, p * u, n), np.bincount(i, p * v, n)
    cuu, cuv, cvv = np.bincount(i, p * u * u, n), np.bincount(i, p * u * v, n), np.bincount(i, p * v * v, n)
    det = cuu * cvv - cuv**2
    ok = det > 1e-12 * (cuu + cvv) ** 2
    lam_u = np.where(ok, (cvv * mu_u - cuv * mu_v) / np.where(ok, det, 1.0), 0.0)
    lam_v = np.where(ok, (cuu * mu_v - cuv * mu_u) / np.where(ok, det, 1.0), 0.0)
    p = p * np.clip(1.0 - lam_u[i] * u - lam_v[i] * v, 0.0, None)
    stay = 1.0 - np.bincount(i, p, n)
    walk = coo_matrix((np.concatenate([p, stay]), (np.concatenate([i, np.arange(n)]), np.concatenate([j, np.arange(n)]))),
                      shape=(n, n)).tocsr().astype(np.float32)
    return walk, float(np.mean(np.bincount(i, p * (u * u + v * v), n)))


def _monomials(fit: str) -> list[tuple[int, int]]:
    """Exponents (p, q) of the terms ξ^p η^q fitted for ``fit``; the first five are always
    ξ², η², ξη and (except "quadric") ξ, η."""
    if fit == "quadric":
        return [(2, 0), (0, 2), (1, 1)]
    terms = [(2, 0), (0, 2), (1, 1), (1, 0), (0, 1), (0, 0)]
    if fit == "quartic":
        terms += [(3 - q, q) for q in range(4)] + [(4 - q, q) for q in range(5)]
    return terms


def _moments(starts: np.ndarray, u: np.ndarray, v: np.ndarray, w: np.ndarray, deg: int):
    """Per-centre sums Σ u^a v^b (a + b ≤ 2 deg) and Σ w u^a v^b (a + b ≤ deg).

    The pairs are sorted by centre and ``starts`` are the first pair of each centre (every
    centre has at least itself as a pair), so one ``np.add.reduceat`` over a contiguous
    (n_moments, n_pairs) array sums all of them at once.

    Returns
    -------
    mom : dict[(a, b), int], rhs : dict[(a, b), int], sums : ndarray (n_moments, n_centres)
    """
    pu = [np.ones_like(u)]
    pv = [np.ones_like(v)]
    for _ in range(2 * deg):
        pu.append(pu[-1] * u)
        pv.append(pv[-1] * v)
    keys = [(a, t - a) for t in range(2 * deg + 1) for a in range(t + 1)]
    rkeys = [(a, t - a) for t in range(deg + 1) for a in range(t + 1)]
    rows = np.empty((len(keys) + len(rkeys), len(u)))
    for k, (a, b) in enumerate(keys):
        np.multiply(pu[a], pv[b], out=rows[k])
    for k, (a, b) in enumerate(rkeys):
        np.multiply(rows[keys.index((a, b))], w, out=rows[len(keys) + k])
    sums = np.add.reduceat(rows, starts, axis=1)
    mom = {key: k for k, key in enumerate(keys)}
    rhs = {key: len(keys) + k for k, key in enumerate(rkeys)}
    return mom, rhs, sums


def _solve_from_moments(mom: dict, rhs: dict, sums: np.ndarray, fit: str) -> np.ndarray:
    """Batched least squares for the terms of ``fit`` from precomputed moments, (n, P)."""
    mons = _monomials(fit)
    p = len(mons)
    idx = np.array([[mom[(a1 + a2, b1 + b2)] for (a2, b2) in mons] for (a1, b1) in mons])
    m = sums[idx].transpose(2, 0, 1)  # (n, P, P)
    b = sums[[rhs[key] for key in mons]].T  # (n, P)
    # a vanishing ridge keeps exactly singular systems from aborting the batched solve;
    # degenerate neighbourhoods are rejected by the caller from their spread
    m = m + (1e-12 * np.trace(m, axis1=1, axis2=2) / p)[:, None, None] * np.eye(p)
    return np.linalg.solve(m, b[..., None])[..., 0]


def _fit_chunk(
    vertices: np.ndarray,
    normals: np.ndarray,
    tree: cKDTree,
    centres: np.ndarray,
    radius: float,
    fit: str,
) -> tuple[np.ndarray, ...]:
    """Fit the local surface at the vertices ``centres`` (vectorised over all of them).

    Returns H, K, k1, k2 (n,), d1, d2 (n, 3) and the neighbour counts (n,).
    """
    n = len(centres)
    p0 = vertices[centres]
    n0 = normals[centres]
    t1, t2 = axis_frames(n0)
    i, j = _neighbour_pairs(tree, p0, radius)
    # Euclidean balls can reach across a thin structure: keep neighbours on the same side
    keep = np.einsum("ij,ij->i", normals[j], n0[i]) > 0.0
    i, j = i[keep], j[keep]
    d = (vertices[j] - p0[i]) / radius  # coordinates scaled by r: well-conditioned systems
    u = np.einsum("ij,ij->i", d, t1[i])
    v = np.einsum("ij,ij->i", d, t2[i])
    w = np.einsum("ij,ij->i", d, n0[i])
    counts = np.bincount(i, minlength=n)  # ≥ 1: every centre is its own neighbour
    count = counts - 1  # neighbours besides the vertex itself
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    mom, rhs, sums = _moments(starts, u, v, w, 4 if fit == "quartic" else 2)
    coef = _solve_from_moments(mom, rhs, sums, fit)
    if fit == "quartic":
        # too few neighbours for 15 terms (e.g. at a boundary): that centre gets the quadratic fit
        weak = count < QUARTIC_MIN_NEIGHBOURS
        if weak.any():
            coef[weak, :6] = _solve_from_moments(mom, rhs, sums[:, weak], "quadratic")
    # neighbours (nearly) on a line cannot fix a surface: smallest/largest spread of (ξ, η)
    c0 = counts.astype(np.float64)
    su, sv = sums[mom[(1, 0)]] / c0, sums[mom[(0, 1)]] / c0
    cuu = sums[mom[(2, 0)]] / c0 - su * su
    cvv = sums[mom[(0, 2)]] / c0 - sv * sv
    cuv = sums[mom[(1, 1)]] / c0 - su * sv
    half_tr = 0.5 * (cuu + cvv)
    root = np.sqrt(np.maximum(half_tr**2 - (cuu * cvv - cuv**2), 0.0))
    degenerate = (half_tr - root) <= 1e-3 * (half_tr + root)
    coef[degenerate | ~np.isfinite(coef).all(axis=1)] = np.nan
    coef[count < MIN_NEIGHBOURS] = np.nan
    # back to physical units: z = r w, ξ = r u  =>  a = A / r, d = D
    a, b, c = coef[:, 0] / radius, coef[:, 1] / radius, coef[:, 2] / radius
    if fit == "quadric":
        gx = gy = np.zeros(n)
    else:
        gx, gy = coef[:, 3], coef[:, 4]
    # graph z = h(ξ, η) at the origin: ∇h = (gx, gy), ∇²h = [[2a, c], [c, 2b]]
    g11, g12, g22 = 1.0 + gx * gx, gx * gy, 1.0 + gy * gy
    det_g = g11 * g22 - g12 * g12
    wn = np.sqrt(det_g)  # = sqrt(1 + |∇h|²)
    c11, c12, c22 = -2.0 * a / wn, -c / wn, -2.0 * b / wn  # curvature tensor, outward normal
    K = (c11 * c22 - c12 * c12) / det_g
    H = 0.5 * (g22 * c11 - 2.0 * g12 * c12 + g11 * c22) / det_g  # tr(g⁻¹ C) / 2
    disc = np.sqrt(np.maximum(H * H - K, 0.0))
    k1, k2 = H + disc, H - disc
    # principal direction of k1: (C − k1 g) x = 0 in (ξ, η); take the better-conditioned row
    r1 = np.stack([-(c12 - k1 * g12), c11 - k1 * g11], axis=1)
    r2 = np.stack([c22 - k1 * g22, -(c12 - k1 * g12)], axis=1)
    x = np.where((np.abs(r1).sum(1) >= np.abs(r2).sum(1))[:, None], r1, r2)
    umbilic = ~(np.abs(x).sum(1) > 1e-12 * np.abs(k1))
    x[umbilic] = (1.0, 0.0)
    e1 = t1 + gx[:, None] * n0  # tangent vectors of the fitted graph
    e2 = t2 + gy[:, None] * n0
    dir1 = unit_vectors(x[:, :1] * e1 + x[:, 1:] * e2)
    nrm = unit_vectors(np.cross(e1, e2))
    dir2 = np.cross(nrm, dir1)
    return H, K, k1, k2, dir1, dir2, count


def default_radius(
    mesh: trimesh.Trimesh,
    fit: FitKind = "auto",
    min_edges: float = DEFAULT_MIN_EDGES,
    fraction: float = DEFAULT_FRACTION,
    quantile: float = DEFAULT_CURVATURE_QUANTILE,
    n_probe: int = PILOT_SAMPLES,
    rng: np.random.Generator | int | None = 0,
) -> tuple[float, dict]:
    """Default fitting radius of :func:`curvature`, from the surface itself: the scale at which
    its curvature is most stable.

    A fit's error has two parts: the wall's roughness (noise, facets), which falls steeply with
    the radius, and the shape's change within the disc, which grows with it. Neither is known,
    but their sum shows in how much the estimate moves when the radius changes. The pilot fits
    the same probe vertices on a ladder of radii × √2, from ``min_edges`` mean edges up to the
    largest radius (:data:`MAX_RADIUS_EDGES` edges; on a closed surface ``fraction`` × the size
    √(A/4π) of its largest connected piece; on an open one half the largest distance of a vertex to the rim, beyond which no
    vertex has a fit off the rim). For each pair of neighbouring rungs it measures the change of
    (k1, k2), the ``1 − quantile`` quantile over the probes (the most changing quarter: its most
    curved parts are not averaged away by the flat ones), per √2 in radius. The radius is the
    geometric mean of the pair that changes least (where both estimates agree: past the
    roughness, short of the shape's change); the top rung when the change still falls there.
    On an open surface the radius is then at most the median distance to the rim (not below the
    smallest radius): a fit needs its ball off the rim, so at least half the vertices keep one.
    On a noisy wall this climbs to a wide fit (the roughness dominates), on a clean one it stays
    at a few edges; the fit that :func:`curvature` will use (``fit``) is the one compared, so
    the quadratic fit's larger bias keeps its radius smaller. Apart from the top, the object's
    size does not enter: a piece cut by the field of view gets the radius of the whole object.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        Surface with outward normals, vertices in physical units; closed or open.
    fit : {"auto", "quadric", "quadratic", "quartic"}
        The fit the radius is for (as :func:`curvature` resolves it at each radius).
    min_edges : float
        Smallest radius in mean edge lengths (:data:`DEFAULT_MIN_EDGES`), > 0.
    fraction : float
        On a closed surface, the largest radius as a fraction of its size √(A/4π), in (0, 2].
    quantile : float
        The most curved / most changing share of the surface that sets the radius, in (0, 1)
        (:data:`DEFAULT_CURVATURE_QUANTILE`); also the quantile of 1/|k|max reported as R_c.
    n_probe : int
        Most vertices the pilot fits (:data:`PILOT_SAMPLES`; fewer at a large radius, see
        :data:`PILOT_PAIR_BUDGET`); ≥ 10.
    rng : numpy.random.Generator or int, optional
        Which vertices the pilot fits (by index: the result does not depend on the pose).

    Returns
    -------
    radius : float
        Fitting radius in the mesh unit.
    info : dict
        JSON-serialisable: ``radius``, ``edge`` (h), ``radius_edges`` (radius / h),
        ``curvature_radius`` (R_c, the ``quantile`` of 1/|k|max at the rung below the radius;
        None when the pilot found no curvature, e.g. a plane), ``rim_cap`` (½ the largest rim
        distance; None on a closed surface), ``limited_by`` (``"stability"``: the pair that
        changes least; ``"size"``, ``"rim"`` or ``"edges"``: the top rung, the change still
        falling there; ``"min_edges"``: no room for a ladder, or the median distance to an open
        surface's rim is below the fewest edges; ``"coverage"``: that median distance), ``ladder`` (each rung's radius
        and the change from it to the next, 1/length), ``n_probe`` (vertices fitted),
        ``fraction``, ``quantile``.

    Raises
    ------
    NemoError
        Unusable mesh, parameters out of range, an unknown ``fit``.
    """
    check_mesh(mesh)
    _check_default_radius_args(fit, min_edges, fraction, quantile, n_probe)
    fraction = float(fraction)  # a numpy scalar computes like the Python float
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    normals = vertex_normals(mesh)
    h = mean_edge_length(mesh)
    if not (math.isfinite(h) and h > 0):
        raise NemoError(f"the mesh's mean edge length is {h}: cannot set a curvature radius from it")
    d_rim = rim(mesh.faces, len(vertices), vertices)["distance"]
    rim_cap = 0.5 * float(d_rim.max()) if np.isfinite(d_rim).all() else math.inf
    if not rim_cap > 0:
        raise NemoError("every vertex of the mesh lies on its rim (an unwelded triangle soup, or a strip one "
                        "triangle wide): no vertex has a surface around it to fit; merge the coincident vertices "
                        "(trimesh: mesh.merge_vertices()) or give a surface mesh")
    order = _as_rng(rng).permutation(np.flatnonzero(np.isfinite(normals[:, 0])))
    if len(order) == 0:
        raise NemoError("no vertex of the mesh has a usable normal (all faces have zero area); repair the mesh")
    # the largest radius: a closed surface's size (the quartic's bias), an open one's rim, the cost
    tops = {"edges": MAX_RADIUS_EDGES * h}
    if rim_cap == math.inf:  # the largest object's size, not the mesh's (several objects in one mesh)
        tops["size"] = fraction * math.sqrt(_largest_component_area(mesh) / (4 * math.pi))
    else:
        tops["rim"] = rim_cap
    top_by = min(tops, key=tops.get)
    radii = _ladder(min(min_edges * h, rim_cap), tops[top_by])
    ks, change, n_fit = _ladder_fits(vertices, normals, order, d_rim, radii, fit, n_probe, quantile)
    radii = radii[: len(ks)]  # the climb may stop early
    radius, low, limited_by = _stablest(radii, change, top_by, "rim" if rim_cap < min_edges * h else "min_edges")
    coverage = 0.99 * float(np.median(d_rim))  # just inside: a vertex needs d_rim > radius for a fit
    if rim_cap < math.inf and radius > max(coverage, radii[0]):
        radius, limited_by = (coverage, "coverage") if coverage > radii[0] else (radii[0], "min_edges")
        low = max(i for i, r in enumerate(radii) if r <= radius * (1 + 1e-9))
    r_c = _quantile_radius_of_curvature(ks[low], quantile)
    info = {
        "radius": float(radius), "edge": float(h), "radius_edges": float(radius / h),
        "curvature_radius": float(r_c) if math.isfinite(r_c) else None,
        "rim_cap": float(rim_cap) if math.isfinite(rim_cap) else None, "limited_by": limited_by,
        "ladder": [{"radius": float(r), "change": None if not math.isfinite(c) else float(c)}
                   for r, c in zip(radii, [*change, math.nan])],
        "n_probe": int(n_fit), "fraction": float(fraction), "quantile": float(quantile),
    }
    logger.info("curvature: default radius %.3g %s (%.1f edges; %s; radius of curvature %s)",
                radius, pretty_unit(_unit_name(mesh)), radius / h,
                {"stability": "where the curvature changes least with the radius",
                 "min_edges": "the fewest edges", "rim": "half the largest distance to the rim",
                 "size": f"{fraction:g} × the surface's size, the curvature still settling there",
                 "edges": f"{MAX_RADIUS_EDGES:g} edges, the curvature still settling there",
                 "coverage": "the median distance to the rim: half the vertices keep a fit"}[limited_by],
                "–" if info["curvature_radius"] is None else f"{r_c:.3g}")
    return float(radius), info


def _check_default_radius_args(fit: str, min_edges: float, fraction: float, quantile: float,
                               n_probe: int) -> None:
    """NemoError naming the parameter out of range."""
    if fit not in ("auto", "quadric", "quadratic", "quartic"):
        raise NemoError(f"unknown curvature fit {fit!r}: use auto, quadric, quadratic or quartic")
    if not (math.isfinite(min_edges) and 0 < min_edges <= MAX_RADIUS_EDGES):
        raise NemoError(f"min_edges (the smallest radius, in edge lengths) must be in (0, {MAX_RADIUS_EDGES:g}], "
                        f"got {min_edges}")
    if not (isinstance(fraction, numbers.Real) and not isinstance(fraction, bool) and math.isfinite(fraction)
            and 0 < fraction <= 2):
        raise NemoError(f"fraction of the surface's size must be in (0, 2], got {fraction}")
    if not (0 < quantile < 1):
        raise NemoError(f"quantile must be in (0, 1), got {quantile}")
    if int(n_probe) < 10:
        raise NemoError(f"the pilot needs at least 10 vertices, got n_probe={n_probe}")


def _ladder(bottom: float, top: float) -> list[float]:
    """Radii × √2 from ``bottom``, ending at ``top`` with one more, shorter step when the top is
    more than × 1.1 above the last rung (a shorter step's change, scaled per √2, magnifies its
    noise by up to × 3.6, which leans against the top: the safe side)."""
    radii = [bottom]
    while radii[-1] * math.sqrt(2.0) <= top:
        radii.append(radii[-1] * math.sqrt(2.0))
    if top > 1.1 * radii[-1]:
        radii.append(top)
    return radii


def _ladder_fits(vertices: np.ndarray, normals: np.ndarray, order: np.ndarray, d_rim: np.ndarray,
                 radii: list[float], fit: str, n_probe: int,
                 quantile: float) -> tuple[list[np.ndarray], list[float], int]:
    """(k1, k2) of the same probe vertices up the ladder, shape (P, 2) per rung, the change per
    pair of rungs (:func:`_ladder_change`) and P; the rungs fitted are the first ``len(ks)`` of
    ``radii``.

    The probes are the first of ``order`` whose ball stays off the rim at the largest radius
    (those farthest from the rim if none does): ``n_probe`` at most, fewer (not below
    :data:`PILOT_MIN_SAMPLES`) when their fits at the largest radius would exceed
    :data:`PILOT_PAIR_BUDGET` (vertex, neighbour) pairs. On an open surface the ladder ends
    below any rung at which fewer than :data:`LADDER_MIN_PROBES` vertices stay off the rim. The
    climb stops early once the change (:func:`_ladder_change`) has grown for two pairs past its
    smallest, to :data:`CLIMB_STOP_GROWTH` × it (:func:`_climb_settled`): the largest fits cost most.
    """
    tree = cKDTree(vertices)
    while len(radii) > 1 and np.count_nonzero(d_rim[order] > radii[-1]) < LADDER_MIN_PROBES:
        radii = radii[:-1]  # too few vertices keep a fit off the rim at the top: a lower top
    probe = order[d_rim[order] > radii[-1]]
    if len(probe) == 0:
        probe = order[np.argsort(-d_rim[order], kind="stable")]
    _, per_fit, _ = _plan_fits(tree, vertices, probe, radii[-1], fit, np.random.default_rng(0))
    probe = np.sort(probe[: min(int(n_probe), max(PILOT_MIN_SAMPLES, int(PILOT_PAIR_BUDGET // per_fit)))])
    ks: list[np.ndarray] = []
    change: list[float] = []
    for j, radius in enumerate(radii):  # a handful of rungs, each fit vectorised over the probes
        kind, _, chunk = _plan_fits(tree, vertices, probe, radius, fit, np.random.default_rng(0))
        out, _, _ = _fit_samples(vertices, normals, tree, probe, radius, kind, chunk)
        ks.append(np.stack([out["k1"], out["k2"]], axis=1))
        if j:
            change += _ladder_change(ks[-2:], radii[j - 1:j + 1], quantile)
        if _climb_settled(change):
            break
    return ks, change, len(probe)


def _climb_settled(change: list[float]) -> bool:
    """Whether the ladder is past its stablest pair: the change has grown for the last two pairs
    and to :data:`CLIMB_STOP_GROWTH` × its smallest (the shape's change, not a rough wall's)."""
    finite = [c for c in change if math.isfinite(c)]
    return len(finite) >= 3 and min(finite) < finite[-2] < finite[-1] and finite[-1] >= CLIMB_STOP_GROWTH * min(finite)


def _largest_component_area(mesh: trimesh.Trimesh) -> float:
    """Area of the mesh's largest connected piece (:func:`nemo.surface.face_components`)."""
    from nemo.surface import face_components

    labels = face_components(mesh.faces, len(mesh.vertices))
    return float(np.bincount(labels, weights=mesh.area_faces).max())


def _quantile_radius_of_curvature(k: np.ndarray, quantile: float) -> float:
    """The ``quantile`` of 1/|k|max over fits (k1, k2), shape (P, 2); inf when none is curved."""
    kmax = np.fmax(np.abs(k[:, 0]), np.abs(k[:, 1]))
    kmax = kmax[np.isfinite(kmax)]
    kq = float(np.quantile(kmax, 1.0 - quantile)) if len(kmax) else 0.0
    return 1.0 / kq if kq > 0 else math.inf


def _ladder_change(ks: list[np.ndarray], radii: list[float], quantile: float) -> list[float]:
    """Per pair of rungs, the ``1 − quantile`` quantile over the probes of |Δ(k1, k2)|, per √2."""
    change = []
    for j in range(len(radii) - 1):
        d = np.linalg.norm(ks[j + 1] - ks[j], axis=1)
        d = d[np.isfinite(d)]
        per_step = math.log(math.sqrt(2.0)) / math.log(radii[j + 1] / radii[j])
        change.append(float(np.quantile(d, 1.0 - quantile)) * per_step if len(d) else math.nan)
    return change


def _stablest(radii: list[float], change: list[float], top_by: str, bottom_by: str) -> tuple[float, int, str]:
    """The radius from the ladder: (radius, index of the rung at or below it, limited_by)."""
    finite = [j for j, c in enumerate(change) if math.isfinite(c)]
    if not finite:  # one rung, or no probe fitted at two
        return radii[0], 0, bottom_by
    j = min(finite, key=lambda i: change[i])
    if j == len(change) - 1:  # still falling at the top
        return radii[-1], len(radii) - 1, top_by
    return math.sqrt(radii[j] * radii[j + 1]), j, "stability"


def curvature(
    mesh: trimesh.Trimesh,
    radius: float,
    n_samples: int | None = None,
    fraction: float | None = None,
    k_interp: int = 8,
    rng: np.random.Generator | int | None = None,
    fit: FitKind = "auto",
    smooth: float = DEFAULT_SMOOTH,
    warn_large: Literal["radius", "mesh"] | None = "radius",
    local_fraction: float = DEFAULT_LOCAL_FRACTION,
    adaptive: bool = True,
) -> pd.DataFrame:
    """Mean and Gaussian curvature at every vertex from local quadric fits.

    At each sampled vertex V0 (normal N0, tangent basis t1, t2) the neighbours within
    ``radius`` on the same side of the surface (N·N0 > 0) give ξ = (V−V0)·t1, η = (V−V0)·t2,
    z = (V−V0)·N0, and a least-squares fit of z(ξ, η) (see the module docstring for ``fit``)
    gives the curvature tensor C (C = [[−2a, −c], [−c, −2b]] for the paper's fit),
    H = tr(g⁻¹C)/2, K = det C / det g. The least squares of all samples are solved at once:
    per-sample moments Σ ξ^p η^q (z) summed with ``np.add.reduceat``, then one batched solve.
    The samples' values are then interpolated to every vertex by inverse-distance weights over
    the ``k_interp`` nearest samples whose normal agrees (paper eq. mesh-interpolation); a
    sampled vertex keeps its own value. Last, H and K are averaged over the surface by a
    diffusion of width σ = ``smooth × radius``, debiased (2 G_σ − G_√2σ,
    :func:`smooth_on_surface`): neighbouring fits' noise averages out, while the σ² bias of
    a plain average at a peak of curvature cancels.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        Surface with outward normals, vertices in physical units.
    radius : float
        Fitting radius in the mesh's unit (µm). A few mesh edge lengths at least, and well
        below the smallest radius of curvature of interest.
    n_samples : int, optional
        Number of randomly sampled vertices where the fit is done. Default: every vertex of
        small meshes, else about eight per fitting disc (:func:`default_n_samples`).
    fraction : float, optional
        Alternatively, the fraction of vertices to sample, in (0, 1].
    k_interp : int
        Number of nearest samples used for the inverse-distance interpolation.
    rng : numpy.random.Generator or int, optional
        Randomness of the sample (seed for reproducibility).
    fit : {"auto", "quadric", "quadratic", "quartic"}
        Fitted surface (module docstring): ``"quadric"`` is the paper's z ≈ aξ² + bη² + cξη,
        ``"quadratic"`` adds linear and constant terms, ``"quartic"`` all terms to 4th order;
        ``"auto"`` (default) picks quartic when the median sample has ≥ 60 neighbours.
        The fit used is in ``df.attrs["fit"]``.
    smooth : float
        Width (σ) of the averaging of H and K over the surface after the fits, as a fraction of
        ``radius`` (default :data:`DEFAULT_SMOOTH`; at most twice the object's radius
        sqrt(area / 4π), where the kernel is already uniform); 0 keeps the fitted and interpolated values
        (the paper). Principal curvatures then follow from the averaged H and K.
        ``df.attrs`` records the fits' scatter about the average (``fit_scatter_H``, 1/unit,
        ``fit_scatter_K``, 1/unit²: their noise; None without averaging).
    warn_large : {"radius", "mesh"} or None
        Warn when ``radius`` looks large for the surface (radius × median |k| above a limit),
        advising a smaller radius (``"radius"``: a radius the user chose) or a finer mesh
        (``"mesh"``: the smallest radius :func:`default_radius` allows, a few edges, is already
        that large). None: no such warning (a radius :func:`default_radius` chose above its
        floor already weighs the wall's roughness against the shape's change).
    local_fraction : float
        A vertex whose radius of curvature 1/|k|max (from the fits at ``radius``) is below
        ``radius / local_fraction`` is refitted at the largest radius ``radius`` × 2^(−k/4) under
        ``local_fraction`` / |k|max, down to :data:`RIM_MIN_EDGES` mean edges and
        :data:`RIM_MIN_FRACTION` × ``radius`` (its
        ``fit_radius``; default :data:`DEFAULT_LOCAL_FRACTION`); 0 = ``radius`` everywhere.
        ``df.attrs["local_fits"]`` counts those vertices.
    adaptive : bool
        Average each vertex's H and K at the widest of ``smooth × radius × 2^(j/2)``
        (:data:`ADAPT_STEPS`) whose value agrees with the narrower ones within their noise
        (:func:`_agreeing_width`; default); False: at ``smooth × radius`` everywhere.

    Returns
    -------
    pandas.DataFrame
        One row per vertex: ``vertex``, ``H`` (1/unit), ``K`` (1/unit²), ``k1 ≥ k2``, the
        principal directions ``d1x, d1y, d1z`` (of k1) and ``d2x, d2y, d2z`` (unit tangent
        vectors taken from the nearest sample, projected onto the vertex's tangent plane),
        ``sampled`` (True where the fit was done at that vertex) and ``fit_radius`` (the radius
        of the fit that vertex's values come from). NaN where the fit had fewer than
        :data:`MIN_NEIGHBOURS` neighbours (with a :class:`NemoWarning`). On an open surface (cut
        by the image border) a fit of ``radius`` within ``radius`` of the rim would see the
        surface on one side only (a biased value): no sample is drawn there, and each such
        vertex is fitted at the largest radius ``radius`` × 2^(−k/4) whose ball stays off the
        rim (its ``fit_radius``; a noisier value), down to :data:`RIM_MIN_EDGES` mean edge
        lengths and :data:`RIM_MIN_FRACTION` × ``radius``; closer vertices are NaN. Band
        values far outside the interior's range are clipped (a fit near a mesh defect).
        ``df.attrs["rim_band"]`` counts the vertices within ``radius`` of the rim,
        ``df.attrs["rim_vertices"]`` those left NaN, ``df.attrs["rim_fits"]`` the band's fits per
        fitted surface (a quartic's smaller rungs fit the quadratic).

    Raises
    ------
    NemoError
        Radius not positive, both ``n_samples`` and ``fraction``, out-of-range values.
    """
    check_mesh(mesh)
    radius, k_interp = _check_curvature_args(radius, n_samples, fraction, fit, k_interp)
    smooth = float(smooth)
    if not (math.isfinite(smooth) and 0 <= smooth <= MAX_SMOOTH):
        raise NemoError(f"curvature smoothing must be a fraction of the radius in [0, {MAX_SMOOTH:g}] "
                        f"(0 = none, default {DEFAULT_SMOOTH}), got {smooth}")
    local_fraction = float(local_fraction)
    if not (math.isfinite(local_fraction) and 0 <= local_fraction <= 2):
        raise NemoError(f"curvature local_fraction (of the local radius of curvature) must be in [0, 2] "
                        f"(0 = one radius everywhere, default {DEFAULT_LOCAL_FRACTION}), got {local_fraction}")
    rng = _as_rng(rng)
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    n_vert = len(vertices)
    n = _sample_count(mesh, n_vert, radius, n_samples, fraction)
    normals = vertex_normals(mesh)
    d_rim = rim(mesh.faces, n_vert, vertices)["distance"]
    near_rim = d_rim <= radius
    samples = _draw_samples(np.where(near_rim[:, None] & ~near_rim.all(), np.nan, normals), n, rng)
    n = len(samples)

    tree = cKDTree(vertices)
    fit, per_sample, chunk = _plan_fits(tree, vertices, samples, radius, fit, rng)
    unit = pretty_unit(_unit_name(mesh))
    with step(f"curvature: {fit} fits at {n} of {n_vert} vertices (radius {radius:g} {unit}, "
              f"~{per_sample:.0f} neighbours each)"):
        out, d1, d2 = _fit_samples(vertices, normals, tree, samples, radius, fit, chunk)
    _warn_fit_problems(mesh, out, radius, vertices, unit, fit, warn_large)

    with step(f"curvature: interpolating {n} samples to {n_vert} vertices (k = {k_interp})"):
        H, K, idx = _idw(vertices, normals, samples, np.stack([out["H"], out["K"]], axis=1), k_interp)
    smallest = max(RIM_MIN_EDGES * mean_edge_length(mesh), RIM_MIN_FRACTION * radius)
    limit = _band_limits(H, K, d_rim, near_rim, radius, smallest, local_fraction)
    band = _rim_band_fits(vertices, normals, tree, limit, near_rim, radius, fit, per_sample, smallest, unit,
                          k_interp, rng, float(mesh.area) / n_vert)
    H, K = _clip_to_interior(np.stack([H, K], axis=1), np.stack([band["H"], band["K"]], axis=1), near_rim)
    scatter = np.full(2, np.nan)
    if smooth > 0:
        widest = 2.0 ** (max(ADAPT_STEPS) / 2.0) if adaptive else 1.0  # the widest width within the cap
        sigma = _capped_width(mesh, smooth * radius * widest) / widest
        walk = _surface_walk(mesh, normals)
        with step(f"curvature: averaging H and K over the surface (σ = {sigma:.3g} {unit}"
                  f"{', adaptive' if adaptive else ''})"):
            HK, scatter = _robust_average(walk, np.stack([H, K], axis=1), sigma, near_rim, adaptive)
        H, K = HK[:, 0], HK[:, 1]
    df = _curvature_table(H, K, idx, out, d1, d2, samples, normals, keep_fitted=not smooth)
    _apply_rim_band(df, band, near_rim, radius, keep_fitted=not smooth)
    df.attrs.update(local_fraction=local_fraction, adaptive=bool(adaptive),
                    local_fits=int((~near_rim & np.isfinite(band["H"])).sum()))
    df.attrs.update(fit=fit, radius=radius, n_samples=int(n), k_interp=int(k_interp),
                    rim_vertices=int(df["H"][near_rim].isna().sum()), rim_band=int(near_rim.sum()),
                    rim_fits=dict(band["kinds"]),
                    smooth=float(smooth),
                    fit_scatter_H=_finite_or_none(scatter[0]), fit_scatter_K=_finite_or_none(scatter[1]))
    return df


def _band_limits(H: np.ndarray, K: np.ndarray, d_rim: np.ndarray, near_rim: np.ndarray, radius: float,
                 smallest: float, local_fraction: float) -> np.ndarray:
    """The largest fitting radius per vertex (N,) for :func:`_rim_band_fits`: ``radius`` off the band,
    the distance to the rim near it (NaN below ``smallest``: no fit), at most ``local_fraction`` /
    |k|max where H, K say so, not below ``smallest`` (on a noisy wall the radius grew with the
    noise, and much smaller fits are noise; a noisy |k|max would call for them)."""
    limit = np.where(near_rim, np.where(d_rim >= smallest, d_rim, np.nan), radius)
    if local_fraction > 0:
        k_max = np.abs(H) + np.sqrt(np.maximum(H * H - K, 0.0))
        with np.errstate(divide="ignore", invalid="ignore"):
            curved = np.maximum(local_fraction / k_max, smallest)
        limit = np.where(curved < radius, np.minimum(limit, curved), limit)  # NaN (no rim fit) stays NaN
    return limit


def _finite_or_none(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def _robust_average(walk: tuple[csr_matrix, float], values: np.ndarray, sigma: float,
                    noisier: np.ndarray | None = None, adaptive: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The debiased average of :func:`smooth_on_surface` (N, C), robust to outlying fits.

    A first pass gives the residual of each value; values beyond :data:`OUTLIER_CLIP` robust
    standard deviations (1.4826 × the median |residual|, per column) are clipped there, and a
    second pass averages the clipped values. A few wild fits on a rough wall (K of −100 / R²)
    would otherwise spread over the kernel's width. ``adaptive``: the second pass at the widths
    σ × 2^(j/2) of :data:`ADAPT_STEPS`, each value the widest that agrees with the narrower
    ones (:func:`_agreeing_width`).

    Returns
    -------
    averaged : ndarray, shape (N, C)
    scatter : ndarray, shape (C,)
        The robust standard deviation of the values about the first pass (without the rows
        ``noisier``, e.g. the rim band's smaller fits, when others are left): the fits' noise
        (on the validation's ellipsoid, H: 0.7 % of |H| noise-free, 2.9 % at SNR 10, 4.0 % at
        SNR 5, where the fits alone err by 0.4, 2.4 and 3.6 %).
    """
    first = _diffuse(walk, values, sigma, debias=True)[0]
    residual = np.abs(values - first)
    if not np.isfinite(residual).any():
        return first, np.full(values.shape[1], np.nan)
    typical = slice(None) if noisier is None or noisier.all() else ~noisier  # rows whose spread is the fits' noise
    scatter = 1.4826 * np.nanmedian(residual[typical], axis=0)
    bound = OUTLIER_CLIP * scatter
    clipped = np.clip(values, first - bound, first + bound)
    if not adaptive:
        return _diffuse(walk, clipped, sigma, debias=True)[0], scatter
    noise = clipped - first
    noise -= np.nanmedian(noise[typical], axis=0)
    widths = [sigma * 2.0 ** (j / 2.0) for j in ADAPT_STEPS]
    both = _diffuse_widths(walk, np.concatenate([clipped, noise], axis=1), widths)
    c = values.shape[1]
    spread = np.stack([1.4826 * np.nanmedian(np.abs(a[:, c:] - np.nanmedian(a[:, c:], axis=0)), axis=0) for a in both])
    return _agreeing_width(np.stack([a[:, :c] for a in both]), spread)[0], scatter


def _diffuse_widths(walk: tuple[csr_matrix, float], values: np.ndarray, sigmas: list[float]) -> list[np.ndarray]:
    """Debiased averages 2 G_σ f − G_√2σ f (N, C) for each σ of ``sigmas``, ascending by √2 each.

    Each width's G_√2σ is the next one's G_σ, so the kernels are τ_0 × 2^k, computed together
    (:func:`_kernel_averages`: one series, or a chain when the widest is long).
    """
    if walk[1] == 0.0:
        return [values.copy() for _ in sigmas]
    taus = [s**2 / (0.5 * walk[1]) for s in sigmas] + [sigmas[-1] ** 2 / (0.25 * walk[1])]
    ratios = _kernel_averages(walk, values, tuple(taus), 2.0 * SERIES_MAX_STEPS)[0]
    usable = np.isfinite(values)
    return [np.where(usable, 2.0 * a - b, np.nan) for a, b in zip(ratios[:-1], ratios[1:])]


def _agreeing_width(averages: np.ndarray, noise: np.ndarray,
                    agreement: float = ADAPT_AGREEMENT) -> tuple[np.ndarray, np.ndarray]:
    """Per value, the widest average whose interval ± ``agreement`` × noise meets every narrower one's.

    Parameters
    ----------
    averages : ndarray, shape (L, N, C)
        Averages at L widths, narrow to wide.
    noise : ndarray, shape (L, C)
        Standard deviation of each width's average (its smoothed noise).

    Returns
    -------
    chosen : ndarray, shape (N, C)
    level : ndarray of int, shape (N, C)
        Index of the width chosen.
    """
    low = np.maximum.accumulate(averages - agreement * noise[:, None, :], axis=0)
    high = np.minimum.accumulate(averages + agreement * noise[:, None, :], axis=0)
    level = np.maximum(np.logical_and.accumulate(low <= high, axis=0).sum(axis=0) - 1, 0)
    return np.take_along_axis(averages, level[None], axis=0)[0], level


#: Columns of the curvature table set to NaN where the fit's neighbourhood reaches an open rim.
_RIM_NAN = ("H", "K", "k1", "k2", "d1x", "d1y", "d1z", "d2x", "d2y", "d2z")


def _rim_band_fits(vertices: np.ndarray, normals: np.ndarray, tree: cKDTree, limit: np.ndarray,
                   near_rim: np.ndarray, radius: float, fit: str, per_sample: float, min_radius: float,
                   unit: str, k_interp: int, rng: np.random.Generator, vertex_area: float) -> dict:
    """Fits for the vertices whose ball of ``radius`` holds a vertex of the open rim, and for
    the vertices more curved than that radius allows (:func:`_band_limits`).

    Each is assigned the largest radius of the ladder ``radius`` × 2^(−k/4) (ending at
    ``min_radius``) at or below its ``limit`` (NaN: no fit; off the
    band: ``radius`` or more): near the rim its distance to the rim (Euclidean), so the ball holds
    no rim vertex and a fit sees the surface on every side (smaller and noisier than the
    interior's, not one-sided and biased); on a curved stretch a fraction of its radius of
    curvature. :data:`RIM_SAMPLES_PER_DISC` vertices per fitting disc of each
    rung are fitted (a rung whose balls hold fewer than :data:`AUTO_QUARTIC_NEIGHBOURS`
    neighbours fits the quadratic instead of the quartic) and interpolated to the band's other
    vertices (:func:`_idw` from the band's samples only). Vertices closer to the rim than
    ``min_radius`` keep NaN, and so do degenerate fits (warned). One batch of fits per rung.
    The rungs' sample count is independent of the interior's ``n_samples`` / ``fraction``:
    the band's fits are smaller and each needs its own density.

    Returns
    -------
    dict
        ``H``, ``K``, ``fit_radius`` (N,), ``d1``, ``d2`` (N, 3) (the nearest band sample's
        directions): NaN off the band and where no rung fits; ``samples`` (the fitted band
        vertices) with their fitted ``k1``, ``k2``; ``kinds``: the number of fits per fitted
        surface (``{"quartic": n, "quadratic": m}``).
    """
    n = len(vertices)
    band = {k: np.full(n, np.nan) for k in ("H", "K", "fit_radius")}
    band["d1"], band["d2"] = np.full((n, 3), np.nan), np.full((n, 3), np.nan)
    band["samples"], band["k1"], band["k2"] = np.zeros(0, np.int64), np.zeros(0), np.zeros(0)
    band["kinds"] = {}
    rungs = radius * 2.0 ** (-np.arange(1, 64) / 4.0)
    rungs = np.r_[rungs[rungs > min_radius], min_radius]  # the last rung: the smallest radius itself
    finite = np.isfinite(limit) & (near_rim | (limit < radius))
    rung = np.searchsorted(-rungs, -np.where(finite, limit, 0.0), side="left")  # the first (largest) rung ≤ limit
    todo = finite & (rung < len(rungs)) & np.isfinite(normals[:, 0])
    fits = []
    for k in np.unique(rung[todo]):  # a loop over the ladder's rungs (at most ~20)
        members = np.flatnonzero(todo & (rung == k))
        r = float(rungs[k])
        count = per_sample * (r / radius) ** 2
        n_fit = min(len(members), max(8, math.ceil(RIM_SAMPLES_PER_DISC * len(members) * vertex_area / (math.pi * r * r))))
        where = np.sort(rng.choice(members, n_fit, replace=False))
        kind = "quadratic" if fit == "quartic" and count - 1 < AUTO_QUARTIC_NEIGHBOURS else fit
        out, d1, d2 = _fit_samples(vertices, normals, tree, where, r, kind, max(1, int(_PAIRS_PER_CHUNK // count)))
        fits.append({"where": where, "r": np.full(len(where), r), "d1": d1, "d2": d2, **out})
        band["kinds"][kind] = band["kinds"].get(kind, 0) + len(where)
    if fits:
        f = {key: np.concatenate([x[key] for x in fits]) for key in fits[0]}
        position = np.searchsorted(np.flatnonzero(todo), f["where"])  # the samples among the band's vertices
        H, K, idx = _idw(vertices[todo], normals[todo], position, np.stack([f["H"], f["K"]], axis=1), k_interp)
        nearest = idx[:, 0]
        band["H"][todo], band["K"][todo], band["fit_radius"][todo] = H, K, f["r"][nearest]
        band["d1"][todo] = project_tangent(f["d1"][nearest], normals[todo])
        band["d2"][todo] = np.cross(normals[todo], band["d1"][todo])
        band["d1"][f["where"]], band["d2"][f["where"]] = f["d1"], f["d2"]
        band["samples"], band["k1"], band["k2"] = f["where"], f["k1"], f["k2"]
    if near_rim.any():
        logger.info("curvature: %d of %d vertices lie within the radius %g of the open rim: %d fitted at radii "
                    "%.3g-%.3g %s (%d fits), %d NaN", int(near_rim.sum()), n, radius, int((todo & near_rim).sum()),
                    min(min_radius, radius), radius, unit, len(band["samples"]), int((near_rim & ~np.isfinite(band["H"])).sum()))
    failed = int(np.count_nonzero(~np.isfinite(band["k1"])))
    if failed:
        warnings.warn(f"curvature: {failed} of {len(band['samples'])} fits near the open rim were degenerate "
                      "(too few or nearly collinear neighbours in their smaller balls); those vertices' H and K "
                      "are NaN", NemoWarning, stacklevel=3)
    if near_rim.all() and not np.isfinite(band["H"]).any():
        warnings.warn(
            f"curvature: every vertex lies within the fitting radius {radius:g} of the surface's open rim, and "
            f"within {min_radius:.3g} (the smallest fit near it): every H and K is NaN; use a smaller radius",
            NemoWarning, stacklevel=3)
    return band


def _clip_to_interior(interior: np.ndarray, band: np.ndarray, near_rim: np.ndarray) -> tuple[np.ndarray, ...]:
    """H and K (N,): the interior's values off the band, the band's on it (a curved vertex whose
    smaller fit failed keeps the interior's), the rim band's clipped to the interior's 1st-99th
    percentile range widened by that range on each side.

    A small fit near a mesh defect at the rim can read H of −600 / R; the robust average's first
    pass is not robust to it and would carry it up to two radii into the interior.
    """
    values = np.where(near_rim[:, None] | np.isfinite(band), band, interior)
    inside = interior[~near_rim]
    if near_rim.any() and np.isfinite(inside).any():
        lo, hi = np.nanpercentile(inside, [1, 99], axis=0)
        values[near_rim] = np.clip(values[near_rim], lo - (hi - lo), hi + (hi - lo))
    return values[:, 0], values[:, 1]


def _apply_rim_band(df: pd.DataFrame, band: dict, near_rim: np.ndarray, radius: float, keep_fitted: bool) -> None:
    """Put the rim band's fits (:func:`_rim_band_fits`) into the curvature table (in place).

    Its vertices take the directions of their nearest band sample (the samples their own, and
    their fitted principal values unless averaged; ``sampled`` marks the band's samples there);
    ``fit_radius`` is ``radius`` off the band; a rim band vertex without a fit is NaN.
    """
    fitted = np.isfinite(band["H"])
    for axis, c in enumerate("xyz"):
        df.loc[fitted, f"d1{c}"] = band["d1"][fitted, axis]
        df.loc[fitted, f"d2{c}"] = band["d2"][fitted, axis]
    if keep_fitted:  # principal values of the band's H, K (an interior sample refitted smaller: not its first fit's)
        H, K = df["H"].to_numpy()[fitted], df["K"].to_numpy()[fitted]
        disc = np.sqrt(np.maximum(H * H - K, 0.0))
        df.loc[fitted, "k1"], df.loc[fitted, "k2"] = H + disc, H - disc
        if len(band["samples"]):
            df.loc[band["samples"], "k1"], df.loc[band["samples"], "k2"] = band["k1"], band["k2"]
    df.loc[fitted, "sampled"] = False
    df.loc[band["samples"], "sampled"] = True
    df.loc[near_rim & ~fitted, list(_RIM_NAN)] = np.nan
    df["fit_radius"] = np.where(near_rim | fitted, band["fit_radius"], radius)


def _check_curvature_args(radius: float, n_samples: int | None, fraction: float | None, fit: str,
                          k_interp: int) -> tuple[float, int]:
    """The radius and ``k_interp`` as numbers, refused when out of range or contradictory."""
    radius = float(radius)
    if not (math.isfinite(radius) and radius > 0):
        raise NemoError(f"curvature radius must be a positive length in µm, got {radius}")
    if n_samples is not None and fraction is not None:
        raise NemoError("give either the number of samples or the fraction of vertices, not both")
    if fit not in ("auto", "quadric", "quadratic", "quartic"):
        raise NemoError(f"unknown curvature fit {fit!r}: use auto, quadric, quadratic or quartic")
    k_interp = int(k_interp)
    if k_interp < 1:
        raise NemoError(f"k_interp must be at least 1, got {k_interp}")
    return radius, k_interp


def _sample_count(mesh: trimesh.Trimesh, n_vert: int, radius: float, n_samples: int | None,
                  fraction: float | None) -> int:
    """Number of sampled vertices: from ``fraction``, ``n_samples`` or :func:`default_n_samples`."""
    if fraction is not None:
        if not (0 < fraction <= 1):
            raise NemoError(f"sample fraction must be in (0, 1], got {fraction}")
        return max(1, int(round(fraction * n_vert)))
    if n_samples is not None:
        if int(n_samples) < 1:
            raise NemoError(f"number of samples must be at least 1, got {n_samples}")
        return min(int(n_samples), n_vert)
    return default_n_samples(n_vert, float(mesh.area), radius)


def _draw_samples(normals: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """Sorted sample vertices: ``n`` drawn among those with a usable normal (all of them if fewer)."""
    usable = np.flatnonzero(np.isfinite(normals[:, 0]))
    if len(usable) == 0:
        raise NemoError("no vertex of the mesh has a usable normal (all faces have zero area); repair the mesh")
    n = min(n, len(usable))
    return np.sort(usable if n == len(usable) else rng.choice(usable, n, replace=False))


def _plan_fits(tree: cKDTree, vertices: np.ndarray, samples: np.ndarray, radius: float, fit: str,
               rng: np.random.Generator) -> tuple[str, float, int]:
    """The fit (``"auto"`` resolved), mean neighbours per sample and the samples per chunk.

    Both come from the neighbour counts of up to 256 probe samples; the chunks keep the
    (sample, neighbour) pairs within memory bounds.
    """
    probe = samples[rng.choice(len(samples), min(len(samples), 256), replace=False)]
    probe_counts = tree.query_ball_point(vertices[probe], radius, return_length=True)
    per_sample = max(1.0, float(np.mean(probe_counts)))
    chunk = max(1, int(_PAIRS_PER_CHUNK // per_sample))
    if fit == "auto":
        fit = "quartic" if np.median(probe_counts) - 1 >= AUTO_QUARTIC_NEIGHBOURS else "quadratic"
    return fit, per_sample, chunk


def _fit_samples(vertices: np.ndarray, normals: np.ndarray, tree: cKDTree, samples: np.ndarray,
                 radius: float, fit: str, chunk: int) -> tuple[dict, np.ndarray, np.ndarray]:
    """Fits at every sample, ``chunk`` samples at a time (:func:`_fit_chunk`).

    Returns
    -------
    out : dict of ndarray, shape (S,)
        ``H``, ``K``, ``k1``, ``k2`` and the neighbour ``count`` of each sample.
    d1, d2 : ndarray, shape (S, 3)
        Principal directions.
    """
    n = len(samples)
    out = {k: np.empty(n) for k in ("H", "K", "k1", "k2", "count")}
    d1 = np.empty((n, 3))
    d2 = np.empty((n, 3))
    for s in range(0, n, chunk):
        sl = slice(s, s + chunk)
        H, K, k1, k2, a1, a2, cnt = _fit_chunk(vertices, normals, tree, samples[sl], radius, fit)
        out["H"][sl], out["K"][sl], out["k1"][sl], out["k2"][sl], out["count"][sl] = H, K, k1, k2, cnt
        d1[sl], d2[sl] = a1, a2
    return out, d1, d2


def _warn_fit_problems(mesh: trimesh.Trimesh, out: dict, radius: float, vertices: np.ndarray, unit: str,
                       fit: str, warn_large: str | None = "radius") -> None:
    """Warn (at the caller of :func:`curvature`) about too few neighbours, a radius too large
    for the surface, and degenerate fits."""
    few = out["count"] < MIN_NEIGHBOURS
    n = len(out["count"])
    diagonal = float(np.linalg.norm(np.ptp(vertices, axis=0)))
    if few.any() and radius >= diagonal:  # no radius helps: too few vertices on a side of the surface
        warnings.warn(
            f"the surface is too coarse for a curvature fit at {int(few.sum())} of {n} sampled vertices: fewer "
            f"than {MIN_NEIGHBOURS} vertices on their side of it even within {radius:g} {unit} (its whole extent, "
            f"{len(vertices)} vertices); their H and K are NaN. Use a finer mesh (subdivide it)",
            NemoWarning, stacklevel=3)
        return
    if few.any():
        edge = mean_edge_length(mesh)
        warnings.warn(
            f"curvature radius {radius:g} {unit} is too small for {int(few.sum())} of {n} sampled "
            f"vertices (fewer than {MIN_NEIGHBOURS} neighbours within it): their H and K are NaN; "
            f"use a larger radius (the mean edge length is {edge:.3g} {unit}, try at least "
            f"{3 * edge:.2g} {unit})",
            NemoWarning,
            stacklevel=3,
        )
    if warn_large:
        _warn_large_radius(radius, out["k1"], out["k2"], vertices, unit,
                           LARGE_RADIUS_RK * (2.0 if fit == "quartic" else 1.0), warn_large)
    bad_fit = ~few & ~np.isfinite(out["H"])
    if bad_fit.any():
        warnings.warn(
            f"curvature: the fit was degenerate (neighbours nearly collinear) at {int(bad_fit.sum())} "
            f"sampled vertices; their H and K are NaN",
            NemoWarning,
            stacklevel=3,
        )


def _curvature_table(H: np.ndarray, K: np.ndarray, idx: np.ndarray, out: dict, d1: np.ndarray,
                     d2: np.ndarray, samples: np.ndarray, normals: np.ndarray,
                     keep_fitted: bool = True) -> pd.DataFrame:
    """The curvature table: interpolated H, K and principal values/directions at every vertex.

    A vertex takes the direction of its nearest sample projected onto its tangent plane;
    sampled vertices keep their own fitted directions, and their fitted principal values
    when ``keep_fitted`` (else those of H and K, averaged over the surface).
    """
    n_vert = len(normals)
    disc = np.sqrt(np.maximum(H * H - K, 0.0))
    k1, k2 = H + disc, H - disc
    # direction from the nearest sample, projected onto the vertex's tangent plane
    dir1 = d1[idx[:, 0]]
    dir1 = project_tangent(dir1, normals)
    dir2 = np.cross(normals, dir1)
    # sampled vertices keep their own fitted directions (and principal values, unless averaged)
    if keep_fitted:
        k1[samples], k2[samples] = out["k1"], out["k2"]
    dir1[samples], dir2[samples] = d1, d2
    sampled = np.zeros(n_vert, dtype=bool)
    sampled[samples] = True
    return pd.DataFrame(
        {
            "vertex": np.arange(n_vert, dtype=np.int64),
            "H": H,
            "K": K,
            "k1": k1,
            "k2": k2,
            "d1x": dir1[:, 0], "d1y": dir1[:, 1], "d1z": dir1[:, 2],
            "d2x": dir2[:, 0], "d2y": dir2[:, 1], "d2z": dir2[:, 2],
            "sampled": sampled,
        }
    )


def _warn_large_radius(
    radius: float, k1: np.ndarray, k2: np.ndarray, vertices: np.ndarray, unit: str, limit: float,
    advice: str = "radius",
) -> None:
    """Warn when the fitting radius is large for the surface: the fits then average over
    regions of changing curvature and bias H and K (towards 0 on a closed surface). ``advice``:
    ``"radius"`` names a smaller radius, ``"mesh"`` a finer mesh (the radius is at its floor)."""
    kmax = np.fmax(np.abs(k1), np.abs(k2))
    rk = float(radius * np.nanmedian(kmax)) if np.isfinite(kmax).any() else 0.0
    diag = float(np.linalg.norm(np.ptp(vertices, axis=0)))
    if rk > limit or radius > 0.25 * diag:
        kmed = float(np.nanmedian(kmax)) if np.isfinite(kmax).any() else 0.0
        better = 0.25 * diag if kmed == 0 else min(0.25 * diag, 0.5 * limit / kmed)
        fix = (f"use a radius of about {better:.2g} {unit} or less" if advice == "radius" else
               "this is the default's smallest radius (a few mesh edges): the mesh is coarse for this surface; "
               "a finer one (mesh.step 1, finer voxels) fits it better")
        warnings.warn(
            f"curvature radius {radius:g} {unit} is large for this surface (radius × median |k1| = "
            f"{rk:.2g}, bounding-box diagonal {diag:.4g} {unit}): the fits span regions of changing "
            f"curvature and H, K are biased; {fix}",
            NemoWarning,
            stacklevel=4,  # curvature -> _warn_fit_problems -> here
        )


def _idw(
    vertices: np.ndarray,
    normals: np.ndarray,
    samples: np.ndarray,
    values: np.ndarray,
    k: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inverse-distance weighted interpolation of sample values to every vertex.

    Samples whose normal points away from the vertex's (other side of a thin structure) and
    samples with NaN values get zero weight; no usable sample among the k nearest -> NaN.
    A vertex that is itself a sample keeps its own value (even NaN).

    Returns
    -------
    H, K : ndarray, shape (N,)
        Interpolated columns 0 and 1 of ``values``.
    idx : ndarray, shape (N, k)
        Indices (into ``samples``) of the k nearest samples, nearest first.
    """
    k = min(k, len(samples))
    dist, idx = cKDTree(vertices[samples]).query(vertices, k=k)
    if k == 1:
        dist, idx = dist[:, None], idx[:, None]
    nrm = np.nan_to_num(normals).astype(np.float32)
    usable = np.isfinite(values).all(axis=1)[idx]  # (N, k)
    usable &= np.einsum("ij,ikj->ik", nrm, nrm[samples][idx]) > 0  # same side of the surface
    with np.errstate(divide="ignore"):
        w = np.where(usable, 1.0 / dist, 0.0)
    wsum = w.sum(axis=1)
    res = np.empty((len(vertices), values.shape[1]))
    vals0 = np.nan_to_num(values)
    with np.errstate(invalid="ignore", divide="ignore"):
        for col in range(values.shape[1]):
            res[:, col] = np.einsum("nk,nk->n", w, vals0[idx, col]) / wsum
    res[wsum == 0] = np.nan
    exact = dist[:, 0] == 0  # the vertex is a sample (or coincides with one): its own value
    res[exact] = values[idx[exact, 0]]
    return res[:, 0], res[:, 1], idx


# --------------------------------------------------------------------------------------------
# thickness
# --------------------------------------------------------------------------------------------


def _ray_distance(
    target: trimesh.Trimesh,
    origins: np.ndarray,
    directions: np.ndarray,
    eps: float,
    back_off: bool,
) -> np.ndarray:
    """Distance t ≥ 0 along unit ``directions`` to the first face of ``target`` (NaN: miss).

    ``back_off``: start the rays ``eps`` behind the origin so that a surface through the origin
    (touching surfaces) is found at t = 0 rather than missed; otherwise start ``eps`` ahead
    (the target is the origin's own mesh and its own faces must be skipped).
    """
    start = origins - eps * directions if back_off else origins + eps * directions
    tri = np.asarray(target.ray.intersects_first(start, directions), dtype=np.int64)
    miss = np.flatnonzero(tri < 0)
    if len(miss):
        # rays through an edge or vertex can slip between triangles: retry once, nudged sideways
        t1, _ = axis_frames(directions[miss])
        retry = np.asarray(target.ray.intersects_first(start[miss] + 10 * eps * t1, directions[miss]), dtype=np.int64)
        tri[miss] = retry
    hit = tri >= 0
    t = np.full(len(origins), np.nan)
    if hit.any():
        # exact float64 distance to the hit face's plane (Embree works in float32); the plane
        # normal of the hit faces only (cheaper than trimesh's face_normals of every face)
        corners = np.asarray(target.vertices, dtype=np.float64)[np.asarray(target.faces)[tri[hit]]]
        p0 = corners[:, 0]
        fn = np.cross(corners[:, 1] - p0, corners[:, 2] - p0)
        with np.errstate(divide="ignore", invalid="ignore"):
            th = np.einsum("ij,ij->i", p0 - origins[hit], fn) / np.einsum("ij,ij->i", directions[hit], fn)
        th[~np.isfinite(th)] = np.nan
        t[hit] = np.maximum(th, 0.0)  # tiny negatives: the surface passes through the origin
    return t


def thickness(
    mesh_from: trimesh.Trimesh,
    mesh_to: trimesh.Trimesh,
    direction: Literal["outward", "inward", "nearest"] = "outward",
    max_distance: float | None = None,
) -> np.ndarray:
    """Distance from every vertex of ``mesh_from`` to ``mesh_to`` along the vertex normal.

    A ray is cast from each vertex V along +N (``"outward"``), −N (``"inward"``) or both
    (``"nearest"``: the closer hit of the two); the first intersection V* with ``mesh_to``
    gives the paper's d = (V* − V)·N (eq. inter-mesh-distance).

    Parameters
    ----------
    mesh_from : trimesh.Trimesh
        Surface whose vertices the distances belong to (outward normals).
    mesh_to : trimesh.Trimesh
        Surface the rays look for. It may be ``mesh_from`` itself (e.g. the wall thickness of a
        closed shell mesh): each ray then skips the faces at its own origin.
    direction : {"outward", "inward", "nearest"}
    max_distance : float, optional
        Hits farther than this (in the mesh unit) count as misses.

    Returns
    -------
    ndarray, shape (N,)
        Signed distance d in the mesh unit: ≥ 0 for outward hits, ≤ 0 for inward hits; NaN
        where no hit (within ``max_distance``) — never a made-up value.

    Raises
    ------
    NemoError
        Unknown direction, non-positive ``max_distance``, unusable meshes.
    """
    check_mesh(mesh_from, "mesh_from")
    check_mesh(mesh_to, "mesh_to")
    if direction not in ("outward", "inward", "nearest"):
        raise NemoError(f"unknown thickness direction {direction!r}: use outward, inward or nearest")
    if max_distance is not None and not (float(max_distance) > 0):
        raise NemoError(f"max_distance must be a positive length, got {max_distance}")
    u_from, u_to = _unit_name(mesh_from), _unit_name(mesh_to)
    if u_from != u_to:
        raise NemoError(f"the two meshes are in different units ({u_from} and {u_to}); convert one")
    check_same_object(mesh_from, mesh_to)
    vertices = np.asarray(mesh_from.vertices, dtype=np.float64)
    normals = vertex_normals(mesh_from)
    valid = np.isfinite(normals[:, 0])
    same = mesh_to is mesh_from or (
        mesh_to.vertices.shape == mesh_from.vertices.shape
        and mesh_to.faces.shape == mesh_from.faces.shape
        and np.array_equal(mesh_to.faces, mesh_from.faces)
        and np.array_equal(mesh_to.vertices, mesh_from.vertices)
    )
    both = np.vstack([np.asarray(m.vertices).min(0) for m in (mesh_from, mesh_to)]
                     + [np.asarray(m.vertices).max(0) for m in (mesh_from, mesh_to)])
    scale = float(np.linalg.norm(np.ptp(both, axis=0)))
    eps = 1e-5 * scale
    origins, dirs = vertices[valid], normals[valid]
    d = np.full(len(vertices), np.nan)
    engine = "Embree" if trimesh.ray.has_embree else "trimesh (slow: install embreex)"
    with step(f"thickness: casting {len(origins)} rays {direction} ({engine})"):
        if direction in ("outward", "nearest"):
            d_out = _ray_distance(mesh_to, origins, dirs, eps, back_off=not same)
        if direction in ("inward", "nearest"):
            d_in = -_ray_distance(mesh_to, origins, -dirs, eps, back_off=not same)
    if direction == "outward":
        res = d_out
    elif direction == "inward":
        res = d_in
    else:
        use_in = np.isnan(d_out) | (np.abs(d_in) < d_out)
        res = np.where(use_in, d_in, d_out)
    if max_distance is not None:
        res[np.abs(res) > float(max_distance)] = np.nan
    d[valid] = res
    _warn_misses(d, direction)
    return d


#: Largest size ratio of two surfaces of one object (walls of a shell, an organoid and its
#: lumen, layers of a tissue); a unit mix-up is a factor of about 1000.
MAX_SIZE_RATIO = 30.0


def check_same_object(mesh_a: trimesh.Trimesh, mesh_b: trimesh.Trimesh) -> None:
    """Refuse two surfaces that cannot be walls of one object: sizes far apart or no overlap.

    Catches a mesh exported in another unit (nm instead of µm: ×1000) or from another image.
    """
    lo_a, hi_a = np.asarray(mesh_a.vertices).min(0), np.asarray(mesh_a.vertices).max(0)
    lo_b, hi_b = np.asarray(mesh_b.vertices).min(0), np.asarray(mesh_b.vertices).max(0)
    size_a, size_b = float(np.linalg.norm(hi_a - lo_a)), float(np.linalg.norm(hi_b - lo_b))
    ratio = max(size_a, size_b) / max(min(size_a, size_b), 1e-300)
    if ratio > MAX_SIZE_RATIO:
        raise NemoError(
            f"the two meshes differ in size by × {ratio:.3g} (bounding-box diagonals {size_a:.4g} and "
            f"{size_b:.4g}): they cannot be two walls of one object. Is one of them in another unit "
            "(nm, mm) or from another image? Re-export both in the image's unit"
        )
    gap = float(np.linalg.norm(np.maximum(0.0, np.maximum(lo_a - hi_b, lo_b - hi_a))))
    if gap > max(size_a, size_b):  # two sheets of a slab may be apart, but not farther than they are large
        raise NemoError(
            f"the two meshes are {gap:.4g} apart, more than either is large ({size_a:.4g}, {size_b:.4g}): "
            "they are not walls of one object; pass two surfaces of the same frame, in the same unit"
        )


#: Fewest rim vertices of a surface on a face of the meshes' bounding box for that face to count as
#: where the image's border cut it (``mesh.border: open`` puts the rim exactly on the border plane;
#: a torn wall's hole may touch the box at a vertex or two).
CUT_MIN_RIM_VERTICES = 3


def beyond_view(mesh_from: trimesh.Trimesh, mesh_to: trimesh.Trimesh, missed: np.ndarray,
                direction: Literal["outward", "inward", "nearest"] = "outward") -> np.ndarray:
    """Which missed thickness rays left the field of view where the image's border cut the wall.

    A surface cut by the border (``mesh.border: open``) has its rim on the border's planes, the
    faces of the two meshes' bounding box. A ray that met nothing and leaves the box through such a
    face while still on its origin's side of ``mesh_to`` (within the wall: the side of the nearest
    vertex of ``mesh_to``, by its normal) would have met the other wall beyond the image: its NaN
    is the field of view's. A ray through a hole in ``mesh_to`` leaves the box on the far side of it,
    and one that leaves through a face without the rim is the wall's too. Without a cut, none is.

    Parameters
    ----------
    mesh_from, mesh_to : trimesh.Trimesh
        The surfaces of :func:`thickness`.
    missed : ndarray of bool, shape (N,)
        The rays to classify (e.g. the vertices of ``mesh_from`` with a NaN thickness).
    direction : {"outward", "inward", "nearest"}
        As in :func:`thickness` (``"nearest"``: both directions missed, so both must have left).

    Returns
    -------
    ndarray of bool, shape (N,)
        True where a ray in ``missed`` leaves the box through a cut face within the wall.
    """
    out = np.zeros(len(mesh_from.vertices), dtype=bool)
    missed = np.asarray(missed, dtype=bool)
    cut, lo, hi = _cut_faces(mesh_from, mesh_to)
    if not missed.any() or not cut.any():
        return out
    origins = np.asarray(mesh_from.vertices, dtype=np.float64)[missed]
    normals = vertex_normals(mesh_from)[missed]
    side = _sides(mesh_to)
    step = 1e-6 * float(np.linalg.norm(hi - lo))  # off the origin: a ray from a point of mesh_to starts on its side
    rows = np.arange(len(origins))
    left = np.ones(len(origins), dtype=bool)
    for sign in {"outward": (1.0,), "inward": (-1.0,), "nearest": (1.0, -1.0)}[direction]:
        dirs = sign * normals  # a NaN under "nearest" is two misses: both must have left the view
        with np.errstate(divide="ignore", invalid="ignore"):  # an axis the ray runs along: never left through
            t = np.where(dirs > 0, (hi - origins) / dirs, np.where(dirs < 0, (lo - origins) / dirs, np.inf))
        t = np.where(np.isfinite(t), t, np.inf)
        axis = np.argmin(t, axis=1)
        through = cut[axis, (dirs[rows, axis] > 0).astype(int)] & np.isfinite(t[rows, axis])
        if through.any():
            ends = origins[through] + t[rows, axis][through, None] * dirs[through]
            through[through] = side(ends) == side(origins[through] + step * dirs[through])
        left &= through
    out[np.flatnonzero(missed)] = left
    return out


def _sides(mesh: trimesh.Trimesh):
    """A function of points (P, 3): True on the side of ``mesh`` its normals point to, by the nearest
    vertex and its normal (the nearest triangle's search costs ~1 ms and ~1 MB per point on a fine
    mesh a wall's thickness away; the points tested here lie well off the surface)."""
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    tree, normals = cKDTree(verts), vertex_normals(mesh)

    def side(points: np.ndarray) -> np.ndarray:
        nearest = tree.query(points)[1]
        return np.einsum("ij,ij->i", points - verts[nearest], normals[nearest]) > 0.0

    return side


def _cut_faces(mesh_from: trimesh.Trimesh, mesh_to: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """((3, 2) bool: the bounding-box faces (x, y, z; low, high) holding at least
    :data:`CUT_MIN_RIM_VERTICES` of ``mesh_to``'s rim vertices, the box's low and high corners)."""
    both = np.vstack([np.asarray(mesh_from.vertices), np.asarray(mesh_to.vertices)])
    lo, hi = both.min(axis=0), both.max(axis=0)
    ends = rim(np.asarray(mesh_to.faces), len(mesh_to.vertices))["vertices"]
    on_rim = np.asarray(mesh_to.vertices, dtype=np.float64)[ends]
    tol = 1e-6 * max(float(np.linalg.norm(hi - lo)), 1e-300)
    cut = np.stack([(np.abs(on_rim - lo) <= tol).sum(axis=0), (np.abs(on_rim - hi) <= tol).sum(axis=0)], axis=1)
    return cut >= CUT_MIN_RIM_VERTICES, lo, hi


def _warn_misses(d: np.ndarray, direction: str) -> None:
    """Warn when most rays found no surface: a thickness of mostly NaN is no measurement."""
    missed = float(np.mean(np.isnan(d))) if len(d) else 1.0
    if missed > 0.5:
        warnings.warn(
            f"{100 * missed:.0f} % of the rays ({direction}) met no surface: check that `direction` "
            "points from `mesh_from` towards `mesh_to` and that `max_distance` is not too small",
            NemoWarning, stacklevel=3,
        )


# --------------------------------------------------------------------------------------------
# measure
# --------------------------------------------------------------------------------------------


def _merge_without_pinches(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Coincident vertices merged (:func:`nemo.mesh.merge_coincident_vertices`), except where the
    merge would pinch an open rim: (N', 3) vertices and the faces left.

    A merge that closes a crack pairs up its boundary edges. One that joins two rim vertices at
    the same place (where a split's cut plane runs through a vertex, :func:`nemo.surface.split_mesh`
    gives each of its face fans its own copy) leaves a vertex with four boundary edges, and its
    Euler characteristic is no longer the surface's (a disk read χ = −1). Those groups stay apart.
    """
    verts, f, index = merge_coincident_vertices(vertices, faces)
    group_size = np.bincount(index, minlength=len(verts))
    if not (group_size > 1).any():
        return verts, f
    edges = np.sort(np.stack([f, np.roll(f, -1, axis=1)], axis=2).reshape(-1, 2), axis=1)
    keys, count = np.unique(edges[:, 0] * len(verts) + edges[:, 1], return_counts=True)
    rim_ends = np.stack([keys[count == 1] // len(verts), keys[count == 1] % len(verts)], axis=1).ravel()
    pinched = (np.bincount(rim_ends, minlength=len(verts)) > 2) & (group_size > 1)
    if not pinched.any():
        return verts, f
    apart = np.flatnonzero(pinched[index])  # the old vertices of pinched groups: each its own vertex
    index = index.copy()
    index[apart] = len(verts) + np.arange(len(apart))
    f = index[faces]
    keep = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    return np.concatenate([verts, vertices[apart]]), f[keep]


def _topology(vertices: np.ndarray, faces: np.ndarray) -> dict:
    """Edge-based topology and angles of a triangle mesh, vectorised (no trimesh caches).

    Coincident vertices are merged first (marching cubes duplicates a vertex wherever the
    level equals a voxel value) and the faces that collapse are dropped, so that the angles,
    the Euler characteristic and the edge pairing are those of the surface
    (:func:`_merge_without_pinches`).
    """
    verts, f = _merge_without_pinches(vertices, faces)
    n_collapsed = len(faces) - len(f)
    nv, nf = len(verts), len(f)
    used = np.zeros(nv, dtype=bool)
    used[f.ravel()] = True

    # directed half-edges a -> b of every face corner, and their undirected keys
    a = f.ravel()
    b = np.roll(f, -1, axis=1).ravel()
    face_of = np.repeat(np.arange(nf), 3)
    key = np.minimum(a, b) * nv + np.maximum(a, b)
    srt = np.argsort(key, kind="stable")
    ks = key[srt]
    first = np.concatenate([[True], ks[1:] != ks[:-1]])
    edge_id = np.cumsum(first) - 1
    n_edges = int(edge_id[-1] + 1) if len(ks) else 0
    count = np.bincount(edge_id, minlength=n_edges)
    boundary_edges = ks[first][count == 1]
    directed = not np.any(np.diff(np.sort(a * nv + b)) == 0)  # consistent winding: no half-edge twice
    watertight = bool(np.all(count == 2) and directed)

    # components of the vertex graph (used vertices only) and boundary loops
    und = np.stack([ks[first] // nv, ks[first] % nv], axis=1)
    graph = coo_matrix((np.ones(len(und)), (und[:, 0], und[:, 1])), shape=(nv, nv))
    _, labels = connected_components(graph, directed=False)
    n_comp = int(np.count_nonzero(np.bincount(labels[used])))
    n_loops = 0
    bverts = np.zeros(nv, dtype=bool)
    if len(boundary_edges):
        be = np.stack([boundary_edges // nv, boundary_edges % nv], axis=1)
        bverts[be.ravel()] = True
        nodes, inv = np.unique(be, return_inverse=True)
        inv = inv.reshape(-1, 2)
        bgraph = coo_matrix((np.ones(len(inv)), (inv[:, 0], inv[:, 1])), shape=(len(nodes), len(nodes)))
        n_loops = int(connected_components(bgraph, directed=False)[0])

    # corner angles -> angle sums per vertex (angle defects)
    tri = verts[f]
    angles = np.empty((nf, 3))
    for c in range(3):
        e1 = tri[:, (c + 1) % 3] - tri[:, c]
        e2 = tri[:, (c + 2) % 3] - tri[:, c]
        angles[:, c] = np.arctan2(np.linalg.norm(np.cross(e1, e2), axis=1), np.einsum("ij,ij->i", e1, e2))
    angle_sum = np.bincount(f.ravel(), weights=angles.ravel(), minlength=nv)

    # signed dihedral angle at every edge shared by exactly two faces (Steiner: ∫H dA = ½ Σ ℓ θ)
    fn, _ = face_normals_areas(verts, f)
    pair_start = np.flatnonzero(first)[count == 2]
    h1, h2 = srt[pair_start], srt[pair_start + 1]  # the two half-edges of the edge
    f1, f2 = face_of[h1], face_of[h2]
    n1, n2 = fn[f1], fn[f2]
    theta = np.arctan2(np.linalg.norm(np.cross(n1, n2), axis=1), np.einsum("ij,ij->i", n1, n2))
    # convex when the far corner of face 2 lies below the plane of face 1
    far = f[f2][np.arange(len(f2)), (np.argmax(f[f2] == a[h2][:, None], axis=1) + 2) % 3]
    convex = np.einsum("ij,ij->i", verts[far] - verts[a[h1]], n1) <= 0
    length = np.linalg.norm(verts[a[h1]] - verts[b[h1]], axis=1)
    total_h = 0.5 * float(np.nansum(length * np.where(convex, theta, -theta)))
    return {
        "vertices": verts, "faces": f, "n_collapsed": int(n_collapsed), "used": used,
        "chi": int(used.sum()) - n_edges + nf, "watertight": watertight,
        "consistent": bool(directed), "non_manifold_edges": int((count > 2).sum()),
        "n_components": n_comp, "n_loops": n_loops, "boundary": bverts,
        "angle_sum": angle_sum, "total_mean_curvature": total_h,
    }


def _image_quality(mesh: trimesh.Trimesh) -> dict:
    """What NEMO's mesh step found in the image (None for meshes from elsewhere)."""
    params = mesh.metadata.get("nemo_params") or {}
    return {key: params.get(key) for key in ("n_objects", "snr", "noise", "saturated", "rim_loops", "largest_hole", "walls",
                                             "regions", "turned_out", "mask_offset", "mask_offset_limit",
                                             "mask_contrast", "edge_check", "deconvolution")}


def _genus(topo: dict, notes: list[str]) -> int | None:
    """Total genus from χ = Σ 2 − 2g − b (None where undefined); notes on the topology's problems."""
    if topo["n_collapsed"]:
        notes.append(f"{topo['n_collapsed']} faces collapse onto coincident vertices; ignored for "
                     "topology and angles")
    if topo["non_manifold_edges"]:
        notes.append(f"{topo['non_manifold_edges']} non-manifold edges (shared by more than two faces)")
    if not topo["consistent"]:
        notes.append("face winding is inconsistent: volume and mean curvature are unreliable")
    genus_twice = 2 * topo["n_components"] - topo["n_loops"] - topo["chi"]
    if genus_twice >= 0 and genus_twice % 2 == 0 and not topo["non_manifold_edges"]:
        return genus_twice // 2
    notes.append("genus undefined: the mesh is not a manifold orientable surface")
    return None


def _fitted_sums(mesh: trimesh.Trimesh, curvature_df: pd.DataFrame, chi: int, n_loops: int, turning: float,
                 notes: list[str]) -> dict:
    """``measure``'s sums of the fitted curvature: ∫K dA, its Gauss–Bonnet ratio, mean H and K."""
    n_vertices = len(mesh.vertices)
    if len(curvature_df) != n_vertices or "K" not in curvature_df or "H" not in curvature_df:
        raise NemoError(
            f"the curvature table has {len(curvature_df)} rows but the mesh {n_vertices} "
            "vertices (or it lacks H, K): was it computed on this mesh?"
        )
    order = np.argsort(curvature_df["vertex"].to_numpy())
    kf = curvature_df["K"].to_numpy(dtype=np.float64)[order]
    hf = curvature_df["H"].to_numpy(dtype=np.float64)[order]
    areas = vertex_areas(mesh)
    ok = np.isfinite(kf) & np.isfinite(hf)
    if (~ok & (areas > 0)).any():
        notes.append(f"fitted curvature is NaN at {int((~ok).sum())} vertices; left out of the sums")
    ik = float(np.sum(kf[ok] * areas[ok]))
    a_ok = float(areas[ok].sum())
    # an open surface's fits are NaN along the rim: the sum then misses a band, no check
    whole = chi != 0 and not (n_loops and (~ok & (areas > 0)).any())
    return {"integral_K_fit": ik,
            "gauss_bonnet_ratio_fit": (ik + turning) / (2 * np.pi * chi) if whole else None,
            "mean_H_fit": float(np.sum(hf[ok] * areas[ok]) / a_ok) if a_ok > 0 else None,
            "mean_K_fit": ik / a_ok if a_ok > 0 else None}


def measure(mesh: trimesh.Trimesh, curvature_df: pd.DataFrame | None = None) -> dict:
    """Global morphology of a surface.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        Surface with outward normals.
    curvature_df : DataFrame, optional
        Output of :func:`curvature` on this mesh; adds the fitted ∫K dA, its Gauss–Bonnet ratio
        and the area-weighted mean of the fitted H and K.

    Returns
    -------
    dict
        ``unit``, ``n_vertices``, ``n_faces``, ``area`` (unit²), ``volume`` (unit³; None for
        open meshes), ``is_watertight``, ``n_components``, ``n_boundary_loops``,
        ``euler_characteristic`` χ = V − E + F, ``genus`` (total over components, from
        χ = Σ 2 − 2g − b), ``integral_K`` (discrete: Σ angle defects of interior vertices),
        ``boundary_turning`` (Σ (π − angle sum) over boundary vertices = ∫k_g ds),
        ``gauss_bonnet_ratio`` ((∫K dA + ∫k_g ds) / 2πχ; None when χ = 0), ``mean_H``
        (area-weighted, from the dihedral angles: ∫H dA = ½ Σ_edges ℓ θ), ``mean_K``, and with
        ``curvature_df``: ``integral_K_fit``, ``gauss_bonnet_ratio_fit`` (None on an open
        surface whose fits are NaN along the rim: the sum misses that band), ``mean_H_fit``,
        ``mean_K_fit`` (over the vertices with a fit); ``n_objects``, ``snr``, ``noise`` and
        ``saturated`` of the image the mesh was made from, ``rim_loops`` (where the image
        border cuts the object; a list per object with several), ``walls`` (1 or 2; a list per object with several) and
        ``turned_out`` (objects that enclosed the dark side, turned out), from
        NEMO's mesh step (None otherwise); ``notes`` (list of
        str). Coincident vertices are merged (and the faces they collapse ignored) for the
        topology and the angles.
    """
    check_mesh(mesh, manifold=False)  # a diagnostic: it reports a non-manifold surface in its notes
    notes: list[str] = []
    unit = _unit_name(mesh)
    vertices_in = np.asarray(mesh.vertices, dtype=np.float64)
    faces_in = np.asarray(mesh.faces, dtype=np.int64)
    n_vertices_in, n_faces_in = len(vertices_in), len(faces_in)
    area = float(face_normals_areas(vertices_in, faces_in)[1].sum())
    topo = _topology(vertices_in, faces_in)
    genus = _genus(topo, notes)
    watertight = topo["watertight"]
    chi = topo["chi"]
    n_comp, n_loops = topo["n_components"], topo["n_loops"]

    volume = signed_volume(vertices_in, faces_in) if watertight else None
    if not watertight:
        notes.append(
            f"open or non-manifold mesh ({n_loops} boundary loop(s)): no enclosed volume; "
            "Gauss–Bonnet includes the boundary turning ∫k_g ds"
        )
    elif volume < 0:
        notes.append("negative volume: the faces are wound inward (normals point inside)")

    used, boundary, angle_sum = topo["used"], topo["boundary"], topo["angle_sum"]
    integral_k = float(np.sum(2 * np.pi - angle_sum[used & ~boundary]))
    turning = float(np.sum(np.pi - angle_sum[boundary]))
    gb = (integral_k + turning) / (2 * np.pi * chi) if chi != 0 else None
    if chi == 0:
        notes.append("χ = 0 (e.g. a torus): Gauss–Bonnet predicts ∫K dA + ∫k_g ds = 0, no ratio")
    mean_h = topo["total_mean_curvature"] / area if area > 0 else None

    result: dict = {
        "unit": unit,
        "n_vertices": int(n_vertices_in),
        "n_faces": int(n_faces_in),
        "area": area,
        "volume": volume,
        "is_watertight": watertight,
        "n_components": n_comp,
        "n_boundary_loops": n_loops,
        "euler_characteristic": chi,
        "genus": genus,
        "integral_K": integral_k,
        "boundary_turning": turning,
        "gauss_bonnet_ratio": gb,
        "mean_H": mean_h,
        "mean_K": integral_k / area if area > 0 else None,
        **_image_quality(mesh),
    }
    if curvature_df is not None:
        result.update(_fitted_sums(mesh, curvature_df, chi, n_loops, turning, notes))
    result["notes"] = notes
    logger.debug("measure: %s", result)
    return result
