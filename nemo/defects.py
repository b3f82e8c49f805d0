"""Topological defects of a tangential nematic field: localisation and curvature-corrected charge.

Method note §7 and the paper's "Defect detection and topological charge". The mesh-edge
graph, geodesic balls, boundary loops and tangent bases it uses are in :mod:`nemo.geometry`.

Localisation
------------
1. **Candidates** are the vertices whose nematic order ``S`` (from :func:`nemo.order.order`) is
   below ``s_threshold``. Default: half the "ordered level" ``S_ref`` = 90th percentile of ``S``
   over the surface, so the threshold follows the data (an averaging radius that gives S ≈ 0.6
   in ordered regions gets a threshold of 0.3, one that gives 0.95 gets 0.475).
2. **Non-maximum suppression**: repeatedly take the candidate with the lowest ``S`` and discard
   every candidate within the geodesic distance ``min_distance`` of it (shortest paths along
   mesh edges, :func:`scipy.sparse.csgraph.dijkstra` with a distance ``limit``, one run per
   accepted defect). Default ``min_distance`` = the averaging radius of the order table: two
   defects closer than that share one dip of ``S`` and cannot be told apart.
3. **Sub-vertex refinement**. The vertex of minimum ``S`` is biased by the averaging (a
   background gradient of the director angle shifts the zero of the averaged Q-tensor by
   ~ c a²), so the position is refined from the *raw* directors near the vertex: a defect model
   θ(ξ, η) = m·atan2(η − η0, ξ − ξ0) + θ0 + c1 ξ + c2 η (charge m from the contour, a linear
   background) is fitted to the director angles within ``fit_radius`` (:data:`FIT_PER_AVERAGING`
   = 1.125 × the averaging radius, at most 0.75 × the surface's size but not below the former
   0.75 × the averaging radius, and at most half the distance to the nearest other dip) in the
   vertex's tangent plane (robust soft-L1 least squares on sin(θ_obs − θ), coherency weights,
   directors at the trial core damped, five starting cores, one re-centred refit; the core at
   most :data:`SHIFT_PER_AVERAGING` × the averaging radius from the vertex), and the fitted core
   (ξ0, η0) is projected back onto the nearest surface triangle.
   When the model fit fails or there are too few directors, the zero of a linear fit of the
   averaged Q-tensor components is used (``refine="q"``), else the vertex itself.

Charge
------
A closed contour around the defect is the boundary loop of the geodesic ball
``{v : d(v) < contour_radius + h/2}`` (h the mean edge, so that the loop's vertices lie at
the radius on average; the faces whose three vertices are inside); walking its
boundary edges in the faces' outward winding order makes the loop counter-clockwise seen from
the outward normal, and each step is one mesh edge. The director on the contour (``winding_field``:
the averaged field ``n_avg`` of the order table, or the nearest raw director) is projected onto
each vertex's tangent plane, aligned head to tail (``n_{i+1} → −n_{i+1}`` when
``n_i·n_{i+1} < 0``) and the signed turning angle of each step is summed,
``atan2((R n_i × n_{i+1})·N_{i+1}, R n_i·n_{i+1})`` with ``R`` the smallest rotation taking
``N_i`` to ``N_{i+1}`` (the discrete parallel transport along the step; the exact angle, the
paper's small-angle form ``(n_i × (n_{i+1} − n_i))·N_i`` = sin Δθ underestimates large steps,
see ``exact_angles``). The curvature term is (1/2π) ∫K dA over the enclosed patch
(``curvature_source``):

* ``contour`` (the default without a ``curvature`` array): Gauss–Bonnet on the contour itself,
  ∫K dA = 2π − Σ turning of the contour's tangent (:func:`contour_curvature`), measured with the
  same points, normals and transported step angles as the winding. The winding's steps carry
  the holonomy of that discrete surface; taking the K term from the same discretisation cancels
  it exactly (each step of the director minus the tangent's is the change of the angle between
  them, so winding + K term is a multiple of ½ on any contour), where the enclosed vertices' ∫K
  (next item) is a second estimate whose noise on a rough wall does not cancel (the z-blurred
  vesicles: charge errors up to 0.09 with it, 0.015 with the contour's and the mean-normal step
  of session 17, docs/validation.md). A contour that turns by more
  than :data:`MAX_CONTOUR_TURN_DEG` in one step (a zigzag), or whose enclosed faces are not a
  disc (a contour round a tube or a hole, where Gauss–Bonnet on one contour does not hold),
  takes the enclosed vertices' ∫K instead, counted in ``contours["k_from_vertices"]``. Because
  the two terms cancel, a contour's charge is a multiple of ½ whatever the field, so the
  off-half test below rejects nothing under this source (a misread field shows as a wrong
  multiple, not as an off-half value); the S floor, the step limit and the
  zero-charge test remain.
* ``angle-defects``: interior vertices count fully and contour vertices half (the contour runs
  through them), the discrete integrated Gaussian curvature (angle defects,
  ``mesh.vertex_defects``, for which discrete Gauss–Bonnet is exact) after three conservative
  smoothing passes (:func:`smooth_conserving`: the total is unchanged, the vertex-to-vertex
  noise that the contour's half-weighted band would pick up is averaged out).
* ``table``: the same with a per-vertex ``curvature`` array, Σ K·A (barycentric vertex areas).

Charge = winding + curvature term (``curvature_correction=False`` drops the second),
``charge_rounded`` = nearest multiple of ½.

Rejection of spurious defects (documented S logic, scaled with the sampling)
-----------------------------------------------------------------------------
Averaging an *isotropic* director field still gives a smooth ``n_avg`` with genuine ±½ zeros
of ``S``; they are noise, not defects. A candidate is reported only when the field around it is
ordered: the median ``S`` on its contour must reach ``s_floor`` = the larger of ``s_ordered``
(default ``s_threshold``) and the noise floor of :func:`noise_floor`: the isotropic mean
sqrt(π/4N) plus ``NOISE_Z`` = 3 standard errors of the contour's median, sqrt((1 − π/4)/N) /
sqrt(M), with ``N`` the raw directors per averaging disc (median over the contour; the order
table's ``count``, else counted in the directors table) and ``M`` = contour length / averaging
diameter the independent discs the median pools; capped midway between the isotropic mean
and perfect order, so that few directors can still pass when they are ordered. It must also
have a resolved, non-zero charge: every step of the winding below :func:`step_limit_deg`
(2.5 × the mean step π/k of a ½ defect on k steps, within 60-80°) and
``|charge − charge_rounded| ≤ charge_tolerance``, ``charge_rounded ≠ 0`` (with
``curvature_correction=False`` the raw winding is biased by design, so the tolerance test is
skipped). On a closed surface, a contour that encloses more than :data:`MAX_ENCLOSED_FRACTION`
of the surface's vertices is rejected (``"contour encloses most of the surface"``): on a small object a contour
radius grown from the averaging radius can reach round the far side, and such a contour's charge
is that of every defect inside it (a "+2" on a sphere with two +1 poles, 26 µm from both, in an
independent review). Rejections are counted in ``df.attrs["parameters"]["rejected"]`` and logged, and
the zeros of the averaged Q-tensor among them that may be defects in ``rejected_zeros``
(:func:`rejected_zeros`: possibly missed defects, which the summary's quality control flags); every
examined candidate (accepted or not, with its contour S, floor, largest step, limit and reason)
is kept in ``df.attrs["candidates"]`` (:func:`candidate_table`, ``nemo defects --candidates``).

Coarse meshes
-------------
When the mesh-edge contour has fewer vertices than :func:`steps_needed` (one per half averaging
radius: edges comparable to the averaging radius, e.g. one director per vertex of a 6-10 µm
grid), the winding is measured on a circle of the contour radius sampled in the candidate's
tangent plane at that density (×2) and projected onto the surface (``contour = "circle"``):
the averaged field there is recomputed from the raw directors within the averaging radius, or
interpolated from the order table's Q-tensor without them; the enclosed ∫K dA weights each
vertex by the fraction of its cell inside the circle. ``df.attrs["parameters"]["contours"]``
counts the contour kinds (``loop``, ``ring`` fallback, ``circle``) and the contours ``shrunk``
to stay off an open rim.

Open surfaces
-------------
A surface cut by the field of view (``mesh.border: open``) has a rim. A contour must be a closed
curve *on* the surface around the candidate: one that reaches the rim leaves the surface and
its winding says nothing about a defect (the director's turning along the rim is not a charge).
So a contour is shrunk until it stays one edge inside the rim (``shrunk``), and a candidate
with no room for a contour of at least min(3 edges, averaging radius) is rejected as
``"contour leaves the surface"`` (:data:`RIM_REASON`, counted in ``rejected`` and listed in the
candidate table like the other rejections): no defect and no charge come from the rim.

Integer defects
---------------
The averaged Q-tensor of an |m| = 1 defect vanishes quadratically, and any noise splits that
zero into two ±½ zeros a few µm apart inside one dip of S. Candidates are therefore grouped
into dips (connected components of ``S < s_threshold``); the lowest centre of a dip is measured
first with a contour of 1.5 × the averaging radius (grown to 2.5× when S on it is still low),
and further centres of the same dip inside that contour belong to it. Contours never reach
another dip (radius ≤ 0.45 × the distance to it). On sparse fields two dips can still lead to
one defect (their refined cores coincide): a defect whose core lies within half an averaging
radius of one already accepted is rejected as "same defect".

Euler check
-----------
On a closed surface the charges add up to the Euler characteristic χ (Poincaré–Hopf). The check
(Σ charge, Σ charge_rounded, χ, closed) is logged and stored in ``df.attrs["euler_check"]``.

Accuracy
--------
The measured accuracy is in ``docs/validation.md`` (``benchmarks/bench_defects.py``, the
validation protocol of :mod:`nemo.validation`). On measured directors the remaining error of a +½
core is mostly a displacement along the comet axis towards the tail: the gradient structure
tensor weights orientations by fibre "ink", which is uneven around a comet of streamlines
(denser on the head side), so the measured field's core moves towards the tail by an amount
that grows with the gradient and integration scales. The fit's first harmonic term
(``fit_harmonic``) does not separate it from a true shift and is off by default.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
import trimesh
from scipy import optimize, sparse
from scipy.spatial import cKDTree

from nemo._log import logger
from nemo.errors import NemoError, NemoWarning, ObjectTooSmallError
from nemo.geometry import (
    boundary_loop,
    edge_graph,
    geodesic_ball,
    project_tangent,
    rim,
    rotate_between,
    smooth_conserving,
    tangent_basis,
)
from nemo.mesh import vertex_areas, vertex_normals
from nemo.order import lift_q, tangential_eig

#: Columns of the defect table (the documented schema first, then diagnostics).
COLUMNS = (
    "x", "y", "z", "vertex", "S", "charge", "charge_winding", "charge_curvature",
    "charge_rounded", "contour_radius", "n_contour", "contour_S", "max_step_deg",
    "refine", "shift", "fit_radius", "fit_residual", "fit_scatter", "fit_uncertainty", "coherency",
)

#: Columns of the candidate table (:func:`candidate_table`, ``nemo defects --candidates``).
CANDIDATE_COLUMNS = (
    "x", "y", "z", "vertex", "S", "charge", "charge_rounded", "contour_S", "s_floor", "max_step_deg",
    "step_limit_deg", "n_contour", "contour", "contour_radius", "accepted", "reason",
)


# ----------------------------------------------------------------------------------------------
# constants and contour helpers (the mesh-graph helpers are in nemo.geometry)


#: Two accepted defects whose refined cores lie closer than this (in averaging radii) are one
#: defect found from two candidates: the second is rejected as "same defect".
SAME_DEFECT_PER_AVERAGING = 0.5

#: Largest contour, averaging or fit radius, in units of the surface's size sqrt(area / 4π).
MAX_RADIUS_PER_SIZE = 2.0

#: Largest turn of a contour's tangent in one step for its Gauss–Bonnet K term (degrees): beyond
#: it the contour zigzags and the sign of the turn is ambiguous (:func:`contour_curvature`).
MAX_CONTOUR_TURN_DEG = 90.0

#: Half-width (contour steps) of the chord that gives a contour's tangent for its K term: a loop
#: of mesh edges zigzags (one turn in four above 90° at one step on the z-blurred vesicles' walls).
CONTOUR_CHORD_STEPS = 3

#: The K terms of :func:`find_defects` (``curvature_source``).
CURVATURE_SOURCES = ("contour", "angle-defects", "table")

#: Default contour radius in averaging radii (the suppression radius default is one averaging radius).
CONTOUR_PER_AVERAGING = 1.5

#: Default radius of the sub-vertex fit (and of the refinement's extra directors) in averaging
#: radii: the core's signature in the directors falls as 1 / r, so a wider fit gains directors
#: whose errors average out, until the linear background no longer holds (docs/validation.md,
#: "The defect model's fit radius": 0.75 → 1.125 brought the median defect of 33 frames of three
#: generators from 2.10 to 1.70 µm, of an independent generator's 43 frames from 2.70 to 2.40 µm).
FIT_PER_AVERAGING = 1.125

#: ... and at most this many sizes of the surface (the radius of the sphere of its area): on a sphere
#: the tangent plane then shortens the fit's farthest distances by less than 10 % (sin x / x > 0.9).
#: Not below the former 0.75 × the averaging radius: an object about as small as its averaging
#: radius keeps the fit it had. (The size is global: a flat, strongly curved face is not protected.)
FIT_MAX_PER_SIZE = 0.75

#: The fitted core may lie at most this many averaging radii (and the fit radius) from the vertex of
#: least S, and the averaged field's zero (the fallback) is read within it: a wider fit must not let
#: a noisy fit's far minimum move the defect farther than before the fit radius was widened.
SHIFT_PER_AVERAGING = 0.75

#: A candidate of the same dip whose S is below this fraction of the surface's ordered level (P90
#: of S) is a zero of the averaged Q-tensor (S 0.01–0.03 for 0.88), not a shallow minimum (0.26–0.44).
ZERO_PER_ORDERED = 0.125

#: Rejection reasons after which a zero of the averaged Q-tensor may still be a defect
#: (:func:`rejected_zeros`): its contour's order or winding could not be read (with a nonzero
#: winding), or the contour read zero round it (a ± pair inside).
UNREAD_REASONS = ("disordered contour", "unresolved winding")
PAIR_REASON = "zero charge"

#: A contour of radius r whose line passes between these fractions of r from such a zero runs
#: through its core (an averaging radius wide, r / 1.5): its winding there is ill-defined.
CONTOUR_CLEAR_BAND = (0.67, 1.33)


def angle_sorted_contour(vertices: np.ndarray, centre: np.ndarray, normal: np.ndarray,
                         idx: np.ndarray, dist: np.ndarray, radius: float, width: float) -> np.ndarray:
    """Fallback contour: vertices with |d − radius| < width/2 sorted counter-clockwise by angle."""
    ring = idx[np.abs(dist - radius) < 0.5 * width]
    t1, t2 = tangent_basis(normal)
    rel = vertices[ring] - centre
    ang = np.arctan2(rel @ t2, rel @ t1)
    return ring[np.argsort(ang)]


def winding_steps(dirs: np.ndarray, normals: np.ndarray, exact: bool = True) -> np.ndarray:
    """Signed turning angles of a closed loop of nematic directors.

    Parameters
    ----------
    dirs : ndarray, shape (L, 3)
        Unit tangent directors along the contour (order = contour direction).
    normals : ndarray, shape (L, 3)
        Unit outward normals at the contour points.
    exact : bool
        The exact angle (default): ``n_i`` is carried to point i + 1 by the smallest rotation
        taking ``N_i`` to ``N_{i+1}`` (the discrete parallel transport along the step) and the
        angle to ``n_{i+1}`` is ``atan2((R n_i × n_{i+1})·N_{i+1}, R n_i·n_{i+1})``. Otherwise
        the paper's small-angle form ``(n_i × (n_{i+1} − n_i))·N_i`` (= sin Δθ).

    Returns
    -------
    ndarray, shape (L,)
        Step angles in radians; their sum / 2π is the winding number. NaN where two successive
        normals are opposite (no smallest rotation).

    Notes
    -----
    Head–tail alignment flips ``n_{i+1}`` when ``n_i·n_{i+1} < 0`` (after the transport). Done
    per step against the *unflipped-chain* neighbour, which is equivalent to the iterative
    flipping of the paper for the step angles (each step is reduced to (−π/2, π/2]).
    """
    nxt = np.roll(dirs, -1, axis=0)
    if not exact:
        nxt = np.where(np.einsum("ij,ij->i", dirs, nxt)[:, None] < 0, -nxt, nxt)
        return np.einsum("ij,ij->i", np.cross(dirs, nxt), normals)
    moved = _transport(dirs, normals)
    nxt = np.where(np.einsum("ij,ij->i", moved, nxt)[:, None] < 0, -nxt, nxt)
    return _angles_about(moved, nxt, np.roll(normals, -1, axis=0))


def _transport(vec: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """``vec[i]`` (L, 3) rotated by the smallest rotation taking ``normals[i]`` to ``normals[i + 1]``
    (cyclic): Rodrigues' formula with axis N_i × N_{i+1}; NaN where the two normals are opposite.

    Measuring each step after this transport makes the step angles of a director and of the
    contour's tangent differ by exactly the change of the angle between them, so the winding and
    :func:`contour_curvature` cancel the holonomy of the discrete surface exactly.
    """
    return rotate_between(vec, normals, np.roll(normals, -1, axis=0))


def _angles_about(vec: np.ndarray, nxt: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Signed angles (L,) from ``vec[i]`` to ``nxt[i]`` about ``normals[i]``."""
    return np.arctan2(np.einsum("ij,ij->i", np.cross(vec, nxt), normals), np.einsum("ij,ij->i", vec, nxt))


def contour_curvature(points: np.ndarray, normals: np.ndarray) -> float | None:
    """∫K dA inside a closed contour from its own turning (Gauss–Bonnet on a disc).

    Parameters
    ----------
    points, normals : ndarray, shape (L, 3)
        The contour, counter-clockwise seen from the outward normals, and the unit normals there.

    Returns
    -------
    float or None
        2π − Σ turning, the turning of the tangent (the chord from ``CONTOUR_CHORD_STEPS`` points
        behind to as many ahead, projected on the tangent plane) measured as
        :func:`winding_steps` measures a director's; None when a step turns by more than
        :data:`MAX_CONTOUR_TURN_DEG` or a tangent vanishes. Each step is measured after the same
        transport as the winding's (:func:`_transport`), so a director's winding plus this term
        is a multiple of ½ on any discrete contour: the holonomy cancels exactly.
    """
    reach = max(1, min(CONTOUR_CHORD_STEPS, len(points) // 16))  # a chord over a few steps: a mesh loop zigzags
    tangent = project_tangent(np.roll(points, -reach, axis=0) - np.roll(points, reach, axis=0), normals)
    length = np.linalg.norm(tangent, axis=1, keepdims=True)
    if not np.all(length > 0):
        return None
    tangent = tangent / length
    turn = _angles_about(_transport(tangent, normals), np.roll(tangent, -1, axis=0), np.roll(normals, -1, axis=0))
    if not np.all(np.isfinite(turn)) or np.abs(turn).max() > math.radians(MAX_CONTOUR_TURN_DEG):
        return None
    return float(2 * math.pi - turn.sum())


def closest_point_local(mesh: trimesh.Trimesh, point: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """Closest point on the faces around ``vertices`` (a small ball) to ``point`` (3,)."""
    inball = np.zeros(len(mesh.vertices), dtype=bool)
    inball[vertices] = True
    faces = np.asarray(mesh.faces)
    tri = mesh.vertices[faces[inball[faces].any(axis=1)]]  # not mesh.vertex_faces: slow on degenerate faces
    cp = trimesh.triangles.closest_point(tri, np.repeat(point[None], len(tri), axis=0))
    return cp[np.argmin(np.linalg.norm(cp - point, axis=1))]


# ----------------------------------------------------------------------------------------------
# refinement


def _fit_defect_model(xi: np.ndarray, eta: np.ndarray, theta: np.ndarray, weight: np.ndarray,
                      m: float, scale: float, harmonic: bool = False,
                      residual: bool = False) -> np.ndarray | tuple[np.ndarray, float, float, float] | None:
    """Fit a defect model to nematic angles in a tangent plane; return the core (ξ0, η0), with
    ``residual`` also the fit's residual and its scatter between neighbours (:func:`_model_residual`, degrees)
    and the core's standard error (:func:`_core_uncertainty`, the unit of ξ, η).

    θ = m·φ + θ0 + (c1 ξ + c2 η)/scale [+ a cos φ + b sin φ], φ = atan2(η − η0, ξ − ξ0). The
    linear term absorbs the smooth background of the other defects and of the surface; the
    optional first harmonic absorbs a director-measurement bias that depends on the director's
    angle (for |m| = 1/2 an angle-dependent bias δ(θ) has a cos φ component that would otherwise
    be mistaken for a core displacement, whose signature is m·δ/r).
    """

    def model(p):
        phi = np.arctan2(eta - p[1], xi - p[0])
        out = m * phi + p[2] + (p[3] * xi + p[4] * eta) / scale
        if harmonic:
            out = out + p[5] * np.cos(phi) + p[6] * np.sin(phi)
        return out

    def resid(p):
        # damp the directors right at the trial core: the model angle is singular there, and an
        # undamped fit can snap the core onto a single noisy director
        r2 = (xi - p[0]) ** 2 + (eta - p[1]) ** 2
        return weight * (r2 / (r2 + r0 * r0)) * np.sin(theta - model(p))

    r0 = scale / math.sqrt(len(xi))  # ~ the spacing of the directors in the window
    best = None
    # a few starting cores (the window centre and a ring around it) guard against local minima
    starts = [(0.0, 0.0)] + [(0.2 * scale * math.cos(a), 0.2 * scale * math.sin(a))
                             for a in np.arange(4) * np.pi / 2]
    for sx, sy in starts:
        # θ0 in closed form for the starting core
        th0 = 0.5 * np.angle(np.sum(weight * np.exp(2j * (theta - m * np.arctan2(eta - sy, xi - sx)))))
        p0 = np.array([sx, sy, th0, 0.0, 0.0] + ([0.0, 0.0] if harmonic else []))
        xs = np.array([scale * 0.1, scale * 0.1] + [0.1] * (len(p0) - 2))
        try:
            res = optimize.least_squares(resid, p0, loss="soft_l1", f_scale=0.2, x_scale=xs)
        except (ValueError, np.linalg.LinAlgError):
            continue
        if res.success and np.all(np.isfinite(res.x)) and (best is None or res.cost < best.cost):
            best = res
    if best is None:
        return None
    if not residual:
        return best.x[:2]
    outer = np.hypot(xi - best.x[0], eta - best.x[1]) > RESIDUAL_INNER * scale
    residual_deg, scatter_deg, noise = _model_residual(theta[outer] - model(best.x)[outer], weight[outer], xi[outer],
                                                       eta[outer], scale)
    return best.x[:2], residual_deg, scatter_deg, _core_uncertainty(best.jac, weight, noise)


#: The fit's residual (:func:`_model_residual`) counts the directors beyond this fraction of the fit radius
#: from the fitted core: nearer ones turn fast and carry the window's smoothing of the core.
RESIDUAL_INNER = 1.0 / 3.0
#: Fewest directors the residual is read from (else NaN).
RESIDUAL_MIN_DIRECTORS = 6
#: Directors nearer each other than this fraction of their mean spacing in the fit's disc are copies of one
#: (a table written twice, layers at one point), not two measurements: the scatter skips such neighbours.
SCATTER_MIN_SPACING = 0.1
#: Nearest neighbours searched for each director's first one beyond :data:`SCATTER_MIN_SPACING`.
SCATTER_NEIGHBOURS = 8


def _model_residual(delta: np.ndarray, weight: np.ndarray, xi: np.ndarray, eta: np.ndarray,
                    scale: float) -> tuple[float, float, float]:
    """How far the directors at (ξ, η) are from the fitted defect model, and how much of it is their own noise.

    The weighted RMS (degrees) of the nematic angle differences ``delta`` (radians, taken modulo π
    into (−90°, 90°]); their scatter, the RMS that the directors' own independent noise alone would
    leave (:func:`_noise_scatter`: near 0 where ``delta`` is smooth, a misplaced core or a texture the
    model does not describe); and that noise σ (radians). NaN for too few directors.
    """
    if len(delta) < RESIDUAL_MIN_DIRECTORS or not np.sum(weight) > 0:
        return math.nan, math.nan, math.nan
    wrapped = 0.5 * np.angle(np.exp(2j * delta))
    residual = float(np.degrees(np.sqrt(np.average(wrapped**2, weights=weight))))
    return residual, *_noise_scatter(delta, weight, xi, eta, scale)


def _noise_scatter(delta: np.ndarray, weight: np.ndarray, xi: np.ndarray, eta: np.ndarray,
                   scale: float) -> tuple[float, float]:
    """The RMS (degrees) of ``delta`` that the directors' own independent noise alone would leave, and that
    noise σ (radians), read from the differences of ``delta`` between nearest neighbours (skipping copies,
    :data:`SCATTER_MIN_SPACING` of the mean spacing in a disc of radius ``scale``).

    Circular statistics, for wrapped-normal noise: E cos 2(δᵢ − δⱼ) = exp(−4σ²), and a wrapped δ's mean
    square π²/12 + Σₖ (−1)ᵏ exp(−2k²σ²) / k² (σ² where it hardly wraps). The wrapped differences' own RMS
    reads low once they wrap: 30-45° of noise left a misfit of 9.5-23° beyond it in a review. NaN (both)
    for too few directors with a neighbour.
    """
    points = np.column_stack([xi, eta])
    count = min(SCATTER_NEIGHBOURS + 1, len(xi))
    dist, idx = cKDTree(points).query(points, k=count)
    apart = dist[:, 1:] > SCATTER_MIN_SPACING * scale * math.sqrt(math.pi / len(xi))
    mine = np.flatnonzero(apart.any(axis=1))
    if len(mine) < RESIDUAL_MIN_DIRECTORS:
        return math.nan, math.nan
    other = idx[mine, 1 + np.argmax(apart[mine], axis=1)]
    weights = weight[mine] * weight[other]
    if not np.sum(weights) > 0:
        return math.nan, math.nan
    resultant = float(np.average(np.cos(2.0 * (delta[mine] - delta[other])), weights=weights))
    variance = -math.log(min(max(resultant, 1e-6), 1.0)) / 4.0
    if variance < 0.35**2:  # |δ| beyond 90° is ~1e-5 likely: the wrap changes nothing
        mean_square = variance
    else:
        k = np.arange(1, 60)
        mean_square = math.pi**2 / 12.0 + float(np.sum((-1.0) ** k * np.exp(-2.0 * k**2 * variance) / k**2))
    return math.degrees(math.sqrt(max(mean_square, 0.0))), math.sqrt(variance)


def _core_uncertainty(jac: np.ndarray, weight: np.ndarray, noise: float) -> float:
    """Standard error (the unit of ξ, η; the RMS over both tangent axes) of the fitted core: the
    Gauss–Newton covariance (JᵀJ)⁻¹ σ² of the model's parameters, ``jac`` (n, p) the robust fit's Jacobian
    (scipy's, scaled by its loss) with the core first, σ the directors' angle noise ``noise`` (radians,
    :func:`_noise_scatter`) times the RMS of their ``weight`` (n,): the weights scale the residuals and so J,
    and the noise with them, so the directors' coherency scale cancels (a review: uniform coherency 1 / 0.5 /
    0.2 read 0.07 / 0.13 / 0.30 of the fit radius without it). On independent noise the error over it had an
    RMS of 1.0-1.4 (4 000 directors, 5-30°). inf where the fit does not fix the core, NaN without a noise.
    Where the directors' noise is correlated over several of them (nemo's own, smoothed at the director
    scale; imported ones from a smoothing tool) their scatter and so this underestimate it: it measures the
    noise of independent directors."""
    if not np.isfinite(noise):
        return math.nan
    try:
        cov = np.linalg.inv(jac.T @ jac)
    except np.linalg.LinAlgError:
        return math.inf
    variance = (cov[0, 0] + cov[1, 1]) * float(np.mean(weight**2))
    return noise * math.sqrt(variance) if np.isfinite(variance) and variance >= 0 else math.inf


def _linear_q_zero(xi: np.ndarray, eta: np.ndarray, q: np.ndarray) -> np.ndarray | None:
    """Zero of a linear least-squares fit q(ξ, η) ≈ q0 + A (ξ, η) of 2-component Q data."""
    design = np.column_stack([np.ones_like(xi), xi, eta])
    coef, *_ = np.linalg.lstsq(design, q, rcond=None)  # (3, 2)
    amat = coef[1:].T
    if np.linalg.cond(amat) > 1e3:
        return None
    return -np.linalg.solve(amat, coef[0])


# ----------------------------------------------------------------------------------------------
# acceptance rule (scales with the sampling, module doc "Rejection of spurious defects")


#: Significance of the contour's order above the isotropic noise floor (standard errors).
NOISE_Z = 3.0


def noise_floor(n_dir: float, n_indep: float, z: float = NOISE_Z) -> float:
    """Median contour ``S`` that an isotropic field of ``n_dir`` directors per disc exceeds rarely.

    The ``S`` of ``N`` randomly oriented directors is the length of the mean of ``N`` random
    unit phasors ``exp(2iθ)``: Rayleigh distributed, mean ``sqrt(π/4N)``, standard deviation
    ``sqrt((1 − π/4)/N)``. The contour's median ``S`` pools ``n_indep`` independent averaging
    discs, so the floor is ``mean + z · sd / sqrt(n_indep)``, capped at the midpoint between the
    isotropic mean and perfect order (``N`` aligned directors give ``S = 1``), which keeps the
    floor below the order that ``N`` directors can reach.

    Parameters
    ----------
    n_dir : float
        Raw directors per averaging disc (median over the contour).
    n_indep : float
        Independent averaging discs along the contour (contour length / averaging diameter).
    z : float
        Standard errors above the isotropic mean.

    Returns
    -------
    float
    """
    n = max(float(n_dir), 1.0)
    mean = math.sqrt(math.pi / (4 * n))
    sd = math.sqrt((1 - math.pi / 4) / n)
    return float(min(mean + z * sd / math.sqrt(max(float(n_indep), 1.0)), 0.5 * (1 + mean)))


def step_limit_deg(n_steps: int) -> float:
    """Largest resolvable winding step (degrees) on a contour of ``n_steps`` steps.

    A ±½ defect turns the director by π/k per step on average over k steps; the limit allows
    2.5 times that, at least 60° and at most 80° (a true turn above 90° reads as its
    head-tail complement, so a step must stay clear of 90°).
    """
    return float(np.clip(2.5 * 180.0 / max(int(n_steps), 1), 60.0, 80.0))


def steps_needed(radius: float, avg_radius: float) -> int:
    """Contour points needed on a circle of ``radius``: one per half averaging radius, at least 8.

    The averaged field varies on the scale of the averaging radius, so points half of it apart
    resolve its turning; a mesh-edge contour with fewer vertices is replaced by a sampled circle.
    """
    return int(max(8, math.ceil(4 * math.pi * radius / avg_radius)))


# ----------------------------------------------------------------------------------------------
# main entry


@dataclass
class _Fields:
    S: np.ndarray  # (N,)
    navg: np.ndarray  # (N, 3)
    count: np.ndarray | None  # (N,) directors averaged per vertex (the order table's ``count``)
    dpos: np.ndarray | None  # (D, 3)
    ddir: np.ndarray | None  # (D, 3)
    dcoh: np.ndarray | None  # (D,)
    dnrm: np.ndarray | None  # (D, 3) surface normals at the directors
    dtree: cKDTree | None


@dataclass
class _Geometry:
    verts: np.ndarray  # (N, 3)
    normals: np.ndarray  # (N, 3)
    faces: np.ndarray  # (F, 3)
    vf: sparse.csr_matrix  # (N, F) vertex -> incident faces
    graph: sparse.csr_matrix  # (N, N) edge lengths
    kdA: np.ndarray  # (N,) integrated Gaussian curvature per vertex
    k_source: str
    boundary: np.ndarray  # (N,) bool, vertices on the mesh boundary
    h: float  # mean edge length

    @property
    def closed(self) -> bool:
        """No boundary: a contour's inside and outside are then ambiguous (which side holds the defect)."""
        return not bool(self.boundary.any())


@dataclass
class _Search:
    """What one search has accepted so far and what it keeps across candidates."""

    comp: np.ndarray  # (N,) dip (connected low-S component) of each candidate vertex, else -1
    fit: dict  # the defect-model fit's settings
    accepted: list = field(default_factory=list)  # (point, contour radius, dip) of each defect
    rows: list = field(default_factory=list)  # the defect rows


@dataclass
class _Settings:
    avg_radius: float
    winding_field: str
    curvature_correction: bool
    exact: bool
    charge_tolerance: float
    s_ordered: float
    k_from_contour: bool = False  # the K term from the contour's turning (module doc)
    s_ref: float = 1.0  # the surface's ordered level, P90 of S


def _check_order_table(mesh: trimesh.Trimesh, order_df: pd.DataFrame, tol: float) -> np.ndarray:
    """Validate the order table against the mesh; return its vertex column."""
    n = len(mesh.vertices)
    for col in ("vertex", "S", "nx", "ny", "nz"):
        if col not in order_df.columns:
            raise NemoError(f"order table lacks column {col!r}; make it with 'nemo order'")
    vtx = order_df["vertex"].to_numpy()
    if len(vtx) == 0:
        raise NemoError("order table is empty: nothing to find defects in")
    if vtx.min() < 0 or vtx.max() >= n:
        raise NemoError(
            f"order table refers to vertex {int(vtx.max())} but the mesh has {n} vertices: "
            "it was computed on another mesh")
    if {"x", "y", "z"} <= set(order_df.columns):
        dev = np.abs(order_df[["x", "y", "z"]].to_numpy(dtype=np.float64) - np.asarray(mesh.vertices)[vtx]).max()
        if dev > tol:
            raise NemoError(f"the order table's vertex positions differ from the mesh by up to {dev:.3g}: "
                            "it was computed on another mesh; give the mesh it was made on")
    return vtx


def _director_fields(mesh: trimesh.Trimesh, directors_df: pd.DataFrame | None, tol: float):
    """Raw directors: positions, directions, coherency, normals, KD-tree (all None without)."""
    if directors_df is None or not len(directors_df):
        return None, None, None, None, None
    n = len(mesh.vertices)
    for col in ("x", "y", "z", "nx", "ny", "nz"):
        if col not in directors_df.columns:
            raise NemoError(f"directors table lacks column {col!r}; make it with 'nemo directors'")
    dpos = directors_df[["x", "y", "z"]].to_numpy(dtype=np.float64)
    if "vertex" in directors_df.columns:
        dv = directors_df["vertex"].to_numpy()
        ok = (dv >= 0) & (dv < n)
        dev = (np.abs(dpos[ok] - np.asarray(mesh.vertices)[dv[ok]]).max() if ok.any() else 0.0)
        if not ok.all() or dev > tol:
            raise NemoError("the directors table does not match the mesh (vertex indices or positions "
                            "differ): it was computed on another mesh; give the mesh it was made on")
    else:
        _, dv = cKDTree(np.asarray(mesh.vertices)).query(np.nan_to_num(dpos))
    ddir = directors_df[["nx", "ny", "nz"]].to_numpy(dtype=np.float64)
    dcoh = (directors_df["coherency"].to_numpy(dtype=np.float64)
            if "coherency" in directors_df.columns else np.ones(len(dpos)))
    ok = np.all(np.isfinite(dpos), axis=1) & np.all(np.isfinite(ddir), axis=1)
    dnrm = vertex_normals(mesh)[np.asarray(dv, dtype=np.int64)[ok]]
    dpos, ddir, dcoh = dpos[ok], ddir[ok], np.nan_to_num(dcoh[ok], nan=0.0)
    ddir = project_tangent(ddir, dnrm)
    good = np.all(np.isfinite(ddir), axis=1)
    dpos, ddir, dcoh, dnrm = dpos[good], ddir[good], dcoh[good], dnrm[good]
    if not len(dpos):
        return None, None, None, None, None
    return dpos, ddir, dcoh, dnrm, cKDTree(dpos)


def _fields(mesh: trimesh.Trimesh, order_df: pd.DataFrame, directors_df: pd.DataFrame | None) -> _Fields:
    n = len(mesh.vertices)
    tol = 1e-3 * float(np.mean(mesh.edges_unique_length))  # PLY stores float32 coordinates
    vtx = _check_order_table(mesh, order_df, tol)
    S = np.full(n, np.nan)
    navg = np.full((n, 3), np.nan)
    S[vtx] = order_df["S"].to_numpy(dtype=np.float64)
    navg[vtx] = order_df[["nx", "ny", "nz"]].to_numpy(dtype=np.float64)
    count = None
    if "count" in order_df.columns:
        count = np.full(n, np.nan)
        count[vtx] = order_df["count"].to_numpy(dtype=np.float64)
    missing = ~np.isfinite(S)
    if missing.any():
        # order computed on a subset of targets: nearest computed vertex fills the rest
        have = np.flatnonzero(~missing)
        if len(have) == 0:
            raise NemoError("order table has no finite S value")
        _, j = cKDTree(mesh.vertices[have]).query(mesh.vertices[missing])
        S[missing] = S[have[j]]
        navg[missing] = navg[have[j]]
        if count is not None:
            count[missing] = count[have[j]]
    return _Fields(S, navg, count, *_director_fields(mesh, directors_df, tol))


def euler_characteristic(mesh: trimesh.Trimesh) -> int:
    """χ = V − E + F of the mesh."""
    return int(len(mesh.vertices) - len(mesh.edges_unique) + len(mesh.faces))


def _geometry(mesh: trimesh.Trimesh, curvature: np.ndarray | None) -> _Geometry:
    """Mesh arrays, edge graph, integrated curvature per vertex and boundary vertices."""
    n = len(mesh.vertices)
    graph = edge_graph(mesh)
    faces = np.ascontiguousarray(mesh.faces, dtype=np.int64)
    # vertex -> incident faces (CSR rows), so that a ball's faces cost O(ball), not O(mesh)
    vf = sparse.csr_matrix((np.ones(faces.size, dtype=np.int8),
                            (faces.ravel(), np.repeat(np.arange(len(faces)), 3))), shape=(n, len(faces)))
    boundary = rim(faces, n)["vertices"]
    kdA, k_source = _integrated_k(mesh, graph, curvature, boundary)
    return _Geometry(np.asarray(mesh.vertices, dtype=np.float64), vertex_normals(mesh), faces, vf, graph,
                     kdA, k_source, boundary, float(np.mean(mesh.edges_unique_length)))


def _integrated_k(mesh: trimesh.Trimesh, graph: sparse.csr_matrix, curvature: np.ndarray | None,
                  boundary: np.ndarray) -> tuple[np.ndarray, str]:
    """∫K dA per vertex (N,) and its source: K × vertex area from a curvature table, else the
    smoothed angle defects. Vertices where the table's K is NaN (e.g. within the fitting radius
    of an open rim) take the angle defects. The angle defect of a rim vertex (``boundary``) is
    the rim's turning (geodesic curvature), not Gaussian curvature: it counts 0, so that the
    smoothing does not spread it into the contours near the rim."""
    n = len(mesh.vertices)
    angle = "angle defects (discrete Gauss-Bonnet, 3 conservative smoothing passes)"
    defects = np.where(boundary, 0.0, np.asarray(mesh.vertex_defects, dtype=np.float64))
    if curvature is None:
        return smooth_conserving(defects, graph, 3), angle
    curvature = np.asarray(curvature, dtype=np.float64)
    if curvature.shape != (n,):
        raise NemoError(f"curvature has shape {curvature.shape}, expected ({n},) = one K per vertex")
    kdA = curvature * vertex_areas(mesh)
    bad = ~np.isfinite(kdA)
    if not bad.any():
        return kdA, "curvature table K x vertex area"
    logger.info("curvature has %d NaN values (e.g. at an open rim): angle defects there for the K term",
                int(bad.sum()))
    kdA[bad] = smooth_conserving(defects, graph, 3)[bad]
    return kdA, f"curvature table K x vertex area; {angle} at {int(bad.sum())} vertices without K"


def _estimate_avg_radius(geo: _Geometry, S: np.ndarray, s_ref: float, size: float) -> float:
    """Geodesic distance over which S recovers from its minimum to 0.9 × S_ref (module doc)."""
    idx, dist = geodesic_ball(geo.graph, int(np.nanargmin(S)), 2 * size)
    rec = dist[S[idx] >= 0.9 * s_ref]
    avg = float(rec.min()) if len(rec) else size / 4
    avg = float(np.clip(avg, 1.5 * geo.h, size))  # at least the spacing of a coarse mesh
    logger.info("averaging radius not given: estimated %.3g from the S field", avg)
    return avg


def _suppress(graph: sparse.csr_matrix, S: np.ndarray, cand: np.ndarray, min_distance: float) -> list[int]:
    """Non-maximum suppression: lowest S first, candidates within ``min_distance`` discarded."""
    centres: list[int] = []
    order_idx = np.argsort(np.where(cand, S, np.inf))
    alive = cand.copy()
    # visits candidates in increasing S; one Dijkstra per accepted vertex
    for v in order_idx[: int(cand.sum())].tolist():
        if not alive[v]:
            continue
        centres.append(v)
        idx, _ = geodesic_ball(graph, v, min_distance)
        alive[idx] = False
    return centres


def find_defects(
    mesh: trimesh.Trimesh,
    order_df: pd.DataFrame,
    directors_df: pd.DataFrame | None = None,
    curvature: np.ndarray | None = None,
    s_threshold: float | None = None,
    min_distance: float | None = None,
    max_defects: int | None = None,
    contour_radius: float | None = None,
    curvature_correction: bool = True,
    avg_radius: float | None = None,
    winding_field: str = "average",
    refine: str = "model",
    s_ordered: float | None = None,
    charge_tolerance: float = 0.15,
    exact_angles: bool = True,
    fit_radius: float | None = None,
    fit_exclude: float = 0.0,
    fit_harmonic: bool = False,
    curvature_source: str | None = None,
) -> pd.DataFrame:
    """Locate the topological defects of a tangential nematic field and measure their charge.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        Surface with outward normals, N vertices (physical units, µm).
    order_df : DataFrame
        Order table (``vertex``, ``S``, ``nx``, ``ny``, ``nz``, optional ``count``) on this mesh,
        ideally at every vertex (``targets="all"``); missing vertices take the nearest computed value.
    directors_df : DataFrame, optional
        Raw directors (``x``, ``y``, ``z``, ``nx``, ``ny``, ``nz``, ``coherency``): used for the
        sub-vertex refinement, the noise floor of ``S``, the averaged field on sampled circle
        contours and ``winding_field="directors"``.
    curvature : ndarray, shape (N,), optional
        Per-vertex Gaussian curvature K (1/µm²), for ``curvature_source="table"``.
    s_threshold : float, optional
        Candidates have ``S`` below it. Default ``0.5 × P90(S)``.
    min_distance : float, optional
        Geodesic suppression radius (µm). Default ``avg_radius``.
    max_defects : int, optional
        Stop after this many accepted defects.
    contour_radius : float, optional
        Geodesic radius of the charge contour (µm). Default 1.5 × ``avg_radius`` (grown up to
        1.67 × when S on the contour is low), capped at 0.45 × the distance to the nearest other
        dip or defect and kept off the mesh boundary, at least min(3 edge lengths, ``avg_radius``).
        A given radius is used as is, and grown up to 1.67 × (within the same cap) only where S
        on it is still low, before the candidate is rejected as disordered.
    curvature_correction : bool
        Add (1/2π)∫K dA over the enclosed patch (the paper's correction).
    avg_radius : float, optional
        Averaging radius the order table was made with (µm). Default: estimated from the data as
        the geodesic distance over which ``S`` recovers from its minimum to 0.9 × P90(S).
    winding_field : {"average", "directors"}
        Director field on the contour: ``n_avg`` of the order table or the nearest raw director.
    refine : {"model", "q", "none"}
        Sub-vertex refinement (module docstring).
    s_ordered : float, optional
        Minimum median ``S`` on the contour for a defect to be reported, on top of the noise
        floor (:func:`noise_floor`). Default ``s_threshold``.
    charge_tolerance : float
        Maximum ``|charge − charge_rounded|`` for a confident charge.
    exact_angles : bool
        Exact signed step angles (default) or the paper's small-angle sum.
    fit_radius : float, optional
        Radius of the data used for the sub-vertex refinement (µm). Default
        :data:`FIT_PER_AVERAGING` (1.125) × ``avg_radius``, at most :data:`FIT_MAX_PER_SIZE` (0.75) ×
        the surface's size (but not below 0.75 × ``avg_radius``); for each defect at most half the
        distance to the nearest other low-S centre, at least 3 mesh edges. At the default the fitted
        core moves at most :data:`SHIFT_PER_AVERAGING` (0.75) × ``avg_radius`` from the vertex of
        least S; a given radius is also the core's reach.
    curvature_source : {"contour", "angle-defects", "table"}, optional
        The K term (module doc): Gauss–Bonnet on the contour itself, or the enclosed vertices'
        angle defects or ``curvature``. Default ``table`` with a ``curvature`` array, else
        ``contour``.

    Returns
    -------
    DataFrame
        One row per defect: ``x, y, z`` (refined position on the surface), ``vertex`` (nearest
        vertex), ``S`` (at that vertex), ``charge``, ``charge_winding``, ``charge_curvature``,
        ``charge_rounded`` and diagnostics ``contour_radius``, ``n_contour``, ``contour_S``
        (median S on the contour), ``max_step_deg``, ``refine`` (method used; ``"zeros"``: an |m| ≥ 1
        defect placed among the Q-zeros of its dip that its contour encloses, :func:`_among_zeros`), ``shift`` (µm from
        the minimum-S vertex), ``fit_radius`` (the model fit's radius), ``fit_residual`` (degrees: the weighted RMS
        of the directors' angles about the fitted model beyond :data:`RESIDUAL_INNER` of the fit radius from the
        core, :func:`_model_residual`; NaN where no model fit placed it: large where the directors do not
        follow a defect there, a misplaced core or an unreadable texture), ``fit_scatter`` (degrees: how much of
        it is the directors' own noise, their differences' scatter between neighbours) and ``fit_uncertainty``
        (the core's standard error with that noise, :func:`_core_uncertainty`), ``coherency`` (the directors'
        median coherency within the contour radius over the surface's, :func:`_local_coherency`: well below 1 where the fibres are
        faint and the position unreliable). ``df.attrs`` holds the parameters used (with the rejection counts
        ``rejected`` and the contour kinds ``contours``), ``euler_check`` and ``candidates``
        (every examined candidate with its reason, as records: :func:`candidate_table`).
    """
    if winding_field not in ("average", "directors"):
        raise NemoError(f"winding_field must be 'average' or 'directors', not {winding_field!r}")
    if refine not in ("model", "q", "none"):
        raise NemoError(f"refine must be 'model', 'q' or 'none', not {refine!r}")
    for name, value in (("s_threshold", s_threshold), ("min_distance", min_distance),
                        ("contour_radius", contour_radius), ("avg_radius", avg_radius),
                        ("fit_radius", fit_radius), ("s_ordered", s_ordered)):
        if value is not None and not (np.isfinite(value) and value > 0):
            raise NemoError(f"{name} must be a positive number, got {value}")
    if max_defects is not None and max_defects < 1:
        raise NemoError(f"max_defects must be at least 1, got {max_defects}")
    if curvature_source is None:
        curvature_source = "contour" if curvature is None else "table"
    if curvature_source not in CURVATURE_SOURCES:
        raise NemoError(f"curvature_source must be one of {', '.join(CURVATURE_SOURCES)}, not {curvature_source!r}")
    if (curvature is not None) != (curvature_source == "table"):
        raise NemoError("a curvature array goes with curvature_source='table' and only with it: "
                        f"got curvature_source={curvature_source!r} and "
                        f"{'a' if curvature is not None else 'no'} curvature array")
    f = _fields(mesh, order_df, directors_df)
    if winding_field == "directors" and f.dtree is None:
        raise NemoError("winding_field='directors' needs a directors table")
    geo = _geometry(mesh, curvature)
    S = f.S
    s_ref = float(np.nanpercentile(S, 90))
    s_threshold = 0.5 * s_ref if s_threshold is None else s_threshold
    size = math.sqrt(float(mesh.area) / (4 * math.pi))  # radius of the sphere of equal area
    for name, value in (("contour_radius", contour_radius), ("avg_radius", avg_radius), ("fit_radius", fit_radius)):
        if value is not None and value > MAX_RADIUS_PER_SIZE * size:
            reason = (f"`{name}` {value:.4g} is larger than {MAX_RADIUS_PER_SIZE:g} × the surface's size ({size:.4g}, "
                      f"the radius of the sphere of equal area)")
            raise ObjectTooSmallError(
                f"{reason}: a defect's contour must enclose a small piece of the surface; leave it unset (derived "
                f"from the averaging radius) or give a smaller value", reason)
    if avg_radius is None:
        avg_radius = _estimate_avg_radius(geo, S, s_ref, size)
    min_distance = avg_radius if min_distance is None else min_distance
    r_contour_default = contour_radius if contour_radius is not None else CONTOUR_PER_AVERAGING * avg_radius
    # the size cap never narrower than the former 0.75 × (an object about as small as its averaging radius)
    size_cap = max(FIT_MAX_PER_SIZE * size, SHIFT_PER_AVERAGING * avg_radius)
    fit_default = fit_radius if fit_radius is not None else min(FIT_PER_AVERAGING * avg_radius, size_cap)
    st = _Settings(float(avg_radius), winding_field, bool(curvature_correction), exact_angles,
                   charge_tolerance, float(s_threshold if s_ordered is None else s_ordered),
                   k_from_contour=curvature_source == "contour", s_ref=s_ref)
    cand = np.isfinite(S) & (S < s_threshold)
    logger.info("defects: %d candidate vertices with S < %.3g (S_ref = P90 = %.3g)",
                int(cand.sum()), s_threshold, s_ref)
    if st.s_ordered >= s_ref:
        warnings.warn(f"the contour of a defect must reach S ≥ {st.s_ordered:.3g} (s_ordered, default "
                      f"s_threshold), above the surface's ordered level S_ref = {s_ref:.3g} (P90 of S): "
                      "almost every candidate will be rejected as disordered; lower s_threshold (default "
                      "S_ref / 2) or give s_ordered", NemoWarning, stacklevel=2)
    centres = _suppress(geo.graph, S, cand, min_distance)
    fit = {"refine": refine, "fit_radius": fit_default, "fit_given": fit_radius is not None,
           "fit_exclude": fit_exclude, "fit_harmonic": fit_harmonic}
    rows, records, tally = _examine(mesh, geo, f, st, centres, cand, contour_radius, r_contour_default,
                                    max_defects, fit)
    df = pd.DataFrame(rows, columns=list(COLUMNS))
    df = df.astype({"vertex": np.int64, "n_contour": np.int64}) if len(df) else df
    df["coherency"] = _local_coherency(f.dtree, f.dcoh, df)
    df.attrs["euler_check"] = _euler_check(mesh, df)
    df.attrs["parameters"] = {
        "s_threshold": float(s_threshold), "s_ref": s_ref, "min_distance": float(min_distance),
        "contour_radius": float(r_contour_default), "avg_radius": float(avg_radius),
        "max_defects": max_defects, "curvature_correction": bool(curvature_correction),
        "curvature_source": curvature_source, "winding_field": winding_field, "refine": refine,
        "k_term": "Gauss-Bonnet on the contour's turning" if st.k_from_contour else geo.k_source,
        "s_ordered": st.s_ordered, "noise_z": NOISE_Z, "charge_tolerance": charge_tolerance,
        "exact_angles": exact_angles, **tally,
        # before each defect's cap at half the distance to its nearest other dip (the table's fit_radius)
        "fit_radius": float(fit_default),
        "rejected_zeros": rejected_zeros(records, s_ref),
    }
    df.attrs["candidates"] = records
    logger.info("defects: %d found, %d low-S candidates rejected (%s)", len(df), sum(tally["rejected"].values()),
                ", ".join(f"{k}: {v}" for k, v in tally["rejected"].items() if v) or "none")
    return df


def rejected_zeros(records: list[dict], s_ref: float) -> int:
    """How many examined candidates may be missed defects: zeros of the averaged Q-tensor (S below
    :data:`ZERO_PER_ORDERED` × ``s_ref``, as deep as a found defect's core, not a shallow minimum)
    rejected because their contour read a nonzero charge but was disordered or its winding
    unresolved (:data:`UNREAD_REASONS`), or read a zero charge (:data:`PAIR_REASON`: a ± pair
    inside one contour sums to 0).

    Such zeros are what defects closer together than the contour radius look like: ±½ pairs and a
    −½ beside a +½ on a peanut's lobes (R 36 µm, 24 µm averaging radius: contours of 20 µm through
    the neighbour's disordered core) read S 0.003–0.013 and were rejected at 0.52–0.98 of the
    contour's S floor, Σ charge still χ (an independent review, session 28); a ±½ pair 20 µm
    apart on a sphere R 60 µm averaged over 15 µm reads one zero of charge 0 (tests). Noise alone
    makes shallow minima, with a zero or an unresolved winding.

    Parameters
    ----------
    records : list of dict
        The candidate records (``df.attrs["candidates"]`` of :func:`find_defects`).
    s_ref : float
        The surface's ordered level (P90 of S).
    """
    def missed(r: dict) -> bool:
        if r["reason"] == PAIR_REASON:
            return True
        return r["reason"] in UNREAD_REASONS and abs(r["charge_rounded"] or 0.0) > 0

    return sum(1 for r in records if r["S"] < ZERO_PER_ORDERED * s_ref and missed(r))


def _local_coherency(tree: cKDTree | None, coherency: np.ndarray | None, df: pd.DataFrame) -> np.ndarray:
    """Per defect (rows of ``df``), the median coherency of the raw directors (positions in ``tree``,
    ``coherency``) within its contour radius over their median: about 1 where the fibres are as
    clear as elsewhere (a defect is ordered fibres turning, each patch still coherent), well below
    where they are faint (no fibres, or fibres across an anisotropic PSF's long axis), where a low
    S says nothing of the field and the position is unreliable. NaN without directors."""
    out = np.full(len(df), np.nan)
    if tree is None or not len(df) or not np.median(coherency) > 0:
        return out
    near = tree.query_ball_point(df[["x", "y", "z"]].to_numpy(np.float64), df["contour_radius"].to_numpy(np.float64))
    for k, idx in enumerate(near):  # a loop over the few defects
        if len(idx):
            out[k] = float(np.median(coherency[idx])) / float(np.median(coherency))
    return out


def candidate_table(df: pd.DataFrame) -> pd.DataFrame:
    """Every candidate :func:`find_defects` examined, accepted or not, as a table.

    Parameters
    ----------
    df : DataFrame
        A result of :func:`find_defects` (its ``attrs["candidates"]``).

    Returns
    -------
    DataFrame
        One row per candidate (K rows), columns :data:`CANDIDATE_COLUMNS`: position ``x, y, z``
        (refined for accepted ones, else the vertex), ``vertex``, ``S``, ``charge``,
        ``charge_rounded``, ``contour_S``, ``s_floor`` (the acceptance floor of contour S),
        ``max_step_deg``, ``step_limit_deg``, ``n_contour``, ``contour`` (``loop``, ``ring`` or
        ``circle``), ``contour_radius``, ``accepted`` and ``reason`` (empty when accepted).
    """
    recs = df.attrs.get("candidates")
    if recs is None:
        raise NemoError("this table has no candidate records: make it with nemo.defects.find_defects")
    out = pd.DataFrame(list(recs), columns=list(CANDIDATE_COLUMNS))
    return out.astype({"vertex": np.int64, "n_contour": np.int64, "accepted": bool})


def _euler_check(mesh: trimesh.Trimesh, df: pd.DataFrame) -> dict:
    """Σ charge against the Euler characteristic (Poincaré–Hopf on a closed surface), logged."""
    chi = euler_characteristic(mesh)
    closed = bool(mesh.is_watertight)
    check = {
        "sum_charge": float(df["charge"].sum()) if len(df) else 0.0,
        "sum_charge_rounded": float(df["charge_rounded"].sum()) if len(df) else 0.0,
        "euler_characteristic": chi, "closed": closed,
        # no defect on a torus (χ 0) matches: the sum of none is 0
        "matches": bool(closed and abs((df["charge_rounded"].sum() if len(df) else 0.0) - chi) < 1e-9),
    }
    if closed:
        logger.info("Euler check: sum of charges %.3f (rounded %.1f) vs chi = %d (%s)",
                    check["sum_charge"], check["sum_charge_rounded"], chi,
                    "ok" if check["matches"] else "MISMATCH")
    else:
        logger.info("Euler check skipped: the surface is open (chi = %d, sum of charges %.3f)",
                    chi, check["sum_charge"])
    return check


def _contour_radii(r_default: float, given: float | None, dmin: float, h: float, avg: float) -> list[float]:
    """Radii to try in turn: the default (or given) one, then grown while S on it is low."""
    r_min = min(3 * h, avg)
    if given is None:
        return sorted({max(min(fac * r_default, 0.45 * dmin), r_min) for fac in (1.0, 1.33, 1.67)})
    # the given radius first; grown (not past other dips) only if S on it is still low
    return [given] + sorted({r for r in (min(fac * given, 0.45 * dmin) for fac in (1.33, 1.67)) if r > given})


def _clear_of_zeros(geo: _Geometry, v: int, radii: list[float], zeros: list[int]) -> tuple[list[float], list[int]]:
    """``radii`` of candidate ``v`` with those whose contour passes through the core (within
    :data:`CONTOUR_CLEAR_BAND`) of one of the ``zeros`` (the other Q-zeros of its dip) put last,
    and the zeros the first radius runs through (:func:`_among_zeros` places the defect among them).

    Under a z-elongated PSF an |m| = 1 defect splits into two +½ zeros in one dip (the +1 asters
    at the poles of a review's noise-free Hydra-like shell, 1.25 µm planes: 13–14 µm apart for a
    12 µm averaging radius), and two +½ closer than about an averaging radius share one dip too. A
    contour around one zero that ran through the other's core read +½, and the other zero, inside
    it, was taken as part of it: Σ charge short by ½ (both poles of that shell; two +½ 14–17 µm
    apart averaged over 20 µm). Enclosing both reads their sum."""
    lo, hi = CONTOUR_CLEAR_BAND
    dist = _distances(geo, v, zeros)
    crossed = [bool(np.any((dist > lo * r) & (dist < hi * r))) for r in radii]
    order = [r for r, c in zip(radii, crossed) if not c] + [r for r, c in zip(radii, crossed) if c]
    return order, [u for u, d in zip(zeros, dist) if lo * radii[0] < d < hi * radii[0]]


def _rejection(res: dict | None, st: _Settings) -> str | None:
    """Reason a measured candidate is not a defect (module doc), or None."""
    if res is None:
        return "no contour"
    if res["contour_S"] < res["s_floor"]:
        return "disordered contour"
    if res["max_step_deg"] > res["step_limit_deg"]:
        return "unresolved winding"
    if res.get("enclosed_fraction", 0.0) > MAX_ENCLOSED_FRACTION:  # set on closed surfaces only
        return ENCLOSES_REASON
    if res["charge_rounded"] == 0:
        return "zero charge"
    if st.curvature_correction and abs(res["charge"] - res["charge_rounded"]) > st.charge_tolerance:
        return "off-half charge"
    return None


def _examine(mesh, geo: _Geometry, f: _Fields, st: _Settings, centres: list[int], cand: np.ndarray,
             contour_radius: float | None, r_default: float, max_defects: int | None, fit: dict):
    """Measure, accept or reject and refine each suppressed candidate in turn.

    Candidates are examined lowest S first; a contour stays within ``0.45 × dmin`` of the nearest
    other dip or accepted defect so it encloses no other defect. A candidate rejected as
    disordered or unresolved on a contour shrunk that way is examined once more at the end, with
    ``dmin`` counting only what may still be a defect: a neighbouring dip whose own contour read a
    zero charge encloses none, and would otherwise cap the contour inside a defect's disordered core
    (the R 80 µm vesicles under a z-PSF lost a pole's +½ to two such dips 26 µm away). The wider
    contour's verdict replaces the first when it accepts the candidate, finds it part of an accepted
    defect ("same defect") or reads zero round it (a ± pair inside).

    Returns the defect rows, the candidate records (every candidate examined) and the tallies
    ``rejected`` (reason -> count) and ``contours`` (contour kind -> count, ``shrunk`` at a rim).
    """
    tally = {"rejected": dict.fromkeys(("disordered contour", "unresolved winding", "zero charge", "off-half charge",
                                        "no contour", RIM_REASON, ENCLOSES_REASON, "same dip", "same defect"), 0),
             "contours": dict.fromkeys(("loop", "ring", "circle", "shrunk", "k_from_vertices"), 0)}
    # low-S dips = connected components of the candidate vertices. Several zeros of the averaged
    # Q-tensor can share one dip (an |m| = 1 defect splits into two ±1/2 zeros a few µm apart under
    # noise): the lowest centre of a dip is measured first and the others of the same dip that its
    # contour encloses are part of it, not defects of their own.
    comp = np.full(len(geo.verts), -1)
    comp[np.flatnonzero(cand)] = sparse.csgraph.connected_components(
        geo.graph[cand][:, cand], directed=False)[1]
    search = _Search(comp=comp, fit=fit)
    records, reasons, retry = [], {}, []
    for v in centres:  # a handful of suppressed candidates, not the vertices
        if max_defects is not None and len(search.rows) >= max_defects:
            break
        if any(c == comp[v] and np.linalg.norm(p - geo.verts[v]) < r for p, r, c in search.accepted):
            reasons[v] = "same dip"
            tally["rejected"]["same dip"] += 1
            records.append(_record(_candidate(geo, f, v), None, "same dip"))
            continue
        dmin = _nearest(geo, v, [u for u in centres if comp[u] != comp[v]], search.accepted)
        radii, crossed = _clear_of_zeros(geo, v, _contour_radii(r_default, contour_radius, dmin, geo.h, st.avg_radius),
                                         _dip_zeros(f, st, centres, comp, v))
        reasons[v], record, contours = _verdict(mesh, geo, f, st, search, v, radii,
                                                dmin if len(centres) > 1 else np.inf, crossed)
        _count(tally, reasons[v], contours)
        records.append(record)
        if reasons[v] in UNREAD_REASONS:
            retry.append((v, len(records) - 1, radii))
    for v, at, radii in retry:  # only dips that may still be defects cap the contour now
        if max_defects is not None and len(search.rows) >= max_defects:
            break
        others = [u for u in centres if comp[u] != comp[v] and reasons.get(u) not in (PAIR_REASON, "same dip")]
        dmin = _nearest(geo, v, others, search.accepted)
        wider, crossed = _clear_of_zeros(geo, v, _contour_radii(r_default, contour_radius, dmin, geo.h, st.avg_radius),
                                         _dip_zeros(f, st, centres, comp, v))
        if max(wider) <= max(radii):
            continue
        reason, record, contours = _verdict(mesh, geo, f, st, search, v, wider, dmin, crossed)
        if reason in (None, "same defect", PAIR_REASON):  # the wider contour read what the first could not
            tally["rejected"][reasons[v]] -= 1  # the first verdict is replaced
            _count(tally, reason, contours)
            records[at] = record
    return search.rows, records, tally


def _dip_zeros(f: _Fields, st: _Settings, centres: list[int], comp: np.ndarray, v: int) -> list[int]:
    """The other candidates of candidate ``v``'s dip that are zeros of the averaged Q-tensor (S below
    :data:`ZERO_PER_ORDERED` of the surface's ordered level)."""
    return [u for u in centres if u != v and comp[u] == comp[v] and f.S[u] < ZERO_PER_ORDERED * st.s_ref]


def _distances(geo: _Geometry, v: int, others: list[int]) -> np.ndarray:
    """Euclidean distances from vertex ``v`` to the vertices ``others``."""
    return np.linalg.norm(geo.verts[others] - geo.verts[v], axis=1) if others else np.empty(0)


def _count(tally: dict, reason: str | None, contours: dict) -> None:
    """Add one verdict (its rejection reason, if any, and the contours it measured) to ``tally``."""
    for key, n in contours.items():
        tally["contours"][key] += n
    if reason:
        tally["rejected"][reason] += 1


def _candidate(geo: _Geometry, f: _Fields, v: int) -> dict:
    """The candidate's own record fields (its vertex, position and S)."""
    return {"x": geo.verts[v, 0], "y": geo.verts[v, 1], "z": geo.verts[v, 2], "vertex": v, "S": f.S[v]}


def _nearest(geo: _Geometry, v: int, others: list[int], accepted: list) -> float:
    """Distance from vertex ``v`` to the nearest of the ``others`` candidates and accepted defects."""
    near = np.concatenate([geo.verts[others].reshape(-1, 3)] + [p[None] for p, _, _ in accepted])
    return float(np.min(np.linalg.norm(near - geo.verts[v], axis=1))) if len(near) else np.inf


def _verdict(mesh, geo: _Geometry, f: _Fields, st: _Settings, search: _Search, v: int, radii: list[float],
             dmin: float, zeros: list[int] = ()) -> tuple[str | None, dict, dict]:
    """Measure candidate ``v`` on ``radii``; accept it (a row refined within ``dmin / 2``, or placed
    among the dip's ``zeros`` its contour encloses, :func:`_among_zeros`; appended to ``search``)
    or say why not. Returns the reason (None: accepted), the candidate's record and the contour
    counts of the measurement."""
    rec = _candidate(geo, f, v)
    res = _measure(geo, f, st, v, radii)
    at_rim = res is AT_RIM
    res = None if at_rim else res
    contours = {}
    if res is not None:
        contours = {res["contour"]: 1, "shrunk": int(res["shrunk"]), "k_from_vertices": int(res["k_from_vertices"])}
    reason = RIM_REASON if at_rim else _rejection(res, st)
    if reason is None:
        used, row = _accept(mesh, geo, f, st, v, res, dmin, search.fit)
        row.update(_among_zeros(mesh, geo, f, v, zeros, row))
        contours["k_from_vertices"] |= int(used["k_from_vertices"])  # the recentred contour counts too
        here = np.array([row["x"], row["y"], row["z"]])
        rec.update(x=row["x"], y=row["y"], z=row["z"])
        if any(np.linalg.norm(p - here) < SAME_DEFECT_PER_AVERAGING * st.avg_radius for p, _, _ in search.accepted):
            reason = "same defect"  # two candidates of different dips whose contours found one defect
        else:
            search.accepted.append((here, row["contour_radius"], search.comp[v]))
            search.rows.append(row)
    if reason:
        logger.debug("rejected candidate at vertex %d (S=%.3g): %s", v, f.S[v], reason)
    return reason, _record(rec, res, reason or ""), contours


def _among_zeros(mesh, geo: _Geometry, f: _Fields, v: int, zeros: list[int], row: dict) -> dict:
    """The position of an |m| ≥ 1 defect whose contour now encloses the Q-zeros of its dip that the
    first contour ran through (``zeros``, :func:`_clear_of_zeros`; within the inner edge of
    :data:`CONTOUR_CLEAR_BAND`): their mean with ``v``, on the surface (``refine`` ``"zeros"``); else
    nothing. Such a defect split into these zeros (a +1 aster under a z-PSF into two +½ 13–14 µm
    apart): the mean lay 2.7 / 3.0 µm from a review's two poles, the model fit around the lowest
    zero 2.9 / 10.2 µm. Zeros inside the first contour are a core the model fit reads better."""
    inside = [u for u in zeros if np.linalg.norm(geo.verts[u] - geo.verts[v]) < CONTOUR_CLEAR_BAND[0] * row["contour_radius"]]
    if not inside or abs(row["charge_rounded"]) < 1:
        return {}
    ids = [v, *inside]
    centre = geo.verts[ids].mean(axis=0)
    ball, _ = geodesic_ball(geo.graph, v, float(np.max(_distances(geo, v, inside))) + 2 * geo.h)
    point = closest_point_local(mesh, centre, ball)
    vv = int(ball[np.argmin(np.linalg.norm(geo.verts[ball] - point, axis=1))])
    return {"x": point[0], "y": point[1], "z": point[2], "vertex": vv, "S": float(f.S[vv]), "refine": "zeros",
            "shift": float(np.linalg.norm(point - geo.verts[v])), "fit_radius": math.nan,  # no fit placed it
            "fit_residual": math.nan, "fit_scatter": math.nan, "fit_uncertainty": math.nan}


def _measure(geo: _Geometry, f: _Fields, st: _Settings, v: int, radii: list[float]) -> dict | None:
    """The charge on the first contour radius whose median S reaches the floor (else the last
    tried); None or :data:`AT_RIM` when no contour fits (:func:`_charge`)."""
    res = None
    for r_c in radii:
        res = _charge(geo, f, st, v, r_c)
        if res is None or res is AT_RIM or res["contour_S"] >= res["s_floor"]:
            break
    return res


def _record(rec: dict, res: dict | None, reason: str) -> dict:
    """One candidate record (JSON-serialisable, :data:`CANDIDATE_COLUMNS`)."""
    keys = ("charge", "charge_rounded", "contour_S", "s_floor", "max_step_deg", "step_limit_deg",
            "n_contour", "contour", "contour_radius")
    out = {k: float(rec[k]) for k in ("x", "y", "z", "S")}
    out["vertex"] = int(rec["vertex"])
    for k in keys:
        val = None if res is None else res[k]
        out[k] = val if isinstance(val, str) or val is None else (int(val) if k == "n_contour" else float(val))
    out["n_contour"] = out["n_contour"] or 0
    out["contour"] = out["contour"] or ""
    out.update(accepted=not reason, reason=reason)
    return out


def _accept(mesh, geo: _Geometry, f: _Fields, st: _Settings, v: int, res: dict, dmin: float,
            fit: dict) -> tuple[dict, dict]:
    """Refine an accepted candidate's position and re-measure its charge there: the measurement
    the row takes (``res`` or the recentred contour's) and the defect row."""
    h = geo.h
    rho = max(min(fit["fit_radius"], 0.5 * dmin), 3 * h)
    # a given fit radius is also the reach (as before the default widened)
    reach = rho if fit["fit_given"] else max(min(rho, SHIFT_PER_AVERAGING * st.avg_radius), 3 * h)
    point, method, (residual, scatter, uncertainty) = _refine(
        mesh, geo.graph, geo.verts, geo.normals, f, v, res["charge_rounded"], rho, h, fit["refine"], fit["fit_exclude"],
        fit["fit_harmonic"], reach)
    # final vertex = nearest to the refined point; recentre the contour when it moved
    ball_idx, _ = geodesic_ball(geo.graph, v, max(4 * h, np.linalg.norm(point - geo.verts[v]) + 2 * h))
    vv = int(ball_idx[np.argmin(np.linalg.norm(geo.verts[ball_idx] - point, axis=1))])
    if vv != v:
        res2 = _charge(geo, f, st, vv, res["contour_radius"])
        if res2 is not None and res2 is not AT_RIM and res2["charge_rounded"] == res["charge_rounded"]:
            res = res2
    return res, {
        "x": point[0], "y": point[1], "z": point[2], "vertex": vv, "S": float(f.S[vv]),
        **{key: res[key] for key in ("charge", "charge_winding", "charge_curvature", "charge_rounded",
                                     "n_contour", "contour_S", "max_step_deg", "contour_radius")},
        "refine": method, "shift": float(np.linalg.norm(point - geo.verts[v])),
        "fit_radius": float(rho) if fit["refine"] != "none" else math.nan, "fit_residual": residual,
        "fit_scatter": scatter, "fit_uncertainty": uncertainty,
    }


#: What :func:`_charge` returns when no contour fits between the candidate and the open rim.
AT_RIM = {"at_rim": True}
#: Largest fraction of the surface's vertices a defect's contour may enclose: beyond it the
#: contour's "inside" holds most of the surface, and its charge is the sum of the defects there.
MAX_ENCLOSED_FRACTION = 0.5
#: The rejection of such a contour.
ENCLOSES_REASON = "contour encloses most of the surface"
#: Rejection reason of a candidate whose contour would leave the surface (an open rim).
RIM_REASON = "contour leaves the surface"


def _charge(geo: _Geometry, f: _Fields, st: _Settings, v: int, r_c: float) -> dict | None:
    """Winding + curvature charge on a closed contour of geodesic radius ``r_c`` around vertex ``v``.

    The contour is the boundary loop of the geodesic ball (``loop``), else the ring of vertices
    at the radius sorted by angle (``ring``); when it has fewer vertices than
    :func:`steps_needed` (a coarse mesh), a circle sampled in ``v``'s tangent plane and projected
    onto the surface (``circle``, :func:`_circle_contour`). Shrunk to stay off a mesh boundary;
    :data:`AT_RIM` when the shrunk contour would be smaller than min(3 edges, ``avg_radius``)
    (a contour that leaves the surface encloses no defect and no charge).
    """
    h = geo.h
    idx, dist = geodesic_ball(geo.graph, v, 1.5 * r_c + 2 * h)
    shrunk = bool(geo.boundary[idx[dist < r_c + h]].any())
    if shrunk:  # shrink the contour so it stays off the mesh boundary
        r_c = 0.9 * float(dist[geo.boundary[idx]].min()) - h
        if r_c < min(3 * h, st.avg_radius):
            return AT_RIM
    inside = np.zeros(len(geo.verts), dtype=bool)
    inside[idx[dist < r_c + 0.5 * h]] = True  # loop vertices then lie at r_c on average (ring: r_c ± h)
    # unique faces: vf lists a face once per incident ball vertex, and duplicated border edges
    # would read as a pinched boundary
    loop, region = boundary_loop(geo.faces, inside, np.unique(geo.vf[idx].indices))
    kind = "loop"
    if loop is not None and len(loop) >= 8:
        enclosed = float(geo.kdA[region].sum() - 0.5 * geo.kdA[loop].sum())  # contour vertices count half
        fraction = len(region) / len(geo.verts) if geo.closed else 0.0
    else:  # non-manifold ball boundary: ring of vertices sorted by angle, ball = enclosed
        loop = angle_sorted_contour(geo.verts, geo.verts[v], geo.normals[v], idx, dist, r_c, 2 * h)
        enclosed = float(geo.kdA[idx[dist < r_c]].sum())
        fraction = float(np.sum(dist < r_c)) / len(geo.verts) if geo.closed else 0.0
        kind = "ring"
    n_pts = steps_needed(r_c, st.avg_radius)
    if len(loop) < n_pts * (2 if kind == "ring" else 1):  # a ring is a band about two vertices wide
        return _circle_contour(geo, f, st, v, r_c, idx, 2 * n_pts, shrunk)
    disc = st.k_from_contour and _is_disc(geo, region if kind == "loop" else idx[dist < r_c])
    pts = geo.verts[loop]
    if st.winding_field == "average":
        dirs = f.navg[loop]
    else:
        dirs = f.ddir[f.dtree.query(pts)[1]]
    if f.count is not None:
        n_dir = float(np.median(f.count[loop]))
    elif f.dtree is not None:
        n_dir = float(np.median(f.dtree.query_ball_point(pts, st.avg_radius, return_length=True)))
    else:
        n_dir = None
    return _winding_result(dirs, geo.normals[loop], f.S[loop], n_dir, pts, enclosed, st,
                           {"contour": kind, "contour_radius": float(r_c), "shrunk": shrunk,
                            "enclosed_fraction": fraction}, disc)


def _is_disc(geo: _Geometry, region: np.ndarray) -> bool:
    """Whether the faces with all three vertices in ``region`` (vertex indices) form a topological
    disc (Euler characteristic V − E + F = 1): Gauss–Bonnet on one contour then gives their ∫K.
    A contour round a tube or a hole of a porous wall encloses no disc."""
    inside = np.zeros(len(geo.verts), dtype=bool)
    inside[region] = True
    faces = geo.faces[np.unique(geo.vf[region].indices)]
    faces = faces[inside[faces].all(axis=1)]
    if not len(faces):
        return False
    return trimesh.Trimesh(geo.verts, faces, process=False).euler_number == 1  # counts referenced vertices


def _circle_contour(geo: _Geometry, f: _Fields, st: _Settings, v: int, r_c: float, ball: np.ndarray,
                    n_pts: int, shrunk: bool) -> dict | None:
    """Charge on ``n_pts`` points of a circle of radius ``r_c`` around vertex ``v`` (coarse meshes).

    The points are placed in ``v``'s tangent plane and projected onto the closest surface
    triangle of the ball; the normal there is the barycentric mean of the vertex normals. The
    averaged field at each point is recomputed from the raw directors within ``avg_radius`` (the
    order table's own average, :func:`nemo.order.lift_q`), or interpolated from the order table's
    Q-tensor without raw directors. The enclosed curvature weights each ball vertex by the
    fraction of its cell inside the circle (a linear ramp one edge length wide).
    """
    x0 = geo.verts[v]
    t1, t2 = tangent_basis(geo.normals[v])
    phi = 2 * np.pi * np.arange(n_pts) / n_pts
    target = x0 + r_c * (np.cos(phi)[:, None] * t1 + np.sin(phi)[:, None] * t2)
    fids = np.unique(geo.vf[ball].indices)
    tri = geo.verts[geo.faces[fids]]  # (T, 3, 3)
    n_t = len(tri)
    cp = trimesh.triangles.closest_point(np.tile(tri, (n_pts, 1, 1)), np.repeat(target, n_t, axis=0))
    j = np.linalg.norm(cp - np.repeat(target, n_t, axis=0), axis=1).reshape(n_pts, n_t).argmin(axis=1)
    pts = cp.reshape(n_pts, n_t, 3)[np.arange(n_pts), j]
    corner = geo.faces[fids[j]]  # (P, 3)
    bary = trimesh.triangles.points_to_barycentric(tri[j], pts)
    nrm = np.einsum("pk,pkj->pj", bary, geo.normals[corner])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    dirs, s_pts, n_dir = _field_at_points(geo, f, st, pts, nrm, corner, bary)
    r_e = float(np.mean(np.linalg.norm(pts - x0, axis=1)))
    w = np.clip(0.5 + (r_e - np.linalg.norm(geo.verts[ball] - x0, axis=1)) / geo.h, 0.0, 1.0)
    enclosed = float(np.sum(w * geo.kdA[ball]))
    disc = st.k_from_contour and _is_disc(geo, ball[np.linalg.norm(geo.verts[ball] - x0, axis=1) < r_e])
    fraction = float(np.sum(np.linalg.norm(geo.verts[ball] - x0, axis=1) < r_e)) / len(geo.verts) if geo.closed else 0.0
    return _winding_result(dirs, nrm, s_pts, n_dir, pts, enclosed, st,
                           {"contour": "circle", "contour_radius": float(r_c), "shrunk": shrunk,
                            "enclosed_fraction": fraction}, disc)


def _field_at_points(geo: _Geometry, f: _Fields, st: _Settings, pts: np.ndarray, nrm: np.ndarray,
                     corner: np.ndarray, bary: np.ndarray) -> tuple[np.ndarray, np.ndarray, float | None]:
    """Director, S and directors per disc at P surface points (on triangles ``corner``, (P, 3)).

    With raw directors around every point: their tangential Q-average within ``avg_radius``
    (as :func:`nemo.order.order` does at vertices), or the nearest raw director for
    ``winding_field="directors"``. Otherwise the barycentric interpolation of the order table's
    Q-tensor ``S (n nᵀ − ½ P)``, which is a continuous field with the same zeros.

    Returns
    -------
    dirs : ndarray, shape (P, 3)
    s_pts : ndarray, shape (P,)
    n_dir : float or None
        Median number of raw directors per averaging disc (None when unknown).
    """
    n_pts = len(pts)
    if f.dtree is not None:
        lens = f.dtree.query_ball_point(pts, st.avg_radius, return_length=True)
        if lens.min() > 0:
            lists = f.dtree.query_ball_point(pts, st.avg_radius)
            flat = np.concatenate([np.asarray(a, dtype=np.int64) for a in lists])  # a few dozen points
            q6 = np.zeros((n_pts, 6))
            np.add.at(q6, np.repeat(np.arange(n_pts), lens), lift_q(f.ddir[flat], f.dnrm[flat]))
            s_pts, dirs = tangential_eig(q6 / lens[:, None], nrm)
            if st.winding_field == "directors":
                dirs = f.ddir[f.dtree.query(pts)[1]]
            return dirs, s_pts, float(np.median(lens))
    qv = f.S[corner][..., None] * lift_q(f.navg[corner].reshape(-1, 3),
                                         geo.normals[corner].reshape(-1, 3)).reshape(n_pts, 3, 6)
    s_pts, dirs = tangential_eig(np.einsum("pk,pkc->pc", bary, qv), nrm)
    n_dir = None
    if f.count is not None:
        n_dir = float(np.median(np.einsum("pk,pk->p", bary, f.count[corner])))
    elif f.dtree is not None:
        n_dir = float(np.median(f.dtree.query_ball_point(pts, st.avg_radius, return_length=True)))
    return dirs, s_pts, n_dir


def _winding_result(dirs: np.ndarray, nrm: np.ndarray, s_pts: np.ndarray, n_dir: float | None,
                    pts: np.ndarray, enclosed: float, st: _Settings, extra: dict, disc: bool = True) -> dict | None:
    """Winding, charge and acceptance diagnostics of one closed contour of L points.

    ``dirs``, ``nrm``, ``pts``: (L, 3) directors, normals and positions in contour order;
    ``s_pts``: (L,) S on the contour; ``n_dir``: directors per averaging disc (None: unknown);
    ``enclosed``: ∫K dA of the vertices inside the contour (used unless ``st.k_from_contour`` and
    the contour encloses a ``disc``).
    """
    dirs = project_tangent(dirs, nrm)
    if len(dirs) < 8 or not np.all(np.isfinite(dirs)):
        return None
    steps = winding_steps(dirs, nrm, exact=st.exact)
    if not np.all(np.isfinite(steps)):  # two successive normals opposite: no transport between them
        return None
    wind = float(steps.sum() / (2 * math.pi))
    on_contour = contour_curvature(pts, nrm) if st.k_from_contour and disc else None
    kterm = (enclosed if on_contour is None else on_contour) / (2 * math.pi)
    charge = wind + (kterm if st.curvature_correction else 0.0)
    length = float(np.linalg.norm(pts - np.roll(pts, -1, axis=0), axis=1).sum())
    floor = st.s_ordered
    if n_dir is not None:  # independent averaging discs along the contour: length / diameter
        floor = max(floor, noise_floor(n_dir, length / (2 * st.avg_radius)))
    return {
        "charge": charge, "charge_winding": wind, "charge_curvature": kterm,
        "charge_rounded": float(np.round(2 * charge) / 2), "n_contour": len(dirs),
        "contour_S": float(np.nanmedian(s_pts)), "s_floor": float(floor),
        "max_step_deg": float(np.degrees(np.abs(steps).max())), "step_limit_deg": step_limit_deg(len(dirs)),
        "k_from_vertices": st.k_from_contour and on_contour is None, **extra,
    }


def _refine(mesh, graph, verts, normals, f: _Fields, v: int, m: float, rho: float, h: float,
            method: str, r_in: float, harmonic: bool, reach: float) -> tuple[np.ndarray, str, tuple[float, float, float]]:
    """Sub-vertex position of the defect near vertex v from the directors within ``rho``, at most
    ``reach`` from it; the averaged field's zero from within ``reach`` (module doc); and the model
    fit's residual and its scatter (degrees, :func:`_model_residual`) and the core's standard error
    (:func:`_core_uncertainty`), NaN where no model placed it."""
    x0 = verts[v]
    unfitted = (math.nan, math.nan, math.nan)
    if method == "none":
        return x0, "vertex", unfitted
    t1, t2 = tangent_basis(normals[v])
    idx, dist = geodesic_ball(graph, v, rho + 2 * h)
    core, name, residual = None, "vertex", unfitted
    if method == "model" and f.dtree is not None:
        (core, *residual), name = _model_core(f, x0, t1, t2, m, rho, r_in, harmonic, reach), "model"
    if core is None and len(idx[dist < reach]) >= 6 and abs(m) == 0.5:
        core, name = _q_core(f, verts, idx[dist < reach], x0, t1, t2, reach), "q"
    if core is None:
        return x0, "vertex", unfitted
    p = x0 + core[0] * t1 + core[1] * t2
    return closest_point_local(mesh, p, idx), name, tuple(residual) if name == "model" else unfitted


def _model_core(f: _Fields, x0: np.ndarray, t1: np.ndarray, t2: np.ndarray, m: float, rho: float, r_in: float,
                harmonic: bool, reach: float) -> tuple[np.ndarray | None, float, float, float]:
    """Core (ξ, η) in the tangent frame at ``x0`` of the defect model fitted to the raw directors within
    ``rho`` (fit, re-centre the window on the fitted core, fit again), or None where it lies farther than
    ``reach`` from ``x0``; and the residual of the fit that placed it, its scatter (:func:`_model_residual`)
    and the core's standard error (:func:`_core_uncertainty`)."""
    centre, found, residual = x0, None, (math.nan, math.nan, math.nan)
    for _ in range(2):
        j = np.asarray(f.dtree.query_ball_point(centre, rho), dtype=np.int64)
        if r_in > 0:
            j = j[np.linalg.norm(f.dpos[j] - centre, axis=1) >= r_in]
        if len(j) < 12:
            break
        rel = f.dpos[j] - x0
        c0 = (centre - x0) @ np.column_stack([t1, t2])
        d = f.ddir[j]
        theta = np.arctan2(d @ t2, d @ t1)
        fitted = _fit_defect_model(rel @ t1 - c0[0], rel @ t2 - c0[1], theta, np.clip(f.dcoh[j], 0.05, None), m,
                                   rho, harmonic, residual=True)
        if fitted is None or np.hypot(*(fitted[0] + c0)) > reach:
            break
        found, residual = fitted[0] + c0, fitted[1:]
        centre = x0 + found[0] * t1 + found[1] * t2
    return found, *residual


def _q_core(f: _Fields, verts: np.ndarray, sel: np.ndarray, x0: np.ndarray, t1: np.ndarray, t2: np.ndarray,
            rho: float) -> np.ndarray | None:
    """Core (ξ, η) of a ±½ defect where the averaged Q field, linearised around ``x0``, vanishes, or None."""
    rel = verts[sel] - x0
    nv = f.navg[sel]
    th = np.arctan2(nv @ t2, nv @ t1)
    q = f.S[sel, None] * np.column_stack([np.cos(2 * th), np.sin(2 * th)])
    core = _linear_q_zero(rel @ t1, rel @ t2, q)
    return core if core is not None and np.hypot(*core) < 0.5 * rho else None


def refine_with_directors(
    mesh: trimesh.Trimesh,
    defects_df: pd.DataFrame,
    order_df: pd.DataFrame,
    directors_df: pd.DataFrame,
    intensity: np.ndarray,
    director_params: dict,
    fraction: float = 0.5,
    seed: int | None = 0,
    fit_radius: float | None = None,
    **find_kwargs,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Second pass of :func:`find_defects` with extra directors around the first-pass defects.

    The random subset of patch centres leaves only a few directors within the fit radius of a
    core, which limits how precisely the defect model can be fitted. This measures directors at
    ``fraction`` of the vertices within the fit radius of each defect (with the same parameters
    as the original directors) and finds the defects again from both sets.

    Parameters
    ----------
    mesh : trimesh.Trimesh
    defects_df : DataFrame
        First-pass result of :func:`find_defects` (its ``attrs["parameters"]`` give the fit radius).
    order_df, directors_df : DataFrame
        The tables the first pass used.
    intensity : ndarray, shape (N,)
        The peeled layer the directors were measured on.
    director_params : dict
        Keyword arguments of :func:`nemo.directors.directors` used for ``directors_df``
        (``patch_radius``/``patch_k``, ``pixel``, ``sigma``, ``frames``).
    fraction : float
        Fraction in (0, 1] of the vertices near each defect that get a director.
    seed : int, optional
        Seed of the subset.
    fit_radius : float, optional
        Neighbourhood radius of every defect; default each defect's own fit radius (the table's
        ``fit_radius``), else the first pass's (its parameters), else :data:`FIT_PER_AVERAGING` ×
        the averaging radius.
    **find_kwargs
        Passed to :func:`find_defects` (the same as for the first pass).

    Returns
    -------
    defects : DataFrame
        Second-pass defects.
    extra : DataFrame
        The extra directors (directors schema).
    """
    from nemo.directors import directors

    if not 0 < fraction <= 1:
        raise NemoError(f"the refinement fraction must be in (0, 1], got {fraction}")
    if len(defects_df) == 0:
        return defects_df, directors_df.iloc[:0]
    params = defects_df.attrs.get("parameters", {})
    rho = fit_radius or params.get("fit_radius")
    if not rho:
        avg = find_kwargs.get("avg_radius") or params.get("avg_radius")
        if not avg:
            raise NemoError("refinement needs the fit radius or the averaging radius of the order table")
        rho = FIT_PER_AVERAGING * float(avg)
    # each defect's own fit radius (capped at half the distance to its nearest other dip), else rho
    own = defects_df.get("fit_radius", pd.Series(np.nan, index=defects_df.index)).to_numpy(np.float64)
    radii = np.where(np.isfinite(own) & (fit_radius is None), own, float(rho))
    near = cKDTree(np.asarray(mesh.vertices)).query_ball_point(defects_df[["x", "y", "z"]].to_numpy(), radii)
    near = np.setdiff1d(np.unique(np.concatenate([np.asarray(v, dtype=np.int64) for v in near])),
                        directors_df["vertex"].to_numpy())
    if fraction < 1:
        near = np.sort(np.random.default_rng(seed).choice(near, size=int(round(fraction * len(near))),
                                                          replace=False))
    keys = ("patch_radius", "patch_k", "pixel", "sigma", "frames")
    extra = directors(mesh, intensity, centres=near, **{k: director_params[k] for k in keys if k in director_params})
    logger.info("refinement: %d extra directors within %.3g-%.3g of %d defect(s)", len(extra), radii.min(), radii.max(),
                len(defects_df))
    refined = find_defects(mesh, order_df, pd.concat([directors_df, extra], ignore_index=True), **find_kwargs)
    if len(refined):  # read on the first pass's directors: the extra ones crowd the defects
        _, _, coherency, _, tree = _director_fields(mesh, directors_df, 1e-3 * float(np.mean(mesh.edges_unique_length)))
        refined["coherency"] = _local_coherency(tree, coherency, refined)
    return refined, extra
