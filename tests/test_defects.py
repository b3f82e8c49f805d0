"""Defect localisation and curvature-corrected charge against analytic director fields.

Fields with known defects are built directly on meshes (no imaging): the paper's stereographic
construction ψ = Σ m_k arg(w − w_k) lifted to spheres (icospheres and marching-cubes spheres),
and θ = Σ m_k atan2(y − y_k, x − x_k) on a planar mesh. The S field comes from a small
reference tangential Q-average written here (method note §6), independent of nemo.order.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
import scipy.sparse as sp
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation
from skimage.measure import marching_cubes
from sparse_fields import close_pair, stereo_field

from nemo.defects import (
    CANDIDATE_COLUMNS,
    FIT_MAX_PER_SIZE,
    FIT_PER_AVERAGING,
    SHIFT_PER_AVERAGING,
    candidate_table,
    contour_curvature,
    find_defects,
    noise_floor,
    step_limit_deg,
    winding_steps,
)
from nemo.errors import NemoError, NemoWarning
from nemo.geometry import edge_graph, geodesic_ball

TETRA = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float) / math.sqrt(3)
OCTA = np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0], [0, 0, -1]], float)


# ------------------------------------------------------------------------------------------------
# analytic fields and meshes


stereo_director = stereo_field  # ψ = Σ m_k arg(w − w_k) lifted (tests/sparse_fields.py)


def rotated(dirs: np.ndarray, seed: int) -> np.ndarray:
    """A random rotation of the defect set that keeps every defect away from the south pole
    (the stereographic chart's point at infinity)."""
    rng = np.random.default_rng(seed)
    while True:
        out = dirs @ Rotation.random(random_state=rng).as_matrix().T
        if out[:, 2].min() > -0.9:
            return out


def mc_sphere(radius: float, step: float) -> trimesh.Trimesh:
    """Sphere about the origin reconstructed by marching cubes (off-grid centre)."""
    off = np.array([0.3137, 0.2718, 0.1414]) * step
    half = radius + 3 * step
    ax = np.arange(-half, half + step / 2, step)
    z, y, x = np.meshgrid(ax, ax, ax, indexing="ij")
    vol = radius - np.sqrt((x - off[0]) ** 2 + (y - off[1]) ** 2 + (z - off[2]) ** 2)
    v, f, _, _ = marching_cubes(vol, 0.0, spacing=(step,) * 3)
    mesh = trimesh.Trimesh(v[:, ::-1] - half - off, f, process=False)
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def grid_mesh(half: float, h: float) -> trimesh.Trimesh:
    """Planar square mesh in z = 0 with +z normals."""
    ax = np.arange(-half, half + h / 2, h)
    n = len(ax)
    x, y = np.meshgrid(ax, ax, indexing="xy")
    v = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="xy")
    a = (j * n + i).ravel()
    f = np.vstack([np.column_stack([a, a + 1, a + n + 1]), np.column_stack([a, a + n + 1, a + n])])
    return trimesh.Trimesh(v, f, process=False)


def sample_directors(mesh, n_dir, field_fn, rng, noise_deg=0.0) -> pd.DataFrame:
    idx = rng.choice(len(mesh.vertices), n_dir, replace=False)
    pos = np.asarray(mesh.vertices)[idx]
    normal = np.asarray(mesh.vertex_normals)[idx]
    n = field_fn(pos)
    n = n - (n * normal).sum(1)[:, None] * normal
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    if noise_deg:
        ang = np.radians(noise_deg) * rng.standard_normal(len(idx))
        n = np.cos(ang)[:, None] * n + np.sin(ang)[:, None] * np.cross(normal, n)
    return pd.DataFrame({"vertex": idx, "x": pos[:, 0], "y": pos[:, 1], "z": pos[:, 2],
                         "nx": n[:, 0], "ny": n[:, 1], "nz": n[:, 2], "coherency": np.ones(len(idx))})


def q_average(mesh, ddf: pd.DataFrame, radius: float) -> pd.DataFrame:
    """Reference tangential Q-average at every vertex (lift, average, project, de-trace)."""
    verts, normals = np.asarray(mesh.vertices), np.asarray(mesh.vertex_normals)
    pos = ddf[["x", "y", "z"]].to_numpy()
    n = ddf[["nx", "ny", "nz"]].to_numpy()
    pairs = cKDTree(pos).sparse_distance_matrix(cKDTree(verts), radius, output_type="coo_matrix")
    a = sp.csr_matrix((np.ones_like(pairs.data), (pairs.col, pairs.row)), shape=(len(verts), len(pos)))
    cnt = np.maximum(np.asarray(a.sum(1)).ravel(), 1)
    q = (a @ np.einsum("ni,nj->nij", n, n).reshape(len(pos), 9)).reshape(-1, 3, 3) / cnt[:, None, None]
    proj = np.eye(3)[None] - np.einsum("ni,nj->nij", normals, normals)
    q = proj @ q @ proj
    q = q - 0.5 * np.trace(q, axis1=1, axis2=2)[:, None, None] * proj
    w, vec = np.linalg.eigh(q)
    nav = vec[:, :, -1]
    return pd.DataFrame({"vertex": np.arange(len(verts)), "S": 2 * w[:, -1],
                         "nx": nav[:, 0], "ny": nav[:, 1], "nz": nav[:, 2]})


def match(df: pd.DataFrame, truth: np.ndarray) -> np.ndarray:
    """Distance from each truth point to the nearest reported defect, shape (K,)."""
    p = df[["x", "y", "z"]].to_numpy()
    return np.linalg.norm(truth[:, None] - p[None], axis=2).min(axis=1)


def sphere_case(radius, step, dirs, charges, n_dir, avg, seed=0, noise=0.0, mesh=None):
    mesh = mc_sphere(radius, step) if mesh is None else mesh
    rng = np.random.default_rng(seed)
    ddf = sample_directors(mesh, n_dir, lambda p: stereo_director(p, dirs, charges), rng, noise)
    return mesh, ddf, q_average(mesh, ddf, avg)


@pytest.fixture(scope="module")
def sphere60():
    return mc_sphere(60.0, 1.5)


# ------------------------------------------------------------------------------------------------
# building blocks


@pytest.mark.parametrize("m", [0.5, -0.5, 1.0, -1.0, 1.5])
def test_winding_exact_vs_small_angle(m):
    """Exact step angles give the winding exactly even on a coarse contour; the paper's
    small-angle form (sin Δθ) underestimates it."""
    n_pts = 10
    phi = np.linspace(0, 2 * np.pi, n_pts, endpoint=False)
    th = m * phi + 0.3
    dirs = np.column_stack([np.cos(th), np.sin(th), np.zeros(n_pts)])
    normals = np.tile([0.0, 0.0, 1.0], (n_pts, 1))
    exact = winding_steps(dirs, normals).sum() / (2 * np.pi)
    small = winding_steps(dirs, normals, exact=False).sum() / (2 * np.pi)
    assert exact == pytest.approx(m, abs=1e-12)
    step = abs(m) * 2 * np.pi / n_pts
    assert small == pytest.approx(m * math.sin(step) / step, rel=1e-9)
    assert abs(small - m) > 1e-3
    # head-tail symmetry: flipping random directors changes nothing
    flip = np.where(np.random.default_rng(0).random(n_pts) < 0.5, -1.0, 1.0)[:, None]
    assert winding_steps(dirs * flip, normals).sum() / (2 * np.pi) == pytest.approx(m, abs=1e-12)


# ------------------------------------------------------------------------------------------------
# planar fields


def test_planar_half_and_integer_defects():
    mesh = grid_mesh(80.0, 1.0)
    pos = np.array([[-30.37, -29.71], [30.23, -30.41], [-29.62, 30.29], [30.44, 29.83]])  # off-grid
    charges = [0.5, -0.5, 1.0, -1.0]

    def field(p):
        th = sum(m * np.arctan2(p[:, 1] - y, p[:, 0] - x) for m, (x, y) in zip(charges, pos))
        return np.column_stack([np.cos(th), np.sin(th), np.zeros(len(p))])

    rng = np.random.default_rng(3)
    ddf = sample_directors(mesh, 6000, field, rng, noise_deg=5.0)
    df = find_defects(mesh, q_average(mesh, ddf, 10.0), ddf, avg_radius=10.0)
    assert len(df) == 4
    truth = np.column_stack([pos, np.zeros(4)])
    d = np.linalg.norm(df[["x", "y", "z"]].to_numpy()[:, None] - truth[None], axis=2)
    k = d.argmin(axis=1)
    assert sorted(k) == [0, 1, 2, 3]
    assert d.min(axis=1).max() < 0.6  # vertex spacing 1: refinement below the spacing
    np.testing.assert_allclose(df["charge"], np.array(charges)[k], atol=0.02)
    np.testing.assert_array_equal(df["charge_rounded"], np.array(charges)[k])
    np.testing.assert_allclose(df["charge_curvature"], 0.0, atol=1e-9)  # flat: no K term
    assert not df.attrs["euler_check"]["closed"]


def test_ordered_patches_report_no_defect():
    mesh = grid_mesh(60.0, 1.0)
    rng = np.random.default_rng(1)
    for field in (lambda p: np.tile([1.0, 0.0, 0.0], (len(p), 1)),
                  lambda p: np.column_stack([np.cos(0.01 * p[:, 0]), np.sin(0.01 * p[:, 0]), 0 * p[:, 0]])):
        ddf = sample_directors(mesh, 3000, field, rng, noise_deg=10.0)
        df = find_defects(mesh, q_average(mesh, ddf, 10.0), ddf)
        assert len(df) == 0
    # an open spherical cap with a smooth defect-free field (latitude lines around a far axis)
    sph = trimesh.creation.icosphere(subdivisions=5, radius=40.0)
    cap = sph.submesh([np.flatnonzero(sph.triangles_center[:, 2] > 20.0)], append=True)
    ddf = sample_directors(cap, 2000, lambda p: np.cross([1.0, 0.0, 0.0], p), rng, noise_deg=5.0)
    df = find_defects(cap, q_average(cap, ddf, 6.0), ddf)
    assert len(df) == 0


def test_isotropic_field_has_no_confident_defect(sphere60):
    rng = np.random.default_rng(7)
    ddf = sample_directors(sphere60, 3000, lambda p: rng.standard_normal(p.shape), rng)
    odf = q_average(sphere60, ddf, 12.0)
    assert odf["S"].quantile(0.9) < 0.4  # really disordered
    df = find_defects(sphere60, odf, ddf, avg_radius=12.0)
    assert len(df) == 0
    assert df.attrs["parameters"]["rejected"]["disordered contour"] > 0
    # even forcing the paper's fixed threshold, no candidate survives the contour-S test
    df = find_defects(sphere60, odf, ddf, avg_radius=12.0, s_threshold=0.3)
    assert len(df) == 0


# ------------------------------------------------------------------------------------------------
# spheres


@pytest.mark.parametrize("seed", [0, 1])
def test_sphere_four_half_defects_random_rotation(sphere60, seed):
    dirs = rotated(TETRA, seed)
    mesh, ddf, odf = sphere_case(60.0, 1.5, dirs, [0.5] * 4, 4000, 15.0, seed=seed, noise=5.0, mesh=sphere60)
    df = find_defects(mesh, odf, ddf, avg_radius=15.0)
    assert len(df) == 4
    err = match(df, 60.0 * dirs)
    assert err.max() < 0.75, err  # vertex spacing ≈ 1.2 µm
    np.testing.assert_allclose(df["charge"], 0.5, atol=0.05)
    assert (df["charge_rounded"] == 0.5).all()
    check = df.attrs["euler_check"]
    assert check["closed"] and check["euler_characteristic"] == 2 and check["matches"]
    assert check["sum_charge"] == pytest.approx(2.0, abs=0.05)


def test_the_fit_radius_follows_the_averaging_radius_within_the_surfaces_size(sphere60):
    """The core is fitted within FIT_PER_AVERAGING × the averaging radius (each defect's radius in
    the table), at most FIT_MAX_PER_SIZE × the surface's size but not below the former
    SHIFT_PER_AVERAGING ×; the core stays within reach."""
    dirs = rotated(TETRA, 3)
    mesh, ddf, odf = sphere_case(60.0, 1.5, dirs, [0.5] * 4, 4000, 15.0, seed=3, noise=5.0, mesh=sphere60)
    df = find_defects(mesh, odf, ddf, avg_radius=15.0)
    assert df.attrs["parameters"]["fit_radius"] == pytest.approx(FIT_PER_AVERAGING * 15.0)
    np.testing.assert_allclose(df["fit_radius"], FIT_PER_AVERAGING * 15.0)  # the defects ~114 µm apart: no cap
    assert (df["refine"] == "model").all() and (df["shift"] <= SHIFT_PER_AVERAGING * 15.0).all()
    assert match(df, 60.0 * dirs).max() < 0.75
    size = math.sqrt(mesh.area / (4 * math.pi))
    wide = find_defects(mesh, odf, ddf, avg_radius=50.0)  # 1.125 × 50 is beyond 0.75 × the size
    assert wide.attrs["parameters"]["fit_radius"] == pytest.approx(FIT_MAX_PER_SIZE * size)
    assert len(wide) == 4 and np.allclose(wide["fit_radius"], FIT_MAX_PER_SIZE * size)
    # an object about as small as its averaging radius keeps the former 0.75 × (the cap never narrows it)
    small = find_defects(mesh, odf, ddf, avg_radius=70.0)
    assert small.attrs["parameters"]["fit_radius"] == pytest.approx(SHIFT_PER_AVERAGING * 70.0)
    given = find_defects(mesh, odf, ddf, avg_radius=15.0, fit_radius=9.0)
    assert given.attrs["parameters"]["fit_radius"] == 9.0 and (given["fit_radius"] == 9.0).all()


def test_a_defect_where_the_fibres_are_faint_is_told_by_its_coherency(sphere60):
    """``coherency``: the directors' median coherency within the contour radius over the surface's.
    The four +½ of a tetrahedron, the directors round one of them faint (coherency 0.3 against
    0.9): that defect reads 1/3, the others 1."""
    dirs = rotated(TETRA, 3)
    mesh, ddf, odf = sphere_case(60.0, 1.5, dirs, [0.5] * 4, 4000, 15.0, seed=3, noise=5.0, mesh=sphere60)
    pos = ddf[["x", "y", "z"]].to_numpy()
    faint = np.linalg.norm(pos - 60.0 * dirs[0], axis=1) < 40.0
    ddf["coherency"] = np.where(faint, 0.3, 0.9)
    df = find_defects(mesh, odf, ddf, avg_radius=15.0)
    assert len(df) == 4
    at_faint = np.linalg.norm(df[["x", "y", "z"]].to_numpy() - 60.0 * dirs[0], axis=1) < 3.0
    assert at_faint.sum() == 1
    assert df["coherency"][at_faint].iloc[0] == pytest.approx(1 / 3, abs=0.01)
    np.testing.assert_allclose(df["coherency"][~at_faint], 1.0)


def test_a_defect_whose_directors_do_not_follow_the_model_has_a_large_fit_residual(sphere60):
    """``fit_residual``: the RMS of the directors' angles about the fitted model beyond a third of the fit radius
    from the core. The four +½ of a tetrahedron with 5° of director noise read about that noise (4.3-5.2°);
    with the raw directors round one of them scrambled (random tangent directions 6-25 µm from it; the
    averaged order left as it was, so the low S still places a defect there) that defect reads ~50° and
    the others are unchanged. The QC flags a frame above 20° (nemo.summary)."""
    dirs = rotated(TETRA, 3)
    mesh, ddf, odf = sphere_case(60.0, 1.5, dirs, [0.5] * 4, 4000, 15.0, seed=3, noise=5.0, mesh=sphere60)
    clean = find_defects(mesh, odf, ddf, avg_radius=15.0)
    assert (clean["refine"] == "model").all() and clean["fit_residual"].between(3.0, 7.0).all(), clean["fit_residual"]
    pos = ddf[["x", "y", "z"]].to_numpy()
    distance = np.linalg.norm(pos - 60.0 * dirs[0], axis=1)
    near = (distance > 6.0) & (distance < 25.0)
    normal = pos[near] / np.linalg.norm(pos[near], axis=1)[:, None]
    random = np.random.default_rng(0).normal(size=(near.sum(), 3))
    random -= normal * np.sum(random * normal, axis=1)[:, None]
    ddf.loc[near, ["nx", "ny", "nz"]] = random / np.linalg.norm(random, axis=1)[:, None]
    df = find_defects(mesh, odf, ddf, avg_radius=15.0)
    assert len(df) == 4
    scrambled = np.linalg.norm(df[["x", "y", "z"]].to_numpy() - 60.0 * dirs[0], axis=1) < 15.0
    assert scrambled.sum() == 1 and df["fit_residual"][scrambled].iloc[0] > 35.0
    assert df["fit_residual"][~scrambled].between(3.0, 7.0).all()
    # random directors scatter too, but a defect's model is a far worse fit than their neighbours' agreement
    from nemo.summary import QC_MAX_DEFECT_RESIDUAL_DEG, defect_misfit

    excess, _ = defect_misfit(df)
    assert excess[scrambled][0] > QC_MAX_DEFECT_RESIDUAL_DEG and excess[~scrambled].max() < 7.0


def _with_outliers(mesh, ddf: pd.DataFrame, fraction: float, seed: int) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The directors with a random ``fraction`` replaced by random tangent directions, and their Q-average."""
    rng = np.random.default_rng(seed)
    ddf = ddf.copy()
    pick = rng.random(len(ddf)) < fraction
    normal = ddf.loc[pick, ["x", "y", "z"]].to_numpy()
    normal = normal / np.linalg.norm(normal, axis=1)[:, None]
    random = rng.normal(size=normal.shape)
    random -= normal * np.sum(random * normal, axis=1)[:, None]
    ddf.loc[pick, ["nx", "ny", "nz"]] = random / np.linalg.norm(random, axis=1)[:, None]
    return ddf, q_average(mesh, ddf, 15.0)


def test_noisy_directors_read_their_noise_as_scatter_and_sparse_ones_an_uncertain_core(sphere60):
    """``fit_scatter`` (the residual's scatter between neighbouring directors) is independent directors' own
    noise, so noisy directors that follow a defect leave no misfit beyond it: 16 000 directors with 20° of noise
    and 5 % random outliers place every defect within 1.5 µm and read residuals of 21-26° (which failed the frame
    on the residual alone) and a scatter that holds them. ``fit_uncertainty`` (the core's standard error with that
    noise) grows as the directors thin out: on 1 000 of them, with 15° and the outliers, defects 6-12 µm off read
    0.4-1.2 of the fit radius (0.07-0.09 on 16 000). The QC's measure is nemo.summary.defect_misfit."""
    from nemo.summary import QC_MAX_DEFECT_RESIDUAL_DEG, QC_MAX_DEFECT_UNCERTAINTY, defect_misfit

    dirs = rotated(TETRA, 2)
    mesh, ddf, _ = sphere_case(60.0, 1.5, dirs, [0.5] * 4, 16000, 15.0, seed=2, noise=20.0, mesh=sphere60)
    df = find_defects(mesh, *_with_outliers(mesh, ddf, 0.05, 102)[::-1], avg_radius=15.0)
    assert len(df) == 4 and match(df, 60.0 * dirs).max() < 1.5 and (df["refine"] == "model").all()
    assert df["fit_residual"].min() > QC_MAX_DEFECT_RESIDUAL_DEG  # noise, not a misplaced core
    assert df["fit_scatter"].between(18.0, 28.0).all(), df["fit_scatter"]
    excess, uncertainty = defect_misfit(df)
    assert excess.max() < QC_MAX_DEFECT_RESIDUAL_DEG and uncertainty.max() < QC_MAX_DEFECT_UNCERTAINTY
    mesh, ddf, _ = sphere_case(60.0, 1.5, dirs, [0.5] * 4, 1000, 15.0, seed=1, noise=15.0, mesh=sphere60)
    df = find_defects(mesh, *_with_outliers(mesh, ddf, 0.05, 101)[::-1], avg_radius=15.0)
    error = np.linalg.norm(df[["x", "y", "z"]].to_numpy()[:, None] - 60.0 * dirs[None], axis=2).min(axis=1)
    _, uncertainty = defect_misfit(df)
    far = error > 5.0
    assert far.any() and np.all((uncertainty[far] > QC_MAX_DEFECT_UNCERTAINTY) | (df["refine"][far] != "model"))


@pytest.mark.parametrize("sigma_deg", [5.0, 20.0, 35.0, 45.0])
def test_the_scatter_is_the_residual_independent_noise_leaves_even_where_it_wraps(sigma_deg):
    """``_noise_scatter`` on pure independent noise (no misfit): the RMS residual it predicts matches the
    wrapped angles' own RMS within 2.5°, also where the noise wraps (the neighbour differences' RMS read it
    9.5-23° low at 30-45°, a review), and copies of each director (a table written twice) change nothing
    (they read 0 before: each director's nearest neighbour was its copy)."""
    from nemo.defects import _noise_scatter

    rng = np.random.default_rng(int(sigma_deg))
    n = 3000
    xi, eta = rng.uniform(-15.0, 15.0, (2, n))
    delta = np.radians(sigma_deg) * rng.standard_normal(n)
    wrapped = np.degrees(np.sqrt(np.mean((0.5 * np.angle(np.exp(2j * delta))) ** 2)))
    scatter, noise = _noise_scatter(delta, np.ones(n), xi, eta, 15.0)
    assert scatter == pytest.approx(wrapped, abs=2.5) and np.degrees(noise) == pytest.approx(sigma_deg, rel=0.12)
    twice = _noise_scatter(np.r_[delta, delta], np.ones(2 * n), np.r_[xi, xi], np.r_[eta, eta + 1e-3], 15.0)
    assert twice[0] == pytest.approx(scatter, abs=1.5)


def test_the_cores_uncertainty_does_not_depend_on_the_coherency_scale(sphere60):
    """``fit_uncertainty`` with every director's coherency × 0.35 is about the one at 1 (the weights scale the
    residuals, their noise with them): it read 0.07-0.14 against 0.30-0.61 of the fit radius at 0.2, a review.
    The robust fit's loss is not scale-free (smaller residuals fall in its quadratic zone), so the cores move by
    up to ~1 µm and the ratio reads 0.72-0.85, not 1 (about 1 / 0.35 without the weights' scale)."""
    dirs = rotated(TETRA, 4)
    mesh, ddf, odf = sphere_case(60.0, 1.5, dirs, [0.5] * 4, 4000, 15.0, seed=4, noise=15.0, mesh=sphere60)
    one = find_defects(mesh, odf, ddf, avg_radius=15.0)
    low = find_defects(mesh, odf, ddf.assign(coherency=0.35), avg_radius=15.0)
    assert len(one) == len(low) == 4 and one["fit_uncertainty"].between(0.5, 4.0).all(), one["fit_uncertainty"]
    ratio = low["fit_uncertainty"].to_numpy() / one["fit_uncertainty"].to_numpy()
    assert np.all((ratio > 0.6) & (ratio < 1.4)), ratio


def test_sphere_five_plus_one_minus_half(sphere60):
    dirs = rotated(OCTA, 5)
    charges = [-0.5, 0.5, 0.5, 0.5, 0.5, 0.5]
    mesh, ddf, odf = sphere_case(60.0, 1.5, dirs, charges, 6000, 15.0, seed=2, noise=5.0, mesh=sphere60)
    df = find_defects(mesh, odf, ddf, avg_radius=15.0)
    assert len(df) == 6
    d = np.linalg.norm(df[["x", "y", "z"]].to_numpy()[:, None] - 60.0 * dirs[None], axis=2)
    k = d.argmin(axis=1)
    assert sorted(k) == list(range(6))
    assert d.min(axis=1).max() < 1.0
    np.testing.assert_allclose(df["charge"], np.array(charges)[k], atol=0.05)
    assert df.attrs["euler_check"]["matches"]


def test_sphere_two_plus_one(sphere60):
    dirs = rotated(np.array([[0, 0, 1.0], [0, 0, -1.0]]), 11)
    mesh, ddf, odf = sphere_case(60.0, 1.5, dirs, [1.0, 1.0], 4000, 15.0, seed=4, noise=5.0, mesh=sphere60)
    df = find_defects(mesh, odf, ddf, avg_radius=15.0)
    assert len(df) == 2  # an |m| = 1 dip may hold two ±1/2 zeros of the averaged Q: one defect
    assert match(df, 60.0 * dirs).max() < 1.0
    np.testing.assert_allclose(df["charge"], 1.0, atol=0.05)
    assert df.attrs["euler_check"]["matches"]


def test_a_contour_round_most_of_a_small_sphere_is_no_defect():
    """Two +1 poles on a sphere R 20 µm: a contour of geodesic radius 38 µm encloses two thirds of
    the surface (one of 58 µm on a sphere R 20, round a dip between the poles, enclosed both and
    read "+2", which passed the Σ-charge check in an independent review). Such a contour is
    rejected; one of 12 µm finds each +1."""
    from nemo.defects import ENCLOSES_REASON

    mesh = mc_sphere(20.0, 1.0)
    dirs = rotated(np.array([[0, 0, 1.0], [0, 0, -1.0]]), 5)  # off the director field's own axis
    mesh, ddf, odf = sphere_case(20.0, 1.0, dirs, [1.0, 1.0], 1500, 6.0, seed=2, noise=3.0, mesh=mesh)
    wide = find_defects(mesh, odf, ddf, avg_radius=6.0, contour_radius=38.0)
    assert len(wide) == 0
    assert wide.attrs["parameters"]["rejected"][ENCLOSES_REASON] >= 1
    assert ENCLOSES_REASON in set(candidate_table(wide)["reason"])
    df = find_defects(mesh, odf, ddf, avg_radius=6.0, contour_radius=12.0)
    assert len(df) == 2 and match(df, 20.0 * dirs).max() < 1.5
    np.testing.assert_allclose(df["charge"], 1.0, atol=0.05)
    # cut by the image border at z = -12, the surface has a rim: a contour's inside is the side away from
    # it, so a contour of 30 µm round the +1 at the top (over half the vertices) measures it
    keep = mesh.vertices[mesh.faces].mean(axis=1)[:, 2] > -12.0
    cap = trimesh.Trimesh(mesh.vertices, mesh.faces[keep], process=False)
    cap.remove_unreferenced_vertices()
    poles = np.array([[0.05, 0.02, 1.0], [-0.05, -0.02, -1.0]]) / np.sqrt(1.0029)
    cap, ddf, odf = sphere_case(20.0, 1.0, poles, [1.0, 1.0], 1200, 6.0, seed=2, noise=3.0, mesh=cap)
    df = find_defects(cap, odf, ddf, avg_radius=6.0, contour_radius=30.0)
    assert len(df) == 1 and df["charge_rounded"].iloc[0] == 1.0 and match(df, 20.0 * poles[:1]).max() < 1.5


@pytest.mark.parametrize("source", ["contour", "angle-defects", "table"])
def test_curvature_term_on_strongly_curved_sphere(source):
    """R = 30 µm, contour of geodesic radius 20 µm: the winding alone misses
    ∫K dA / 2π = 1 − cos(r/R) ≈ 0.2 of the charge; with the K term it is exact."""
    radius, r_c = 30.0, 20.0
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=radius)  # edge ≈ 1 µm
    dirs = rotated(TETRA, 3)
    _, ddf, odf = sphere_case(radius, None, dirs, [0.5] * 4, 3000, 8.0, seed=1, mesh=mesh)
    k = np.full(len(mesh.vertices), 1.0 / radius**2) if source == "table" else None
    with_k = find_defects(mesh, odf, ddf, curvature=k, avg_radius=8.0, contour_radius=r_c, curvature_source=source)
    without = find_defects(mesh, odf, ddf, curvature=k, avg_radius=8.0, contour_radius=r_c,
                           curvature_correction=False, curvature_source=source)
    assert with_k.attrs["parameters"]["curvature_source"] == source
    assert len(with_k) == len(without) == 4
    # the enclosed Gaussian curvature of each contour (edge-path radius ≥ geodesic radius)
    enclosed = with_k["charge_curvature"].to_numpy()
    r_geo_max = 1.0 - math.cos(r_c / radius)
    assert np.all(enclosed > 0.8 * r_geo_max) and np.all(enclosed < r_geo_max + 0.01)
    np.testing.assert_allclose(with_k["charge"], 0.5, atol=0.05)
    np.testing.assert_allclose(without["charge"], 0.5 - enclosed, atol=0.02)
    assert np.all(np.abs(without["charge"] - 0.5) > 0.15)
    np.testing.assert_allclose(without["charge_winding"], with_k["charge_winding"], atol=1e-12)


def test_contour_curvature_is_the_enclosed_cap_of_a_sphere():
    """Gauss–Bonnet on a geodesic circle of radius r on a sphere of radius R: ∫K dA =
    2π (1 − cos(r / R)) from the circle's own turning; a clockwise circle reads the rest of the
    sphere; a zigzag has no turning to read."""
    radius = 30.0
    for r in (5.0, 15.0, 30.0):
        polar = r / radius
        phi = np.linspace(0, 2 * np.pi, 400, endpoint=False)
        normals = np.column_stack([np.sin(polar) * np.cos(phi), np.sin(polar) * np.sin(phi),
                                   np.full_like(phi, np.cos(polar))])
        points = radius * normals
        cap = 2 * np.pi * (1 - np.cos(polar))
        assert contour_curvature(points, normals) == pytest.approx(cap, rel=1e-3)
        assert contour_curvature(points[::-1], normals[::-1]) == pytest.approx(4 * np.pi - cap, rel=1e-3)
    corners = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.5, 0.9, 0.0]])  # its tangents turn by 120°
    assert contour_curvature(corners, np.tile([0.0, 0.0, 1.0], (3, 1))) is None


@pytest.mark.parametrize(("jitter", "seed"), [(0.3, 0), (0.3, 1), (0.6, 1)])
def test_contour_k_term_keeps_charges_on_a_rough_wall(jitter, seed):
    """A sphere of R 30 µm whose vertices are jittered 0.3-0.6 µm along the radius (edges ≈ 1 µm),
    as a noisy image's wall: the winding's steps carry the rough wall's holonomy. The K term from
    the contour's own turning, measured after the same transport, cancels it exactly (charges ½
    to rounding); the enclosed vertices' angle defects are a second estimate that does not (off
    by 0.05-0.19 here)."""
    radius = 30.0
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=radius)
    rng = np.random.default_rng(seed)
    scale = 1 + jitter / radius * rng.standard_normal(len(mesh.vertices))
    mesh = trimesh.Trimesh(mesh.vertices * scale[:, None], mesh.faces, process=False)
    _, ddf, odf = sphere_case(radius, None, rotated(TETRA, 3), [0.5] * 4, 3000, 8.0, seed=1, mesh=mesh)
    contour = find_defects(mesh, odf, ddf, avg_radius=8.0)
    vertices = find_defects(mesh, odf, ddf, avg_radius=8.0, curvature_source="angle-defects")
    assert len(contour) == len(vertices) == 4
    assert contour.attrs["parameters"]["curvature_source"] == "contour"
    assert contour.attrs["parameters"]["contours"]["k_from_vertices"] == 0
    assert np.abs(contour["charge"] - 0.5).max() < 1e-9
    assert np.abs(vertices["charge"] - 0.5).max() > 0.04


def test_a_recentred_contour_that_takes_the_enclosed_k_is_counted(monkeypatch):
    """An accepted defect's charge is re-measured on a contour around its refined vertex; when that
    contour's K comes from the enclosed vertices (a fallback), contours["k_from_vertices"] counts it
    (it counted the first contour only)."""
    import nemo.defects as D

    radius = 30.0
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=radius)
    _, ddf, odf = sphere_case(radius, None, rotated(TETRA, 3), [0.5] * 4, 3000, 8.0, seed=1, mesh=mesh)
    charge, accept, state = D._charge, D._accept, {"in_accept": False}

    def charge_marking_recentred(*args, **kwargs):
        res = charge(*args, **kwargs)
        if state["in_accept"] and isinstance(res, dict) and "k_from_vertices" in res:
            res = {**res, "k_from_vertices": True}
        return res

    def accept_flagged(*args, **kwargs):
        state["in_accept"] = True
        try:
            return accept(*args, **kwargs)
        finally:
            state["in_accept"] = False

    monkeypatch.setattr(D, "_charge", charge_marking_recentred)
    monkeypatch.setattr(D, "_accept", accept_flagged)
    df = find_defects(mesh, odf, ddf, avg_radius=8.0)
    moved = int((df["shift"] > 0).sum())  # refined off their vertex: recentred where the nearest vertex changed
    counted = df.attrs["parameters"]["contours"]["k_from_vertices"]
    assert len(df) == 4 and 1 <= counted <= moved, (counted, moved)


@pytest.mark.parametrize("m", [0.5, -0.5, 1.0, 0.0])
def test_winding_and_contour_k_cancel_the_holonomy_of_any_loop(m):
    """On a rough closed loop with scattered normals (a noisy mesh's contour), a director that
    turns by 2π(m − 1) relative to the loop's tangent has winding + K term = m exactly: both
    are measured after the same transport between successive normals, so the discrete surface's
    holonomy cancels. Without the transport (the angle about the mean normal) it does not."""
    rng = np.random.default_rng(3)
    n_pts = 60
    phi = 2 * np.pi * np.arange(n_pts) / n_pts
    polar = 0.6 + 0.05 * rng.standard_normal(n_pts)
    normals = np.column_stack([np.sin(polar) * np.cos(phi), np.sin(polar) * np.sin(phi), np.cos(polar)])
    normals += 0.15 * rng.standard_normal((n_pts, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    points = 20.0 * np.column_stack([np.sin(0.6) * np.cos(phi), np.sin(0.6) * np.sin(phi),
                                     np.full(n_pts, np.cos(0.6))]) + 0.3 * rng.standard_normal((n_pts, 3))
    reach = 3  # the chord contour_curvature takes for 60 points
    tangent = np.roll(points, -reach, axis=0) - np.roll(points, reach, axis=0)
    tangent -= np.einsum("ij,ij->i", tangent, normals)[:, None] * normals
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    alpha = 2 * np.pi * (m - 1) * np.arange(n_pts) / n_pts + 0.1 * rng.standard_normal(n_pts) + 0.4
    dirs = np.cos(alpha)[:, None] * tangent + np.sin(alpha)[:, None] * np.cross(normals, tangent)
    k_term = contour_curvature(points, normals)
    assert k_term is not None and abs(k_term - 2 * np.pi * (1 - np.cos(0.6))) > 0.02  # a rough loop
    charge = (winding_steps(dirs, normals).sum() + k_term) / (2 * np.pi)
    assert charge == pytest.approx(m, abs=1e-9)
    nmid = normals + np.roll(normals, -1, axis=0)  # the step about the mean normal, for contrast
    nmid /= np.linalg.norm(nmid, axis=1, keepdims=True)

    def about_mean(vec):
        nxt = np.roll(vec, -1, axis=0)
        nxt = np.where(np.einsum("ij,ij->i", vec, nxt)[:, None] < 0, -nxt, nxt)
        return np.arctan2(np.einsum("ij,ij->i", np.cross(vec, nxt), nmid), np.einsum("ij,ij->i", vec, nxt))

    untransported = 1 + (about_mean(dirs).sum() - about_mean(tangent).sum()) / (2 * np.pi)
    assert abs(untransported - m) > 1e-3


def test_a_contour_with_opposite_successive_normals_is_no_defect():
    """Two successive normals exactly opposite (a folded or flat, two-sided mesh) have no
    transport between them: the step is NaN, and the contour is refused (no NaN charge that every
    rejection test would let through)."""
    from nemo.defects import _Settings, _winding_result

    n_pts = 16
    phi = 2 * np.pi * np.arange(n_pts) / n_pts
    pts = np.column_stack([np.cos(phi), np.sin(phi), np.zeros(n_pts)]) * 10
    nrm = np.tile([0.0, 0.0, 1.0], (n_pts, 1))
    dirs = np.column_stack([np.cos(phi / 2), np.sin(phi / 2), np.zeros(n_pts)])
    st = _Settings(avg_radius=5.0, winding_field="average", curvature_correction=True, exact=True,
                   charge_tolerance=0.15, s_ordered=0.1, k_from_contour=True)
    good = _winding_result(dirs, nrm, np.ones(n_pts), None, pts, 0.0, st, {})
    assert good is not None and good["charge"] == pytest.approx(0.5, abs=1e-9)
    nrm[5] = [0.0, 0.0, -1.0]
    assert np.isnan(winding_steps(dirs, nrm)).sum() == 2
    assert _winding_result(dirs, nrm, np.ones(n_pts), None, pts, 0.0, st, {}) is None


def _torus_half_field(mesh: trimesh.Trimesh, major: float, tube_fraction: float = 0.35) -> pd.DataFrame:
    """An order table on a torus about z: the director turns by half the angle of the constant
    vector x projected on the tangent plane (±½ zeros where x is normal: the outer and inner
    equator at y = 0), S falling to the zeros."""
    v, nm = np.asarray(mesh.vertices), np.asarray(mesh.vertex_normals)
    phi = np.arctan2(v[:, 1], v[:, 0])
    tube = np.arctan2(v[:, 2], np.hypot(v[:, 0], v[:, 1]) - major)
    e_phi = np.column_stack([-np.sin(phi), np.cos(phi), 0 * phi])
    e_tube = np.column_stack([-np.sin(tube) * np.cos(phi), -np.sin(tube) * np.sin(phi), np.cos(tube)])
    normal = np.column_stack([np.cos(tube) * np.cos(phi), np.cos(tube) * np.sin(phi), np.sin(tube)])
    x_t = np.array([1.0, 0.0, 0.0]) - normal[:, :1] * normal
    half = 0.5 * np.arctan2(np.einsum("ij,ij->i", x_t, e_tube), np.einsum("ij,ij->i", x_t, e_phi))
    n = np.cos(half)[:, None] * e_phi + np.sin(half)[:, None] * e_tube
    n -= (n * nm).sum(1)[:, None] * nm
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    s = np.clip(np.linalg.norm(x_t, axis=1) / tube_fraction, 0.02, 1.0)
    return pd.DataFrame({"vertex": np.arange(len(v)), "S": s, "nx": n[:, 0], "ny": n[:, 1], "nz": n[:, 2]})


def test_a_contour_round_the_tube_of_a_torus_takes_the_enclosed_k():
    """A contour wider than a torus's tube (R 30, r 12 µm; contour radius 40 µm) encloses no disc:
    Gauss–Bonnet on that one contour does not give the enclosed ∫K and would read a −½ defect of
    the inner equator as +1. Such contours take the enclosed vertices' K (as `angle-defects`), and
    at the default radius the contour K keeps the four ±½ defects."""
    mesh = trimesh.creation.torus(30.0, 12.0, major_sections=180, minor_sections=72)
    odf = _torus_half_field(mesh, 30.0)
    wide = find_defects(mesh, odf, None, avg_radius=5.0, contour_radius=40.0, refine="none")
    same = find_defects(mesh, odf, None, avg_radius=5.0, contour_radius=40.0, refine="none",
                        curvature_source="angle-defects")
    assert wide.attrs["parameters"]["contours"]["k_from_vertices"] >= len(wide) > 0
    np.testing.assert_allclose(np.sort(wide["charge"]), np.sort(same["charge"]))
    assert np.all(wide["charge_rounded"] == -0.5)
    default = find_defects(mesh, odf, None, avg_radius=5.0, refine="none")
    assert sorted(default["charge_rounded"]) == [-0.5, -0.5, 0.5, 0.5]
    assert np.abs(default["charge"] - default["charge_rounded"]).max() < 0.01


def test_no_defect_on_a_torus_matches_its_euler_characteristic():
    """Fibres along a torus's ring have no defect and Σ charge 0 = χ: the check says it matches
    (an independent review: zero defects always read "MISMATCH")."""
    mesh = trimesh.creation.torus(30.0, 12.0, major_sections=120, minor_sections=48)
    v = np.asarray(mesh.vertices)
    phi = np.arctan2(v[:, 1], v[:, 0])
    odf = pd.DataFrame({"vertex": np.arange(len(v)), "S": 1.0, "nx": -np.sin(phi), "ny": np.cos(phi), "nz": 0.0})
    df = find_defects(mesh, odf, None, avg_radius=5.0, refine="none")
    check = df.attrs["euler_check"]
    assert len(df) == 0 and check["closed"] and check["euler_characteristic"] == 0 and check["matches"]


def test_a_curvature_array_goes_with_the_table_source(sphere60):
    mesh, ddf, odf = sphere_case(60.0, 1.5, rotated(TETRA, 0), [0.5] * 4, 2000, 15.0, mesh=sphere60)
    k = np.full(len(mesh.vertices), 1 / 60.0**2)
    with pytest.raises(NemoError, match="curvature_source='table'"):
        find_defects(mesh, odf, ddf, curvature=k, curvature_source="contour")
    with pytest.raises(NemoError, match="curvature_source='table'"):
        find_defects(mesh, odf, ddf, curvature_source="table")
    with pytest.raises(NemoError, match="curvature_source must be one of"):
        find_defects(mesh, odf, ddf, curvature_source="faces")


def test_curvature_term_matches_marching_cubes_sphere():
    """Same check on a reconstructed (marching-cubes) sphere with angle defects."""
    radius, r_c = 30.0, 18.0
    dirs = rotated(TETRA, 8)
    mesh, ddf, odf = sphere_case(radius, 0.8, dirs, [0.5] * 4, 3000, 8.0, seed=6)
    df = find_defects(mesh, odf, ddf, avg_radius=8.0, contour_radius=r_c)
    assert len(df) == 4
    np.testing.assert_allclose(df["charge"], 0.5, atol=0.05)
    assert np.all(df["charge_curvature"] > 0.1)
    assert match(df, radius * dirs).max() < 0.5


# ------------------------------------------------------------------------------------------------
# parameters and bad input


def test_max_defects_and_min_distance(sphere60):
    """max_defects keeps the defects of the deepest S dips (non-maximum suppression visits the
    candidates in increasing S); a suppression radius wider than the defect spacing keeps only
    the deepest one."""
    dirs = rotated(TETRA, 0)
    truth = 60.0 * dirs
    mesh, ddf, odf = sphere_case(60.0, 1.5, dirs, [0.5] * 4, 4000, 15.0, seed=0, mesh=sphere60)
    # depth of each true defect's S dip, from the order table alone (measured: 0.029, 0.011,
    # 0.0063, 0.025: the two deepest, 2 and 1, are well apart from the others)
    verts, s = np.asarray(mesh.vertices), odf["S"].to_numpy()
    dip = np.array([s[np.linalg.norm(verts - p, axis=1) < 10.0].min() for p in truth])
    deepest = np.argsort(dip)
    assert dip[deepest[2]] > 2 * dip[deepest[1]]  # the case separates the 2 deepest clearly
    full = find_defects(mesh, odf, ddf, avg_radius=15.0)
    assert len(full) == 4
    # reported in the order they were accepted: deepest dip first
    order = np.linalg.norm(full[["x", "y", "z"]].to_numpy()[:, None] - truth[None], axis=2).argmin(axis=1)
    np.testing.assert_array_equal(order, deepest)
    df = find_defects(mesh, odf, ddf, avg_radius=15.0, max_defects=2)
    assert len(df) == 2
    dist = np.linalg.norm(df[["x", "y", "z"]].to_numpy()[:, None] - truth[None], axis=2)
    assert dist.min(axis=1).max() < 1.0
    assert sorted(dist.argmin(axis=1)) == sorted(deepest[:2])  # the 2 deepest dips, not any 2
    # the same defects as the first two of the unlimited run, which stops there
    np.testing.assert_allclose(df[["x", "y", "z", "charge"]], full[["x", "y", "z", "charge"]].iloc[:2])
    # a suppression radius wider than the defect spacing leaves only the lowest-S defect
    spacing = 60.0 * math.acos(-1.0 / 3.0)  # geodesic distance between tetrahedron vertices
    one = find_defects(mesh, odf, ddf, avg_radius=15.0, min_distance=1.2 * spacing)
    assert len(one) == 1
    assert np.linalg.norm(one[["x", "y", "z"]].to_numpy()[0] - truth[deepest[0]]) < 1.0
    # without the raw directors: refined from the averaged Q field, still on the surface
    df = find_defects(mesh, odf, None, avg_radius=15.0)
    assert len(df) == 4 and set(df["refine"]) <= {"q", "vertex"}
    r = np.linalg.norm(df[["x", "y", "z"]].to_numpy(), axis=1)
    np.testing.assert_allclose(r, 60.0, atol=0.1)
    assert match(df, 60.0 * dirs).max() < 3.0


def test_a_threshold_above_the_ordered_level_is_warned_about(sphere60):
    """s_threshold 1 makes every vertex a candidate and, as the contour's S must reach it too (the
    default s_ordered), rejects the real defects as disordered: warned, with the fix."""
    dirs = rotated(TETRA, 0)
    mesh, ddf, odf = sphere_case(60.0, 1.5, dirs, [0.5] * 4, 4000, 15.0, seed=0, mesh=sphere60)
    with pytest.warns(NemoWarning, match=r"above the surface's ordered level.*lower s_threshold"):
        df = find_defects(mesh, odf, ddf, avg_radius=15.0, s_threshold=1.0)
    assert len(df) < 4
    assert len(find_defects(mesh, odf, ddf, avg_radius=15.0, s_threshold=1.0, s_ordered=0.3)) == 4


def test_bad_input(sphere60):
    odf = pd.DataFrame({"vertex": [0, 1, len(sphere60.vertices) + 5], "S": [0.1, 0.2, 0.3],
                        "nx": [1.0] * 3, "ny": [0.0] * 3, "nz": [0.0] * 3})
    with pytest.raises(NemoError, match="another mesh"):
        find_defects(sphere60, odf, None)
    with pytest.raises(NemoError, match="lacks column 'S'"):
        find_defects(sphere60, odf.drop(columns="S"), None)
    good = odf.iloc[:2]
    with pytest.raises(NemoError, match="min_distance"):
        find_defects(sphere60, good, None, min_distance=-1.0)
    with pytest.raises(NemoError, match="one K per vertex"):
        find_defects(sphere60, good, None, curvature=np.zeros(3))
    with pytest.raises(NemoError, match="winding_field"):
        find_defects(sphere60, good, None, winding_field="nearest")


def test_winding_from_raw_directors_and_no_refinement(sphere60):
    dirs = rotated(TETRA, 21)
    mesh, ddf, odf = sphere_case(60.0, 1.5, dirs, [0.5] * 4, 4000, 15.0, seed=5, noise=5.0, mesh=sphere60)
    raw = find_defects(mesh, odf, ddf, avg_radius=15.0, winding_field="directors")
    assert len(raw) == 4
    np.testing.assert_allclose(raw["charge"], 0.5, atol=0.05)
    plain = find_defects(mesh, odf, ddf, avg_radius=15.0, refine="none")
    assert len(plain) == 4 and (plain["refine"] == "vertex").all() and (plain["shift"] == 0).all()
    np.testing.assert_allclose(plain[["x", "y", "z"]].to_numpy(),
                               np.asarray(mesh.vertices)[plain["vertex"].to_numpy()])
    # the model refinement beats the minimum-S vertex, which the averaging biases
    assert match(find_defects(mesh, odf, ddf, avg_radius=15.0), 60.0 * dirs).mean() < match(plain, 60.0 * dirs).mean()


# ------------------------------------------------------------------------------------------------
# contour path, curvature term and every rejection branch on constructed cases


def test_contour_is_the_ball_boundary_loop_and_k_term_is_k_times_area():
    """On a clean closed surface every charge uses the boundary loop of the geodesic ball (not
    the fallback ring), and with a constant K the curvature term is K × (area of the enclosed
    faces) / 2π: interior vertices count fully and contour vertices half (module doc)."""
    radius, r_c = 50.0, 20.0
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=radius)
    _, ddf, odf = sphere_case(radius, None, rotated(TETRA, 3), [0.5] * 4, 4000, 8.0, seed=1, mesh=mesh)
    k = np.full(len(mesh.vertices), 1.0 / radius**2)
    df = find_defects(mesh, odf, ddf, curvature=k, avg_radius=8.0, contour_radius=r_c, refine="none")
    assert len(df) == 4
    assert df.attrs["parameters"]["contours"] == {"loop": 4, "ring": 0, "circle": 0, "shrunk": 0, "k_from_vertices": 0}
    graph = edge_graph(mesh)
    h = mesh.edges_unique_length.mean()
    for _, row in df.iterrows():
        idx, dist = geodesic_ball(graph, int(row["vertex"]), 2 * r_c)
        inside = np.zeros(len(mesh.vertices), bool)
        inside[idx[dist < row["contour_radius"] + 0.5 * h]] = True  # the loop lies at the radius on average
        area = mesh.area_faces[inside[mesh.faces].all(axis=1)].sum()
        # counting the contour vertices fully (or not at all) is off by ≈ 2e-3 here
        assert row["charge_curvature"] == pytest.approx(area / radius**2 / (2 * np.pi), abs=1e-3)
        assert row["n_contour"] > 40


def _planar_case(theta_fn, centre=(0.0, 0.0), half=40.0, h=1.0, a=6.0):
    """Grid mesh with a hand-made order table: S = min(1, r / a) around ``centre``, n from θ(x, y)."""
    mesh = grid_mesh(half, h)
    v = np.asarray(mesh.vertices)
    r = np.hypot(v[:, 0] - centre[0], v[:, 1] - centre[1])
    th = theta_fn(v[:, 0] - centre[0], v[:, 1] - centre[1])
    odf = pd.DataFrame({"vertex": np.arange(len(v)), "S": np.clip(r / a, 0.02, 1.0),
                        "nx": np.cos(th), "ny": np.sin(th), "nz": np.zeros(len(v))})
    return mesh, odf


@pytest.mark.parametrize(("theta", "kwargs", "reason"), [
    # a wall where the director jumps by 80°: the contour crosses it twice (+80°, −80°)
    (lambda x, y: np.where(x < 0, 0.0, np.radians(80.0)), {}, "unresolved winding"),
    # a uniform field around an S dip (a disordered spot, not a defect)
    (lambda x, y: np.zeros_like(x), {}, "zero charge"),
    # a +1/2 field with a K term that adds 0.3: 0.8 is not a multiple of 1/2 within 0.15
    (lambda x, y: 0.5 * np.arctan2(y, x), {"curvature": 0.3 * 2 / 15.0**2}, "off-half charge"),
])
def test_rejection_branches(theta, kwargs, reason):
    mesh, odf = _planar_case(theta)
    if "curvature" in kwargs:
        kwargs = {"curvature": np.full(len(mesh.vertices), kwargs["curvature"])}
    df = find_defects(mesh, odf, None, avg_radius=6.0, contour_radius=15.0, **kwargs)
    assert len(df) == 0
    rejected = df.attrs["parameters"]["rejected"]
    assert rejected[reason] == 1 and sum(rejected.values()) == 1, rejected
    cands = candidate_table(df)
    assert list(cands["reason"]) == [reason] and not cands["accepted"].any()
    # the same field as a +1/2 defect is accepted: the branch is the field, not the set-up
    mesh, odf = _planar_case(lambda x, y: 0.5 * np.arctan2(y, x))
    assert len(find_defects(mesh, odf, None, avg_radius=6.0, contour_radius=15.0)) == 1


def test_a_zero_charge_dip_nearby_does_not_cap_a_defect_contour():
    """A +½ defect whose disordered core reaches 12 µm, with a spurious S dip 22 µm away: the dip
    caps the first contour at 0.45 × 22 µm, still in the core (rejected as disordered). Once the
    dip's own contour reads zero charge, the defect is measured again on wider contours and found."""
    mesh, odf = _planar_case(lambda x, y: 0.5 * np.arctan2(y, x))
    v = np.asarray(mesh.vertices)
    r = np.hypot(v[:, 0], v[:, 1])
    s = np.clip((r / 15.0) ** 2, 1e-3, 1.0)
    s[np.hypot(v[:, 0] - 22.0, v[:, 1]) < 3.0] = 0.05  # a disordered spot, no defect
    odf["S"] = s
    df = find_defects(mesh, odf, None, avg_radius=6.0, min_distance=15.0)
    cands = candidate_table(df)
    assert len(df) == 1, cands
    assert np.hypot(df["x"].iloc[0], df["y"].iloc[0]) < 1.5
    assert df["charge_rounded"].iloc[0] == 0.5 and df["contour_radius"].iloc[0] > 0.45 * 22.0
    assert sorted(cands["reason"]) == ["", "zero charge"]
    assert df.attrs["parameters"]["rejected"]["disordered contour"] == 0
    # the dip is what capped it: alone, the first contour is wide enough
    odf["S"] = np.clip((r / 15.0) ** 2, 1e-3, 1.0)
    assert len(find_defects(mesh, odf, None, avg_radius=6.0, min_distance=15.0)) == 1


def test_contour_shrinks_at_an_open_rim():
    """A defect 8 µm from the rim is measured on a contour shrunk off the rim (the default is
    1.5 × 6 = 9 µm); one 2 µm from the rim has no room for a contour ("contour leaves the surface")."""
    half = 40.0
    mesh, odf = _planar_case(lambda x, y: 0.5 * np.arctan2(y, x), centre=(half - 8.3, 0.2))
    df = find_defects(mesh, odf, None, avg_radius=6.0)
    assert len(df) == 1 and df["charge_rounded"].iloc[0] == 0.5
    assert df.attrs["parameters"]["contours"]["shrunk"] == 1
    assert df["contour_radius"].iloc[0] < 0.9 * 8.3
    mesh, odf = _planar_case(lambda x, y: 0.5 * np.arctan2(y, x), centre=(half - 2.3, 0.2))
    df = find_defects(mesh, odf, None, avg_radius=6.0)
    assert len(df) == 0 and df.attrs["parameters"]["rejected"]["contour leaves the surface"] == 1
    assert list(candidate_table(df)["reason"]) == ["contour leaves the surface"]


def test_open_hemisphere_interior_defects_found_rim_dips_rejected():
    """An open hemisphere (a surface cut by the field of view) with +1/2, +1 and −1/2 defects inside
    and a −1/2 and a +1/2 defect 3.5 and 2 µm inside the rim: their S dips reach the rim, so no
    closed contour on the surface encloses them (a contour through the rim would read the
    director's turning along the cut as a charge). The interior defects are found with their
    charges; the rim dips are rejected as "contour leaves the surface", nothing else reported."""
    from sparse_fields import polar_dirs

    R = 40.0
    sph = mc_sphere(R, 1.5)
    sub = sph.submesh([np.flatnonzero(sph.triangles_center[:, 2] > 0.0)], append=True)
    cap = trimesh.Trimesh(sub.vertices, sub.faces, process=False)
    assert not cap.is_watertight
    # inside: +1/2, +1 and a -1/2 15 µm from the rim; at the rim: -1/2 and +1/2 3.5 and 2 µm
    # inside it
    dirs = np.vstack([polar_dirs(35, 0), polar_dirs(30, 180), polar_dirs(68, 300), polar_dirs(85, 120),
                      polar_dirs(87, 270)])
    charges = [0.5, 1.0, -0.5, -0.5, 0.5]
    ddf = sample_directors(cap, 3000, lambda p: stereo_director(p, dirs, charges), np.random.default_rng(0), 5.0)
    df = find_defects(cap, q_average(cap, ddf, 8.0), ddf, avg_radius=8.0)
    assert len(df) == 3
    err = match(df, R * dirs[:3])
    assert err.max() < 1.0, err  # measured 0.2-0.4 µm
    np.testing.assert_allclose(sorted(df["charge"]), [-0.5, 0.5, 1.0], atol=0.02)
    assert (df["z"] > 10).all()  # nothing from the rim (z = 0)
    rejected = df.attrs["parameters"]["rejected"]
    assert rejected["contour leaves the surface"] == 2
    cands = candidate_table(df)
    at_rim = cands[cands["reason"] == "contour leaves the surface"]
    assert len(at_rim) == 2 and (at_rim["z"] < 4.0).all() and at_rim["charge"].isna().all()
    assert not df.attrs["euler_check"]["closed"]


# ------------------------------------------------------------------------------------------------
# acceptance rule scaled with the sampling


@pytest.mark.parametrize("n_dir", [4, 7, 14, 30, 100])
def test_noise_floor_bounds_isotropic_contours(n_dir):
    """The floor exceeds the median contour S of an isotropic field in ≥ 99 % of draws (Monte
    Carlo over n_indep independent discs of n_dir random directors), and stays below the S
    that ordered directors reach (20° noise: S = exp(−2σ²) ≈ 0.78) from 7 directors on."""
    rng = np.random.default_rng(n_dir)
    n_indep = 5
    phase = np.exp(2j * rng.uniform(0, np.pi, (20000, n_indep, n_dir)))
    s_med = np.median(np.abs(phase.mean(axis=2)), axis=1)
    floor = noise_floor(n_dir, n_indep)
    cap = 0.5 * (1 + math.sqrt(math.pi / (4 * n_dir)))  # midway between noise and perfect order
    if n_dir >= 7:
        assert floor < cap and np.mean(s_med < floor) > 0.99
    else:  # too few directors to be 3 standard errors sure: the cap keeps order reachable
        assert floor == pytest.approx(cap) and np.mean(s_med < floor) > 0.95
    assert floor < 1.0
    if n_dir >= 7:
        s_ordered = np.abs(np.exp(2j * np.radians(20.0) * rng.standard_normal((2000, n_dir))).mean(axis=1))
        assert floor < np.median(s_ordered) - 0.1
    # the old rule 3 sqrt(π/4N) reached 1 at N = 7: nothing sparse could pass
    assert noise_floor(7, 4.7) < 0.6


def test_step_limit_follows_contour_length():
    assert step_limit_deg(40) == 60.0
    assert step_limit_deg(6) == pytest.approx(75.0)  # a 1/2 defect turns 30° per step on average
    assert step_limit_deg(3) == 80.0  # never near the 90° head-tail ambiguity


@pytest.mark.parametrize("seed", [0, 1])
def test_a_close_pair_missed_is_counted_as_rejected_zeros(sphere60, seed):
    """A +½/−½ pair 20 µm apart beside four tetrahedral +½ (sphere R 60, 15 µm averaging): one
    contour encloses both and reads 0, so the pair is missed and Σ charge is still χ; its deep
    Q-zero is counted in ``rejected_zeros`` (the summary flags the frame). The four alone count none."""
    base = rotated(TETRA, 3)
    dirs = np.vstack([base, close_pair(base[0], base[1], 20.0, 60.0)])
    mesh, ddf, odf = sphere_case(60.0, 1.5, dirs, [0.5] * 4 + [0.5, -0.5], 6000, 15.0, seed=seed, noise=5.0,
                                 mesh=sphere60)
    df = find_defects(mesh, odf, ddf, avg_radius=15.0)
    assert len(df) == 4 and match(df, 60.0 * base).max() < 1.0  # the pair is missed, Σ = χ
    assert df.attrs["euler_check"]["matches"]
    assert df.attrs["parameters"]["rejected_zeros"] >= 1
    mesh, ddf, odf = sphere_case(60.0, 1.5, base, [0.5] * 4, 6000, 15.0, seed=seed, noise=5.0, mesh=sphere60)
    alone = find_defects(mesh, odf, ddf, avg_radius=15.0)
    assert len(alone) == 4 and alone.attrs["parameters"]["rejected_zeros"] == 0


def test_rejected_zeros_counts_deep_zeros_rejected_for_their_contour():
    """Only zeros as deep as a defect's core (S < ZERO_PER_ORDERED × S_ref) count, and only when
    their contour was unreadable with a nonzero charge, or read zero (a pair inside)."""
    from nemo.defects import ZERO_PER_ORDERED, rejected_zeros

    deep, shallow = 0.5 * ZERO_PER_ORDERED, 2 * ZERO_PER_ORDERED
    recs = [{"S": deep, "charge_rounded": 0.5, "reason": "disordered contour"},
            {"S": deep, "charge_rounded": -0.5, "reason": "unresolved winding"},
            {"S": deep, "charge_rounded": 0.0, "reason": "zero charge"},
            {"S": deep, "charge_rounded": 0.0, "reason": "disordered contour"},  # no winding to miss
            {"S": deep, "charge_rounded": None, "reason": "no contour"},
            {"S": deep, "charge_rounded": 0.5, "reason": ""},  # accepted
            {"S": deep, "charge_rounded": 0.5, "reason": "same dip"},
            {"S": shallow, "charge_rounded": 0.5, "reason": "disordered contour"},
            {"S": shallow, "charge_rounded": 0.0, "reason": "zero charge"}]
    assert rejected_zeros(recs, 1.0) == 3
    assert rejected_zeros(recs, 0.25) == 0  # a lower ordered level: none is that deep


def test_candidate_table_reports_accepted_and_rejected(sphere60):
    dirs = rotated(TETRA, 0)
    mesh, ddf, odf = sphere_case(60.0, 1.5, dirs, [0.5] * 4, 4000, 15.0, seed=0, noise=5.0, mesh=sphere60)
    df = find_defects(mesh, odf, ddf, avg_radius=15.0, s_threshold=0.6)  # a generous threshold
    cands = candidate_table(df)
    assert list(cands.columns) == list(CANDIDATE_COLUMNS)
    assert cands["accepted"].sum() == len(df) == 4
    np.testing.assert_allclose(cands.loc[cands["accepted"], ["x", "y", "z"]], df[["x", "y", "z"]])
    assert (cands.loc[cands["accepted"], "reason"] == "").all()
    rej = cands.loc[~cands["accepted"]]
    assert rej["reason"].isin(df.attrs["parameters"]["rejected"].keys()).all()
    assert rej["reason"].value_counts().to_dict() == {k: v for k, v in df.attrs["parameters"]["rejected"].items() if v}
    with pytest.raises(NemoError, match="candidate records"):
        candidate_table(pd.DataFrame())


def test_cli_writes_candidates(tmp_path, sphere60):
    from nemo.cli import main
    from nemo.mesh import save_mesh
    from nemo.tables import read_provenance, write_table

    dirs = rotated(TETRA, 0)
    mesh, ddf, odf = sphere_case(60.0, 1.5, dirs, [0.5] * 4, 4000, 15.0, seed=0, noise=5.0, mesh=sphere60)
    save_mesh(mesh, tmp_path / "m.ply")
    odf = odf.assign(x=mesh.vertices[:, 0], y=mesh.vertices[:, 1], z=mesh.vertices[:, 2],
                     count=np.ones(len(odf), dtype=np.int64))
    write_table(odf, tmp_path / "o.parquet", radius=15.0)
    write_table(ddf, tmp_path / "d.parquet")
    assert main(["defects", str(tmp_path / "m.ply"), str(tmp_path / "o.parquet"), str(tmp_path / "d.parquet"),
                 "-o", str(tmp_path / "x.parquet"), "--candidates", str(tmp_path / "c.parquet")]) == 0
    cands = pd.read_parquet(tmp_path / "c.parquet")
    assert list(cands.columns) == list(CANDIDATE_COLUMNS) and cands["accepted"].sum() == 4
    assert read_provenance(tmp_path / "c.parquet")["command"] == "defects candidates"


# ------------------------------------------------------------------------------------------------
# sparse fields: one director per vertex of a coarse mesh (tests/sparse_fields.py)


def _sparse_check(mesh, ddf, truth, charges, with_directors=True, avg_radius="order"):
    """Order radius 1.7 × spacing, default defect parameters: every defect within 2 spacings,
    right charge, no extras."""
    import sparse_fields as sf

    from nemo.order import order

    d = sf.mean_spacing(mesh)
    odf = order(mesh, ddf, 1.7 * d)
    df = find_defects(mesh, odf, ddf if with_directors else None,
                      avg_radius=1.7 * d if avg_radius == "order" else None)
    sc = sf.score(df, truth, charges)
    assert sc["found"] == len(truth) and sc["extras"] == 0, (sc, df.attrs["parameters"]["rejected"])
    assert sc["charge_ok"], df
    assert sc["dist"].max() < 2 * d, sc["dist"] / d
    return df


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("noise", [0.0, 10.0, 20.0])
@pytest.mark.parametrize("spacing", [6.0, 10.0])
def test_sparse_sphere_four_half_defects(spacing, noise, seed):
    """R = 50 µm, vertices 6 or 10 µm apart (≈ 10 directors per averaging disc), randomly
    rotated tetrahedral +1/2 defects (the old noise floor 3 sqrt(π/4N) ≈ 0.9 rejected them)."""
    import sparse_fields as sf

    dirs = sf.rotated_defects(sf.TETRA, seed)
    mesh, ddf, truth = sf.sphere_case(50.0, spacing, dirs, [0.5] * 4, noise, seed)
    df = _sparse_check(mesh, ddf, truth, [0.5] * 4)
    if spacing >= 10:  # edges ~ averaging radius: sampled circles (at 6 µm most loops suffice)
        assert df.attrs["parameters"]["contours"]["circle"] >= 3
    assert df.attrs["euler_check"]["matches"]
    np.testing.assert_allclose(df["charge"], 0.5, atol=0.1)


@pytest.mark.parametrize("noise", [0.0, 10.0, 20.0])
@pytest.mark.parametrize("spacing", [6.0, 10.0])
def test_sparse_open_cap_plus_and_minus_half(spacing, noise):
    """Open spherical cap (75° from the pole) with a +1/2 and a −1/2 defect 50° apart."""
    import sparse_fields as sf

    dirs = sf.polar_dirs([25.0, 25.0], [0.0, 180.0])
    mesh, ddf, truth = sf.cap_case(50.0, spacing, 75.0, dirs, [0.5, -0.5], noise, int(noise))
    assert not mesh.is_watertight
    df = _sparse_check(mesh, ddf, truth, [0.5, -0.5])
    assert not df.attrs["euler_check"]["closed"]


@pytest.mark.parametrize("spacing", [6.0, 10.0])
def test_sparse_without_directors_or_radius(spacing):
    """Only the order table (circle contours interpolate its Q-tensor), or no averaging radius
    (estimated from S, at least 1.5 mesh edges)."""
    import sparse_fields as sf

    dirs = sf.rotated_defects(sf.TETRA, 4)
    mesh, ddf, truth = sf.sphere_case(50.0, spacing, dirs, [0.5] * 4, 10.0, 4)
    _sparse_check(mesh, ddf, truth, [0.5] * 4, with_directors=False)
    df = _sparse_check(mesh, ddf, truth, [0.5] * 4, avg_radius=None)
    assert 1.3 < df.attrs["parameters"]["avg_radius"] / sf.mean_spacing(mesh) < 2.5


def test_radii_larger_than_the_surface_are_refused():
    """--contour-radius 300 on a 50 µm sphere took 80 s and meant nothing: now a clear error."""
    import sparse_fields as sf

    mesh, ddf, _ = sf.sphere_case(50.0, 6.0, sf.rotated_defects(sf.TETRA, 0), [0.5] * 4, 0.0, 0)
    from nemo.order import order

    odf = order(mesh, ddf, radius=10.2)
    for name in ("contour_radius", "avg_radius", "fit_radius"):
        with pytest.raises(NemoError, match=f"`{name}` 300 is larger than 2 × the surface's size"):
            find_defects(mesh, odf, ddf, **{name: 300.0})
    assert len(find_defects(mesh, odf, ddf, contour_radius=20.0)) == 4


@pytest.mark.parametrize("preset", ["tetrahedron", "five-one"])
@pytest.mark.parametrize("noise", [10.0, 20.0])
@pytest.mark.parametrize("spacing", [6.0, 10.0])
def test_sparse_sampling_of_the_projects_vesicle_field(spacing, noise, preset):
    """The synthetic vesicle's own analytic field (nemo.synthetic.director_field, the paper's
    tetrahedron and the five +1/2 / one -1/2 set), rotated at random, sampled once per vertex of
    a 6 or 10 µm mesh with 10-20° angle noise: every defect, right charge, no extras."""
    import sparse_fields as sf
    from scipy.spatial.transform import Rotation

    from nemo.synthetic import director_field, preset_defects, projection_pole

    dirs, charges = preset_defects(preset)
    dirs = dirs @ Rotation.random(random_state=int(spacing + noise)).as_matrix().T
    mesh = sf.fibonacci_sphere(50.0, spacing)
    field = director_field(np.asarray(mesh.vertices), dirs, charges, pole=projection_pole(dirs))
    ddf = sf.vertex_directors(mesh, field, noise, int(noise))
    _sparse_check(mesh, ddf, 50.0 * dirs, charges)


@pytest.mark.parametrize("avg, separation, expect", [(20.0, 14.0, [1.0]), (16.0, 16.0, [0.5, 0.5])])
def test_zeros_of_one_dip_are_enclosed_not_cut_by_the_contour(avg, separation, expect):
    """Two +½ `separation` µm apart (a +1 split, as an aster splits under a z-PSF) and their χ
    partner, a +1 at the other pole of a sphere R 60 µm. Averaged over 20 µm the pair's Q-zeros
    share one dip, 28 µm apart: the default contour (30 µm) around one ran through the other's core
    and read +½, and the other, inside it, was taken as part of it (Σ 1.5). The contour now clears
    that core and encloses both: one +1 between them (Σ = χ). A pair resolved by a 16 µm average
    still reads two +½."""
    from nemo import stages

    R = 60.0
    a = separation / (2 * R)
    pair = np.array([[np.sin(a), 0, np.cos(a)], [-np.sin(a), 0, np.cos(a)]])
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=R)
    v = np.asarray(mesh.vertices)[::2]
    n = stereo_field(v, pair, [0.5, 0.5])
    ddf = pd.DataFrame({"vertex": np.arange(0, len(mesh.vertices), 2), "x": v[:, 0], "y": v[:, 1], "z": v[:, 2],
                        "nx": n[:, 0], "ny": n[:, 1], "nz": n[:, 2], "coherency": 1.0})
    odf, _ = stages.order(mesh, ddf, {"radius": avg})
    df = find_defects(mesh, odf, ddf, avg_radius=avg, refine="none")
    assert df["charge_rounded"].sum() == pytest.approx(2.0)
    north = df[df["z"] > 0]
    assert sorted(north["charge_rounded"]) == expect
    if expect == [1.0]:  # placed between the two zeros: at the pole
        assert np.hypot(north["x"], north["y"]).max() < 3.0 and (north["refine"] == "zeros").all()
        assert north["fit_radius"].isna().all()  # no fit placed it
