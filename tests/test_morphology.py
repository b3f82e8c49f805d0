"""Curvature, thickness and global measures against analytic shapes.

Test meshes are reconstructed from a volume: marching cubes (scikit-image) on an analytic
signed-distance (sphere, torus) or first-order distance (ellipsoid) field sampled on a voxel
grid, possibly anisotropic, scaled to physical units and turned into a NEMO mesh by
``nemo.mesh.make_mesh`` (or by ``nemo mesh`` on the shell image of conftest.py; one icosphere
checks the too-large-radius warning). Ground truth is analytic (closest point on the ellipsoid, exact ray
intersections with spheres and ellipsoids).
"""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
import trimesh
from skimage.measure import marching_cubes

from nemo.errors import NemoError, NemoWarning
from nemo.geometry import rim
from nemo.mesh import load_mesh, make_mesh, save_mesh
from nemo.morphology import beyond_view, curvature, measure, thickness, vertex_areas
from nemo.tables import read_provenance, read_table

ISO = (1.0, 1.0, 1.0)
ANISO = (2.0, 1.0, 1.0)  # (dz, dy, dx): dz = 2 dx


# --------------------------------------------------------------------------------------------
# meshes from volumes
# --------------------------------------------------------------------------------------------


def _grid(half, spacing):
    """Physical coordinates (X, Y, Z arrays in (Z, Y, X) order) of a grid covering ±half."""
    dz, dy, dx = spacing
    x = np.arange(-half[0], half[0] + dx / 2, dx)
    y = np.arange(-half[1], half[1] + dy / 2, dy)
    z = np.arange(-half[2], half[2] + dz / 2, dz)
    Z, Y, X = np.meshgrid(z, y, x, indexing="ij")
    return X, Y, Z, np.array([x[0], y[0], z[0]])


def _mesh(field, origin, spacing):
    """Marching cubes at level 0, vertices to physical x, y, z, outward faces."""
    verts, faces, _, _ = marching_cubes(field, 0.0, spacing=spacing)
    return make_mesh(verts[:, ::-1] + origin, faces, unit="um")


def sphere_mesh(R, spacing=ISO, centre=(0.3, -0.2, 0.1)):
    h = R + 3 * max(spacing)
    X, Y, Z, o = _grid((h, h, h), spacing)
    c = np.asarray(centre)
    return _mesh(np.sqrt((X - c[0]) ** 2 + (Y - c[1]) ** 2 + (Z - c[2]) ** 2) - R, o, spacing)


def ellipsoid_mesh(abc, spacing=ISO):
    a, b, c = abc
    X, Y, Z, o = _grid(tuple(s + 3 * max(spacing) for s in abc), spacing)
    g = (X / a) ** 2 + (Y / b) ** 2 + (Z / c) ** 2 - 1
    grad = 2 * np.sqrt((X / a**2) ** 2 + (Y / b**2) ** 2 + (Z / c**2) ** 2)
    return _mesh(g / np.maximum(grad, 1e-12), o, spacing)  # ≈ signed distance near the surface


def torus_mesh(Rt, r, spacing=ISO):
    X, Y, Z, o = _grid((Rt + r + 3, Rt + r + 3, r + 3), spacing)
    return _mesh(np.sqrt((np.hypot(X, Y) - Rt) ** 2 + Z**2) - r, o, spacing)


def closest_on_ellipsoid(p, abc):
    """Closest points on x²/a² + y²/b² + z²/c² = 1 (Newton on the Lagrange multiplier)."""
    a2 = np.asarray(abc, float) ** 2
    t = np.zeros(len(p))
    for _ in range(60):
        den = a2 + t[:, None]
        f = (p**2 * a2 / den**2).sum(1) - 1
        df = -2 * (p**2 * a2 / den**3).sum(1)
        t -= f / df
    return p * a2 / (a2 + t[:, None])


def ellipsoid_HK(q, abc):
    """Analytic H (outward normal: positive) and K at points q on the ellipsoid."""
    a, b, c = abc
    x, y, z = q.T
    s = x**2 / a**4 + y**2 / b**4 + z**2 / c**4
    K = 1.0 / ((a * b * c) ** 2 * s**2)
    H = (a * a + b * b + c * c - x * x - y * y - z * z) / (2 * (a * b * c) ** 2 * s**1.5)
    return H, K


def ray_ellipsoid(origin, direction, abc):
    """Exact first positive t with origin + t·direction on the ellipsoid (NaN: miss)."""
    inv = 1.0 / np.asarray(abc, float) ** 2
    A = (direction**2 * inv).sum(1)
    B = 2 * (origin * direction * inv).sum(1)
    C = (origin**2 * inv).sum(1) - 1
    disc = B * B - 4 * A * C
    with np.errstate(invalid="ignore"):
        roots = np.stack([(-B - np.sqrt(disc)) / (2 * A), (-B + np.sqrt(disc)) / (2 * A)], 1)
    roots[roots < 0] = np.nan
    return np.nanmin(np.where(np.isnan(roots), np.inf, roots), axis=1).clip(max=np.inf)


def rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


ELL = (30.0, 22.0, 16.0)


@pytest.fixture(scope="module")
def ellipsoids():
    return {sp: ellipsoid_mesh(ELL, sp) for sp in (ISO, ANISO)}


@pytest.fixture(scope="module")
def sphere15():
    return sphere_mesh(15.0)


# --------------------------------------------------------------------------------------------
# curvature
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("R", [8.0, 15.0, 25.0])
def test_sphere_H_and_K(R):
    mesh = sphere_mesh(R)
    df = curvature(mesh, radius=4.0, rng=0)
    assert list(df.columns[:5]) == ["vertex", "H", "K", "k1", "k2"]
    assert len(df) == len(mesh.vertices) and df["H"].notna().all()
    assert abs(np.median(df["H"]) * R - 1) < 0.02
    assert abs(np.median(df["K"]) * R * R - 1) < 0.03
    assert np.percentile(np.abs(df["H"] * R - 1), 90) < 0.05
    assert np.all(df["k1"] >= df["k2"])


@pytest.mark.parametrize("spacing", [ISO, ANISO], ids=["iso", "dz=2dx"])
def test_ellipsoid_pointwise_H_K(ellipsoids, spacing):
    mesh = ellipsoids[spacing]
    v = np.asarray(mesh.vertices)
    H_true, K_true = ellipsoid_HK(closest_on_ellipsoid(v, ELL), ELL)
    df = curvature(mesh, radius=8.0, rng=1)  # auto -> quartic fit (≥ 60 neighbours)
    assert df.attrs["fit"] == "quartic"
    eh = np.abs(df["H"] / H_true - 1)
    ek = np.abs(df["K"] / K_true - 1)
    assert np.median(eh) <= 0.02, np.median(eh)
    assert np.median(ek) <= 0.03, np.median(ek)
    # principal curvatures bracket the analytic mean; d1 ⟂ d2, both tangent
    d1 = df[["d1x", "d1y", "d1z"]].to_numpy()
    d2 = df[["d2x", "d2y", "d2z"]].to_numpy()
    n = np.asarray(mesh.vertex_normals)
    ok = np.isfinite(d1).all(1)
    assert ok.mean() > 0.99
    assert np.abs(np.einsum("ij,ij->i", d1[ok], d2[ok])).max() < 1e-6
    assert np.median(np.abs(np.einsum("ij,ij->i", d1[ok], n[ok]))) < 0.05


def test_ellipsoid_principal_curvatures_and_directions(ellipsoids):
    """k1, k2 = H ± √(H² − K) pointwise; at the tip x = a the larger curvature a/c² bends
    toward z, the smaller a/b² toward y."""
    mesh = ellipsoids[ISO]
    v = np.asarray(mesh.vertices)
    H_true, K_true = ellipsoid_HK(closest_on_ellipsoid(v, ELL), ELL)
    root = np.sqrt(np.maximum(H_true**2 - K_true, 0))
    df = curvature(mesh, radius=6.0, rng=0)
    assert np.median(np.abs(df["k1"] / (H_true + root) - 1)) < 0.02
    assert np.median(np.abs(df["k2"] / (H_true - root) - 1)) < 0.02
    a, b, c = ELL
    tip = np.argsort(np.linalg.norm(v - (a, 0, 0), axis=1))[:10]
    assert np.median(df["k1"].to_numpy()[tip]) == pytest.approx(a / c**2, rel=0.03)
    assert np.median(df["k2"].to_numpy()[tip]) == pytest.approx(a / b**2, rel=0.03)
    assert np.abs(df["d1z"].to_numpy()[tip]).min() > 0.95
    assert np.abs(df["d2y"].to_numpy()[tip]).min() > 0.95


def test_fit_variants_documented(ellipsoids):
    """The module docstring's claim: at r = 6 µm (~160 neighbours) the quartic fit is several
    times more accurate than the paper's quadric, whose r²/R² bias shows up as overestimation."""
    mesh = ellipsoids[ISO]
    H_true, _ = ellipsoid_HK(closest_on_ellipsoid(np.asarray(mesh.vertices), ELL), ELL)
    err = {}
    for fit in ("quadric", "quadratic", "quartic"):
        df = curvature(mesh, radius=6.0, fit=fit, n_samples=3000, rng=0, smooth=0)  # the fits alone
        assert df.attrs["fit"] == fit
        err[fit] = np.median(np.abs(df["H"] / H_true - 1))
        if fit == "quadric":
            assert np.median(df["H"] / H_true - 1) > 0.01  # biased upward
    assert err["quartic"] < err["quadric"] / 3
    assert err["quartic"] < err["quadratic"] / 3


def test_subsampling_and_interpolation(sphere15):
    R = 15.0
    df = curvature(sphere15, radius=5.0, fraction=0.15, rng=3)
    n = len(sphere15.vertices)
    assert df["sampled"].sum() == round(0.15 * n)
    assert df["H"].notna().all()
    assert np.median(np.abs(df["H"] * R - 1)) < 0.01
    assert np.percentile(np.abs(df["K"] * R * R - 1), 95) < 0.05
    # a sampled vertex keeps its own fitted value: same seed, sampled set identical
    full = curvature(sphere15, radius=5.0, fraction=0.15, rng=3)
    assert np.array_equal(df["H"].to_numpy(), full["H"].to_numpy())


def test_default_sample_count_bounds_the_fit_pairs(sphere15, monkeypatch):
    """Many samples at a small radius; at a large radius no more than the pair budget allows,
    but never fewer than eight per fitting disc, and the fit stays right with that few."""
    import nemo.morphology as nm

    area, n_vert = 4 * np.pi * 200.0**2, 188_650  # the paper's inner wall at step 2
    assert nm.default_n_samples(n_vert, area, 10.0) == nm.MIN_DEFAULT_SAMPLES  # ~120 neighbours
    assert nm.default_n_samples(5000, area, 5.0) == 5000
    r = 27.8  # the default radius there: ~900 neighbours per fit
    n = nm.default_n_samples(n_vert, area, r)
    per_disc = 8 * area / (np.pi * r**2)
    assert per_disc <= n < nm.MIN_DEFAULT_SAMPLES
    assert n * n_vert * np.pi * r**2 / area <= 1.001 * nm.DEFAULT_PAIR_BUDGET
    monkeypatch.setattr(nm, "DEFAULT_PAIR_BUDGET", 1)
    df = curvature(sphere15, radius=5.0, rng=3)
    assert df["sampled"].sum() == np.ceil(8 * sphere15.area / (np.pi * 25.0)) < len(sphere15.vertices)
    assert np.median(np.abs(df["H"] * 15.0 - 1)) < 0.01


def test_radius_pilot_fits_fewer_vertices_at_a_large_radius(sphere15, monkeypatch):
    """The pilot's pair budget cuts its vertices (not below PILOT_MIN_SAMPLES); R_c stays right."""
    import nemo.morphology as nm

    radius, info = nm.default_radius(sphere15, n_probe=2000, rng=0)
    assert info["n_probe"] == min(2000, len(sphere15.vertices))
    monkeypatch.setattr(nm, "PILOT_PAIR_BUDGET", 1)
    radius_cut, cut = nm.default_radius(sphere15, n_probe=2000, rng=0)
    assert cut["n_probe"] == nm.PILOT_MIN_SAMPLES
    assert cut["curvature_radius"] == pytest.approx(15.0, rel=0.05) and radius_cut == pytest.approx(radius, rel=0.05)


def test_seed_reproducibility(sphere15):
    a = curvature(sphere15, radius=4.0, n_samples=500, rng=7)
    b = curvature(sphere15, radius=4.0, n_samples=500, rng=7)
    c = curvature(sphere15, radius=4.0, n_samples=500, rng=8)
    assert a.equals(b)
    assert not np.array_equal(a["sampled"], c["sampled"])


def test_rotation_invariance(ellipsoids):
    mesh = ellipsoids[ISO]
    rot = rotation(np.random.default_rng(5))
    turned = make_mesh(np.asarray(mesh.vertices) @ rot.T + (5.0, -3.0, 2.0), mesh.faces, orient_outward=False)
    a = curvature(mesh, radius=5.0, n_samples=2000, rng=11)
    b = curvature(turned, radius=5.0, n_samples=2000, rng=11)
    np.testing.assert_allclose(b["H"], a["H"], rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(b["K"], a["K"], rtol=1e-6, atol=1e-10)
    d1 = a[["d1x", "d1y", "d1z"]].to_numpy() @ rot.T
    d1b = b[["d1x", "d1y", "d1z"]].to_numpy()
    sampled = a["sampled"].to_numpy() & (a["k1"] - a["k2"] > 1e-3).to_numpy()
    assert np.median(np.abs(np.einsum("ij,ij->i", d1[sampled], d1b[sampled]))) > 0.9999


def test_torus_sign_of_K_and_zero_total_curvature():
    Rt, r = 20.0, 8.0
    mesh = torus_mesh(Rt, r)
    df = curvature(mesh, radius=4.0, rng=0)
    v = np.asarray(mesh.vertices)
    rho = np.hypot(v[:, 0], v[:, 1])
    cosv = np.clip((rho - Rt) / r, -1, 1)
    K_true = cosv / (r * (Rt + r * cosv))
    H_true = (Rt + 2 * r * cosv) / (2 * r * (Rt + r * cosv))
    inner, outer = rho < Rt - 0.5 * r, rho > Rt + 0.5 * r
    assert (df["K"][inner] < 0).mean() > 0.99
    assert (df["K"][outer] > 0).mean() > 0.99
    assert np.median(np.abs(df["K"] - K_true)) < 0.03 / r**2
    assert np.median(np.abs(df["H"] / H_true - 1)) < 0.02
    res = measure(mesh, df)
    assert res["euler_characteristic"] == 0 and res["genus"] == 1 and res["is_watertight"]
    assert abs(res["integral_K"]) < 1e-9  # discrete Gauss–Bonnet, exact
    assert abs(res["integral_K_fit"]) < 0.02 * 4 * np.pi  # fitted K: ∫K dA ≈ 0
    assert res["gauss_bonnet_ratio"] is None
    assert res["mean_H"] == pytest.approx(1 / (2 * r), rel=0.02)  # ∫H dA = 2π²Rt, area 4π²Rt r
    assert res["volume"] == pytest.approx(2 * np.pi**2 * Rt * r**2, rel=0.01)
    assert any("coincident" in note for note in res["notes"])  # level through grid points


def _torus_truth(mesh, Rt, r):
    v = np.asarray(mesh.vertices)
    cosv = np.clip((np.hypot(v[:, 0], v[:, 1]) - Rt) / r, -1, 1)
    return (Rt + 2 * r * cosv) / (2 * r * (Rt + r * cosv)), cosv / (r * (Rt + r * cosv))


def test_a_thin_tube_is_fitted_at_a_fraction_of_its_radius():
    """A torus 30 / 8 µm fitted at 7.5 µm, 0.94 × the tube's radius: the quartic of a circle that
    nearly fills its ball reads the tube flat. Each vertex is refitted at most 0.65 × its radius of
    curvature (`local_fraction`; from the fits at 7.5 µm, which read it a few % flat: the ladder's
    rung 5.3 µm here) and reads it within 1 %."""
    Rt, r = 30.0, 8.0
    mesh = torus_mesh(Rt, r, spacing=(0.5, 0.5, 0.5))
    H_true, K_true = _torus_truth(mesh, Rt, r)
    one = curvature(mesh, 7.5, rng=0, smooth=0)  # the default: one radius
    local = curvature(mesh, 7.5, rng=0, smooth=0, local_fraction=0.65)
    e_one, e_local = (np.median(np.abs(df["H"] / H_true - 1)) for df in (one, local))
    assert e_one > 0.03 and e_local < 0.01, (e_one, e_local)
    k_rms = np.sqrt(np.mean(K_true**2))
    assert np.median(np.abs(local["K"] - K_true)) / k_rms < 0.02
    assert local.attrs["local_fits"] == len(mesh.vertices) and (one["fit_radius"] == 7.5).all()
    assert local["fit_radius"].max() < 0.7 * r


def test_a_tube_thinner_than_the_floor_is_fitted_at_the_floor():
    """A torus 20 / 4 µm at 1 µm voxels fitted at 8 µm: 0.65 × 4 µm is below the floor of 6 mean
    edges, so the vertices are refitted (all but the mesh's few coincident vertices, which have no
    normal), most at the floor itself (not left at 8 µm: 326 refitted before the floor was a rung)."""
    from nemo.morphology import RIM_MIN_EDGES, mean_edge_length

    mesh = torus_mesh(20.0, 4.0)  # the floor: 6 edges (half the radius, 4 µm, is smaller)
    df = curvature(mesh, 8.0, rng=0, smooth=0, local_fraction=0.65)
    at_floor = np.isclose(df["fit_radius"], RIM_MIN_EDGES * mean_edge_length(mesh))
    assert df.attrs["local_fits"] > 0.99 * len(mesh.vertices) and at_floor.mean() > 0.95, (df.attrs, at_floor.mean())


def test_a_flat_enough_surface_keeps_one_radius(sphere15):
    """A sphere of 15 µm at radius 5 µm (a third of its radius of curvature): no vertex is refitted,
    and the table equals the one-radius fit's."""
    local = curvature(sphere15, 5.0, rng=0, local_fraction=0.65)
    one = curvature(sphere15, 5.0, rng=0)
    assert local.attrs["local_fits"] == 0 and (local["fit_radius"] == 5.0).all()
    pd.testing.assert_frame_equal(local, one)


def test_the_averages_at_several_widths_are_the_single_width_averages(sphere15):
    """_diffuse_widths shares one series (or one chain of kernels) between the widths σ √2^k; each
    equals the debiased average at its own width, NaN kept."""
    import nemo.morphology as nm

    walk = nm._surface_walk(sphere15, nm.vertex_normals(sphere15))
    values = np.asarray(sphere15.vertices)[:, :2] ** 2
    values[::50, 1] = np.nan
    for sigma in (1.0, 6.0):  # one series; a chain (τ beyond SERIES_MAX_STEPS)
        widths = [sigma * 2 ** (j / 2) for j in nm.ADAPT_STEPS]
        for width, together in zip(widths, nm._diffuse_widths(walk, values, widths)):
            alone = nm._diffuse(walk, values, width, debias=True)[0]
            np.testing.assert_allclose(together, alone, rtol=2e-4, atol=2e-4 * np.nanmax(np.abs(values)))
            assert np.array_equal(np.isnan(together), np.isnan(values))


def test_the_widest_agreeing_width_is_chosen_per_value():
    """Intersection of confidence intervals: the widest average within ±2 noise of every narrower one."""
    from nemo.morphology import _agreeing_width

    noise = np.array([[1.0], [0.5], [0.25]])  # narrow → wide
    averages = np.array([[[10.0], [10.0], [10.0]],    # all agree: the widest
                         [[10.5], [14.0], [10.3]],    # the middle width disagrees: the narrowest
                         [[10.2], [11.5], [13.0]]])   # the widest alone disagrees: the middle
    averages = averages.transpose(1, 0, 2)  # (L, N, C)
    chosen, level = _agreeing_width(averages, noise)
    assert level[:, 0].tolist() == [2, 0, 1]
    assert chosen[:, 0].tolist() == [10.0, 10.5, 11.5]


def test_the_adaptive_average_keeps_a_tip_and_averages_a_uniform_wall():
    """Noise-free ellipsoid 30 × 15 × 15 µm (tips' radius of curvature 7.5 µm), radius 5 µm and a
    wide average (0.7 × the radius): one width flattens the tips' peak of H by 6.7 % (measured); the
    adaptive width (per value, the widest that agrees with the narrower ones) by 3.7 %; on a noisy
    sphere, where nothing peaks, the adaptive average keeps the width (as good as one width)."""
    abc = (30.0, 15.0, 15.0)
    mesh = ellipsoid_mesh(abc)
    H_true, _ = ellipsoid_HK(closest_on_ellipsoid(np.asarray(mesh.vertices), abc), abc)
    tip = np.abs(np.asarray(mesh.vertices)[:, 0]) > 28.0
    one = curvature(mesh, 5.0, rng=0, local_fraction=0, adaptive=False, smooth=0.7)
    adaptive = curvature(mesh, 5.0, rng=0, local_fraction=0, smooth=0.7)
    e_one, e_adaptive = (np.median(df["H"][tip] / H_true[tip] - 1) for df in (one, adaptive))
    assert e_one < -0.05 and abs(e_adaptive) < 0.65 * abs(e_one), (e_one, e_adaptive)
    rng = np.random.default_rng(1)
    sphere = sphere_mesh(15.0)
    noisy = trimesh.Trimesh(sphere.vertices + 0.15 * rng.normal(size=sphere.vertices.shape), sphere.faces, process=False)
    tables = [curvature(noisy, 5.0, rng=0, adaptive=a) for a in (False, True)]
    errors = [np.nanmedian(np.abs(df["H"] * 15.0 - 1)) for df in tables]
    assert errors[1] <= 1.05 * errors[0] < 0.15, errors  # 0.102 against 0.103 (measured)
    assert tables[0]["H"].isna().sum() == tables[1]["H"].isna().sum() < 0.01 * len(sphere.vertices)


def test_radius_too_small_gives_nan_and_warning(sphere15):
    with pytest.warns(NemoWarning, match=r"radius 0\.4 µm .*larger radius"):
        df = curvature(sphere15, radius=0.4, rng=0)
    assert df["H"].isna().all() and df["K"].isna().all()
    assert len(df) == len(sphere15.vertices)


def test_curvature_radius_too_large_warns():
    ico = trimesh.creation.icosphere(subdivisions=3, radius=30.0)
    mesh = make_mesh(ico.vertices, ico.faces)
    with pytest.warns(NemoWarning, match="large for this surface"):
        curvature(mesh, 1000.0, rng=0)


def test_partly_too_small_radius_only_local_nan():
    """A mesh that is dense on one side and coarse on the other: NaN only where too coarse."""
    fine = sphere_mesh(12.0, spacing=(0.5, 0.5, 0.5))
    v = np.asarray(fine.vertices).copy()
    # keep the upper half dense, thin the lower half: drop faces below z = 0 and add a coarse cap
    coarse = sphere_mesh(12.0, spacing=(3.0, 3.0, 3.0))
    up = fine.submesh([np.flatnonzero(fine.triangles_center[:, 2] > 0)], append=True)
    lo = coarse.submesh([np.flatnonzero(coarse.triangles_center[:, 2] < -1)], append=True)
    mesh = make_mesh(np.vstack([up.vertices, lo.vertices]),
                     np.vstack([up.faces, lo.faces + len(up.vertices)]), orient_outward=False)
    with pytest.warns(NemoWarning, match="too small"):
        df = curvature(mesh, radius=1.6, fraction=1.0, rng=0)
    v = np.asarray(mesh.vertices)
    assert df["H"][v[:, 2] > 2].notna().mean() > 0.99
    assert df["H"][v[:, 2] < -2].isna().mean() > 0.9
    del fine


def test_open_hemisphere_curvature_and_measure(sphere15):
    R = 15.0
    up = np.flatnonzero(sphere15.triangles_center[:, 2] > 0.1)
    sub = sphere15.submesh([up], append=True)
    cap = make_mesh(sub.vertices, sub.faces, orient_outward=False)
    assert np.median(np.einsum("ij,ij->i", cap.vertex_normals, cap.vertices - (0.3, -0.2, 0.1))) > 0
    df = curvature(cap, radius=4.0, rng=0)
    # fits whose 4 µm ball reaches the rim (z ≈ 0) would be one-sided: NaN, not a biased value
    z = np.asarray(cap.vertices)[:, 2]
    assert df["H"][z < 3.5].isna().all() and df["K"][z < 3.5].isna().all()
    assert df["H"][z > 4.5].notna().all() and df.attrs["rim_vertices"] == int(df["H"].isna().sum())
    assert abs(np.median(df["H"].dropna()) * R - 1) < 0.02
    assert np.percentile(np.abs(df["H"].dropna() * R - 1), 95) < 0.05
    res = measure(cap, df)
    assert res["gauss_bonnet_ratio_fit"] is None  # the fitted ∫K misses the rim band
    assert res["mean_H_fit"] * R == pytest.approx(1.0, abs=0.02)
    res = measure(cap)
    assert res["volume"] is None and not res["is_watertight"]
    assert res["n_boundary_loops"] == 1 and res["euler_characteristic"] == 1 and res["genus"] == 0
    assert res["gauss_bonnet_ratio"] == pytest.approx(1.0, abs=1e-9)  # with ∫k_g ds
    assert res["integral_K"] == pytest.approx(2 * np.pi * (1 - 0.1 / R), rel=0.05)
    assert any("open" in note for note in res["notes"])


def test_curvature_bad_input(sphere15):
    with pytest.raises(NemoError, match="positive"):
        curvature(sphere15, radius=0)
    with pytest.raises(NemoError, match="positive"):
        curvature(sphere15, radius=-2)
    with pytest.raises(NemoError, match="not both"):
        curvature(sphere15, radius=3, n_samples=10, fraction=0.5)
    with pytest.raises(NemoError, match="fraction"):
        curvature(sphere15, radius=3, fraction=1.5)
    with pytest.raises(NemoError, match="fit"):
        curvature(sphere15, radius=3, fit="cubic")


# --------------------------------------------------------------------------------------------
# measure
# --------------------------------------------------------------------------------------------


def test_measure_sphere_and_gauss_bonnet(sphere15):
    R = 15.0
    df = curvature(sphere15, radius=5.0, rng=0)
    res = measure(sphere15, df)
    assert res["area"] == pytest.approx(4 * np.pi * R**2, rel=0.01)
    assert res["volume"] == pytest.approx(4 / 3 * np.pi * R**3, rel=0.01)
    assert res["euler_characteristic"] == 2 and res["genus"] == 0 and res["n_components"] == 1
    assert res["gauss_bonnet_ratio"] == pytest.approx(1.0, abs=1e-9)
    assert res["gauss_bonnet_ratio_fit"] == pytest.approx(1.0, abs=0.02)
    assert res["mean_H"] == pytest.approx(1 / R, rel=0.01)
    assert res["mean_H_fit"] == pytest.approx(1 / R, rel=0.01)
    assert res["unit"] == "um"
    json.dumps(res)  # serialisable as is


def test_measure_two_components_and_vertex_areas():
    a = sphere_mesh(6.0, centre=(0, 0, 0))
    b = sphere_mesh(6.0, centre=(0, 0, 0))
    mesh = make_mesh(np.vstack([a.vertices, np.asarray(b.vertices) + (20, 0, 0)]),
                     np.vstack([a.faces, b.faces + len(a.vertices)]))
    res = measure(mesh)
    assert res["n_components"] == 2 and res["euler_characteristic"] == 4 and res["genus"] == 0
    assert res["gauss_bonnet_ratio"] == pytest.approx(1.0, abs=1e-9)
    assert vertex_areas(mesh).sum() == pytest.approx(mesh.area, rel=1e-12)
    assert (vertex_areas(mesh) >= 0).all()


def _rolled_strip(n_around=24, n_up=6, crack=False):
    """A strip rolled around the z axis (r 10 µm) whose two ends meet only at the bottom corner
    (the top is narrower: θ = 2π u (1 − 0.3 v)): a disk whose rim touches itself at one point,
    two distinct vertices at the same place, as a split leaves where its cut plane runs through
    a vertex. ``crack``: the ends meet along their whole edge (a tube cut open along a line, as
    marching cubes leaves duplicated vertices)."""
    u, v = np.meshgrid(np.linspace(0, 1, n_around + 1), np.linspace(0, 1, n_up + 1), indexing="ij")
    theta = 2 * np.pi * u * (1.0 if crack else (1.0 - 0.3 * v))
    verts = np.stack([10 * np.cos(theta), 10 * np.sin(theta), 5 * v], axis=-1).reshape(-1, 3)
    verts = verts.reshape(n_around + 1, n_up + 1, 3)
    verts[-1, : (n_up + 1 if crack else 1)] = verts[0, : (n_up + 1 if crack else 1)]  # exactly coincident
    ids = np.arange((n_around + 1) * (n_up + 1)).reshape(n_around + 1, n_up + 1)
    a, b, c, d = ids[:-1, :-1], ids[1:, :-1], ids[1:, 1:], ids[:-1, 1:]
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return verts.reshape(-1, 3), faces


def test_measure_keeps_a_rim_that_touches_itself_apart():
    """Coincident vertices are merged to close marching-cubes cracks (the cut tube is a tube,
    χ 0), but two rim vertices at one place are not joined: the strip is a disk (χ 1, one rim
    loop); merged, it read χ 0 (a split wall read −1)."""
    import trimesh

    from nemo.morphology import _topology

    verts, faces = _rolled_strip()
    assert len(np.unique(verts, axis=0)) == len(verts) - 1
    topo = _topology(verts, faces)
    assert topo["chi"] == 1 and topo["n_loops"] == 1 and topo["n_components"] == 1
    res = measure(trimesh.Trimesh(verts, faces, process=False))
    assert res["euler_characteristic"] == 1 and res["genus"] == 0
    tube = _topology(*_rolled_strip(crack=True))
    assert tube["chi"] == 0 and tube["n_loops"] == 2 and tube["watertight"] is False


def test_averaging_width_is_capped_at_the_object(sphere15, monkeypatch):
    """smooth × radius far beyond the object (σ = 400 µm on a sphere of 15 µm) took 7 minutes for a
    kernel that is uniform from σ ≈ 2 R on: the width is capped at twice the object's radius."""
    import nemo.morphology as nm

    widths = []
    real = nm._robust_average

    def spy(walk, values, sigma, noisier=None, adaptive=False):
        widths.append(sigma * (2.0 ** (max(nm.ADAPT_STEPS) / 2.0) if adaptive else 1.0))  # the widest width
        return real(walk, values, sigma, noisier, adaptive)

    monkeypatch.setattr(nm, "_robust_average", spy)
    with pytest.warns(NemoWarning):  # the radius is too large for the surface
        curvature(sphere15, 200.0, rng=0, smooth=2.0)
    curvature(sphere15, 5.0, rng=0)
    assert widths[0] == pytest.approx(2 * np.sqrt(sphere15.area / (4 * np.pi)))
    assert widths[1] == pytest.approx(0.35 * 5.0 * 2.0 ** (max(nm.ADAPT_STEPS) / 2.0))
    values = np.asarray(sphere15.vertices)[:, 2]
    wide, products = nm.smooth_on_surface(sphere15, values, 1000.0)
    capped, capped_products = nm.smooth_on_surface(sphere15, values, widths[0])
    assert products == capped_products and np.array_equal(wide, capped)


def test_measure_flags_inconsistent_winding_and_non_manifold():
    import trimesh

    box = trimesh.creation.box(extents=(2.0, 3.0, 4.0))
    res = measure(make_mesh(box.vertices, box.faces))
    assert res["volume"] == pytest.approx(24.0) and res["area"] == pytest.approx(52.0)
    assert res["mean_H"] == pytest.approx(0.5 * (np.pi / 2) * 4 * (2 + 3 + 4) / 52.0)  # ½ Σ ℓ θ / A
    flipped = box.faces.copy()
    flipped[0] = flipped[0][::-1]
    res = measure(make_mesh(box.vertices, flipped, orient_outward=False))
    assert res["volume"] is None and any("winding" in note for note in res["notes"])
    # a third face on the box edge (0, 1): non-manifold, no genus
    res = measure(make_mesh(box.vertices, np.vstack([box.faces, [[0, 1, 7]]]), orient_outward=False))
    assert res["genus"] is None and any("non-manifold" in note for note in res["notes"])


# --------------------------------------------------------------------------------------------
# thickness
# --------------------------------------------------------------------------------------------


def _exact_sphere_t(v, n, centre, R):
    p = v - centre
    b = np.einsum("ij,ij->i", p, n)
    return -b + np.sqrt(b * b - (np.einsum("ij,ij->i", p, p) - R * R))


@pytest.mark.parametrize("spacing", [ISO, ANISO], ids=["iso", "dz=2dx"])
def test_thickness_concentric_spheres(spacing):
    c = np.array([0.3, -0.2, 0.1])
    inner, outer = sphere_mesh(12.0, spacing, c), sphere_mesh(17.0, spacing, c)
    d = thickness(inner, outer, "outward")
    exact = _exact_sphere_t(np.asarray(inner.vertices), np.asarray(inner.vertex_normals), c, 17.0)
    assert np.isfinite(d).all()
    assert np.abs(d - exact).max() < 0.25 * min(spacing)
    # from the outer surface inward: negative, same magnitude
    d_in = thickness(outer, inner, "inward")
    assert np.nanmax(d_in) < 0 and np.median(np.abs(d_in + 5.0)) < 0.05
    # outward from the outer surface nothing is hit: NaN, never a value
    assert np.isnan(thickness(outer, inner, "outward")).all()
    # nearest: the closer of the two directions (here the inward one)
    np.testing.assert_array_equal(thickness(outer, inner, "nearest"), d_in)


@pytest.mark.parametrize("spacing", [ISO, ANISO], ids=["iso", "dz=2dx"])
def test_thickness_concentric_ellipsoids(spacing):
    small, big = (20.0, 15.0, 11.0), (25.0, 21.0, 18.0)
    inner, outer = ellipsoid_mesh(small, spacing), ellipsoid_mesh(big, spacing)
    v, n = np.asarray(inner.vertices), np.asarray(inner.vertex_normals)
    exact = ray_ellipsoid(v, n, big)  # along each vertex's actual normal
    d = thickness(inner, outer, "outward")
    assert np.isfinite(d).all()  # also at duplicated vertices (zero normal: the twin's is used)
    ok = np.linalg.norm(n, axis=1) > 0.5
    err = np.abs(d - exact)[ok]
    assert err.max() < 0.25 * min(spacing), err.max()
    # and back along the outer surface's normals, inward
    vo, no = np.asarray(outer.vertices), np.asarray(outer.vertex_normals)
    d_back = thickness(outer, inner, "inward")
    ok = np.linalg.norm(no, axis=1) > 0.5
    exact_back = -ray_ellipsoid(vo[ok], -no[ok], small)
    assert np.abs(d_back[ok] - exact_back).max() < 0.25 * min(spacing)


def test_thickness_misses_and_max_distance():
    c = np.array([0.0, 0.0, 0.0])
    inner, outer = sphere_mesh(12.0, ISO, c), sphere_mesh(17.0, ISO, c)
    # open target: only the upper cap of the outer sphere
    cap_faces = np.flatnonzero(outer.triangles_center[:, 2] > 4.0)
    sub = outer.submesh([cap_faces], append=True)
    cap = make_mesh(sub.vertices, sub.faces, orient_outward=False)
    d = thickness(inner, cap, "outward")
    v, n = np.asarray(inner.vertices), np.asarray(inner.vertex_normals)
    hit_z = (v + _exact_sphere_t(v, n, c, 17.0)[:, None] * n)[:, 2]
    assert np.isnan(d[hit_z < 3.0]).all()  # rays that miss the cap: NaN
    assert np.isfinite(d[hit_z > 5.0]).all()
    # max_distance: all hits are at 5 µm
    assert np.isnan(thickness(inner, outer, max_distance=4.9)).all()
    assert np.isfinite(thickness(inner, outer, max_distance=5.1)).all()
    dn = thickness(outer, inner, "nearest", max_distance=4.9)
    assert np.isnan(dn).all()


def _cut(mesh, k, lo=-np.inf, hi=np.inf):
    """The part of ``mesh`` between ``lo`` and ``hi`` along axis ``k`` with its rim put on those planes,
    as ``mesh.border: open`` leaves a surface cut by the image's border."""
    centre = mesh.triangles_center[:, k]
    part = mesh.submesh([np.flatnonzero((centre > lo) & (centre < hi))], append=True)
    verts = np.array(part.vertices)
    on_rim = rim(np.asarray(part.faces), len(verts))["vertices"]
    verts[on_rim, k] = np.where(np.abs(verts[on_rim, k] - lo) < np.abs(verts[on_rim, k] - hi), lo, hi)
    return make_mesh(verts, part.faces, unit="um", orient_outward=False)


def _torn(mesh, axis, degrees):
    """``mesh`` without its faces within ``degrees`` of the direction ``axis`` (from the origin)."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    centres = mesh.triangles_center
    keep = centres @ axis < np.cos(np.radians(degrees)) * np.linalg.norm(centres, axis=1)
    return make_mesh(*_faces_kept(mesh, keep), unit="um", orient_outward=False)


def test_rays_that_leave_the_view_through_the_cut_are_told_from_a_hole():
    """A shell (R 20 / 26 µm) cut 5 µm below its centre: an inner vertex whose radial ray meets the
    outer sphere below the cut (u_z < −5/26) misses because the view ends there. A hole in the outer
    wall makes misses that are not the view's: one whose rays leave through an uncut face, and one
    beside a cut (the shell cut at x = ±15 µm, a hole towards (0.5, 0, 0.6)), whose rays leave
    through the cut face but from outside the wall."""
    c = np.zeros(3)
    inner, outer = (_cut(sphere_mesh(r, ISO, c), 2, lo=-5.0) for r in (20.0, 26.0))
    v = np.asarray(inner.vertices)
    u_z = v[:, 2] / np.linalg.norm(v, axis=1)
    d = thickness(inner, outer)
    missed = np.isnan(d)
    beyond = beyond_view(inner, outer, missed)
    below = u_z < -5.0 / 26.0 - 0.01
    assert below.sum() > 100 and missed[below].all() and beyond[below].all()
    assert not missed[u_z > -5.0 / 26.0 + 0.01].any() and not beyond[~missed].any()
    torn = _torn(outer, [1.0, 1.0, 1.0], 15.0)  # its rays leave through the upper faces: no rim there
    d_torn = thickness(inner, torn)
    hole = np.isnan(d_torn) & ~missed
    beyond_torn = beyond_view(inner, torn, np.isnan(d_torn))
    assert hole.sum() > 20 and not beyond_torn[hole].any() and beyond_torn[below].all()
    # "nearest": a NaN is two misses; a hole's outward ray escapes even where the inward one leaves the view
    nearest = np.isnan(thickness(inner, torn, "nearest"))
    beyond_nearest = beyond_view(inner, torn, nearest, "nearest")
    assert nearest[hole].sum() > 20 and not beyond_nearest[hole].any()
    whole = sphere_mesh(20.0, ISO, c)
    assert not beyond_view(whole, sphere_mesh(26.0, ISO, c), np.ones(len(whole.vertices), bool)).any()
    # a hole beside the cut: its rays leave through the cut face, but outside the wall
    inner, outer = (_cut(sphere_mesh(r, ISO, c), 0, lo=-15.0, hi=15.0) for r in (20.0, 26.0))
    missed = np.isnan(thickness(inner, outer))
    torn = _torn(outer, [0.5, 0.0, 0.6], 12.0)
    d_torn = thickness(inner, torn)
    hole = np.isnan(d_torn) & ~missed
    beyond_torn = beyond_view(inner, torn, np.isnan(d_torn))
    assert missed.sum() > 500 and beyond_torn[missed].all()
    assert hole.sum() > 10 and not beyond_torn[hole].any()


def _faces_kept(mesh, keep):
    part = mesh.submesh([np.flatnonzero(keep)], append=True)
    return np.asarray(part.vertices), np.asarray(part.faces)


def test_thickness_touching_and_self():
    c = np.array([0.0, 0.0, 0.0])
    sph = sphere_mesh(12.0, ISO, c)
    # the target shares the upper half of the surface: rays start exactly on it -> 0, not a miss
    up = sph.submesh([np.flatnonzero(sph.triangles_center[:, 2] > 0)], append=True)
    half = make_mesh(up.vertices, up.faces, orient_outward=False)
    d = thickness(sph, half, "outward")
    z = np.asarray(sph.vertices)[:, 2]
    assert np.abs(d[z > 1.0]).max() < 1e-6
    assert np.isnan(d[z < -1.0]).all()
    # the same mesh as target: inward rays cross to the opposite side (a diameter)
    d_self = thickness(sph, sph, "inward")
    assert np.median(d_self) == pytest.approx(-24.0, abs=0.1)


def test_thickness_bad_input(sphere15):
    with pytest.raises(NemoError, match="direction"):
        thickness(sphere15, sphere15, "sideways")
    with pytest.raises(NemoError, match="max_distance"):
        thickness(sphere15, sphere15, max_distance=0)


def test_thickness_refuses_a_mesh_in_another_unit_and_warns_on_misses(tmp_path, run_cli):
    """A wall exported in nm (× 1000) gave 100 % NaN with exit 0 and no word."""
    c = np.array([0.0, 0.0, 0.0])
    inner, outer = sphere_mesh(12.0, ISO, c), sphere_mesh(17.0, ISO, c)
    outer_nm = make_mesh(np.asarray(outer.vertices) * 1000.0, outer.faces)
    with pytest.raises(NemoError, match="differ in size by × 1e\\+03|another unit"):
        thickness(inner, outer_nm)
    far = make_mesh(np.asarray(outer.vertices) + [500.0, 0, 0], outer.faces)
    with pytest.raises(NemoError, match="are 4.* apart, more than either is large"):
        thickness(inner, far)
    lumen = sphere_mesh(3.0, ISO, c)  # an organoid (R 17) and its lumen (R 3): ratio 5.7 is fine
    assert np.isfinite(thickness(outer, lumen, "inward")).all()
    upper = make_mesh(np.asarray(inner.vertices) + [0, 0, 30.0], inner.faces)  # disjoint boxes, near
    thickness(inner, upper, "outward", max_distance=100)
    with pytest.warns(NemoWarning, match="100 % of the rays"):
        thickness(outer, inner, "outward")  # the inner wall lies inward: every ray misses
    save_mesh(inner, tmp_path / "in.ply")
    save_mesh(outer_nm, tmp_path / "out_nm.ply")
    code, _, err = run_cli("thickness", tmp_path / "in.ply", tmp_path / "out_nm.ply", "-o", tmp_path / "t.parquet")
    assert code == 2 and "nemo thickness: error: the two meshes differ in size" in err
    assert not (tmp_path / "t.parquet").exists()


# --------------------------------------------------------------------------------------------
# CLI
# --------------------------------------------------------------------------------------------


def test_cli_curvature_thickness_measure(tmp_path, run_cli):
    c = (0.0, 0.0, 0.0)
    save_mesh(sphere_mesh(12.0, ISO, c), tmp_path / "in.ply")
    save_mesh(sphere_mesh(16.0, ISO, c), tmp_path / "out.ply")

    code, out, err = run_cli("curvature", tmp_path / "in.ply", "-o", tmp_path / "c.parquet",
                             "--radius", "4", "--fraction", "0.5", "--seed", "2")
    assert code == 0, err
    assert "median H" in out and "NaN: 0" in out
    df = read_table(tmp_path / "c.parquet", "curvature")
    assert np.median(df["H"]) == pytest.approx(1 / 12, rel=0.02)
    prov = read_provenance(tmp_path / "c.parquet")
    assert prov["command"] == "curvature" and prov["unit"] == "um"
    assert prov["parameters"]["radius"] == 4 and prov["parameters"]["seed"] == 2
    assert prov["inputs"]["mesh"].endswith("in.ply")

    code, out, err = run_cli("thickness", tmp_path / "in.ply", tmp_path / "out.ply",
                             "-o", tmp_path / "t.parquet", "--direction", "nearest")
    assert code == 0, err
    assert "NaN" in out and "0 of" in out
    t = read_table(tmp_path / "t.parquet", "thickness")
    assert np.median(t["thickness"]) == pytest.approx(4.0, abs=0.05)
    assert read_provenance(tmp_path / "t.parquet")["parameters"]["direction"] == "nearest"

    code, out, err = run_cli("thickness", tmp_path / "out.ply", tmp_path / "in.ply",
                             "-o", tmp_path / "t2.parquet")
    assert code == 0 and f"{len(t)} of {len(t)}" not in out  # counts differ: outer mesh
    assert read_table(tmp_path / "t2.parquet", "thickness")["thickness"].isna().all()

    code, out, err = run_cli("measure", tmp_path / "in.ply", "--json", "--curvature", tmp_path / "c.parquet")
    assert code == 0, err
    res = json.loads(out)
    assert res["euler_characteristic"] == 2 and res["gauss_bonnet_ratio_fit"] == pytest.approx(1, abs=0.03)
    code, out, err = run_cli("measure", tmp_path / "in.ply")
    assert code == 0 and "Gauss–Bonnet ratio 1" in out


def test_cli_errors(tmp_path, run_cli):
    save_mesh(sphere_mesh(6.0), tmp_path / "s.ply")
    code, out, err = run_cli("curvature", tmp_path / "missing.ply", "-o", tmp_path / "c.parquet", "--radius", "2")
    assert code == 2 and "not found" in err and "Traceback" not in err
    code, out, err = run_cli("curvature", tmp_path / "s.ply", "-o", tmp_path / "c.csv", "--radius", "2")
    assert code == 2 and ".parquet" in err
    code, out, err = run_cli("curvature", tmp_path / "s.ply", "-o", tmp_path / "c.parquet", "--radius", "0.2")
    assert code == 0 and "warning" in err and "radius 0.2" in err
    with pytest.raises(SystemExit) as exc:  # argparse rejects it before any work
        run_cli("thickness", tmp_path / "s.ply", tmp_path / "s.ply", "-o", tmp_path / "t.parquet",
                "--max-distance", "-1")
    assert exc.value.code == 2
    (tmp_path / "bad.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nend_header\n\x00")
    code, out, err = run_cli("measure", tmp_path / "bad.ply")
    assert code == 2 and "Traceback" not in err


def test_cli_thickness_and_curvature_record_their_mesh_and_measure_refuses_another(meshed_shell, tmp_path,
                                                                                   run_cli, cli_error):
    shell = meshed_shell
    n_inner = len(load_mesh(shell / "m.inner.ply").vertices)
    code, _, err = run_cli("thickness", shell / "m.inner.ply", shell / "m.outer.ply", "-o", tmp_path / "th.parquet")
    assert code == 0, err
    prov = read_provenance(tmp_path / "th.parquet")
    assert prov["mesh"] == str(shell / "m.inner.ply") and prov["n_vertices"] == n_inner
    code, _, err = run_cli("curvature", shell / "m.inner.ply", "-o", tmp_path / "k.parquet", "--radius", "3")
    assert code == 0, err
    assert read_provenance(tmp_path / "k.parquet")["n_vertices"] == n_inner
    # the inner half's curvature measured on the outer half
    code, _, err = run_cli("measure", shell / "m.outer.ply", "--curvature", tmp_path / "k.parquet")
    cli_error(code, err, "k.parquet", "vertices")


# --------------------------------------------------------------------------------------------
# default radius (issue 12): meshes reconstructed from rendered images
# --------------------------------------------------------------------------------------------


def render(sdf, half, spacing, psf, noise=3.0, photons=20.0, rng=0, rot=None):
    """A (Z, Y, X) image of the solid sdf < 0 centred in the stack, and its centre (x, y, z).

    The edge is rendered at sub-voxel precision: intensity 20 + 180 · ½ erfc(d / √2 s), d the
    signed distance at the voxel centre and s² = Σ (n_i σ_i)² + (n_x² + n_y²) dx²/12 the
    z-elongated Gaussian PSF (σz, σy, σx) and the pixel's box along the surface normal n (a
    locally planar edge convolved with both), then shot noise (``photons`` per grey level) and
    Gaussian noise. ``rot`` turns the shape (sdf of rot⁻¹ p).
    """
    from scipy.special import erfc

    dz, dy, dx = spacing
    sp = np.array([dx, dy, dz])
    n = (2 * np.ceil((np.asarray(half, float) + 4 * max(psf) + 3 * sp) / sp) + 1).astype(int)
    centre = (n - 1) / 2 * sp
    axes = [np.arange(k) * s - c for k, s, c in zip(n, sp, centre)]
    Z, Y, X = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    p = np.stack([X, Y, Z], -1)
    f = sdf if rot is None else (lambda q: sdf(q @ rot))
    d = f(p)
    eps = 0.25 * min(spacing)
    g = np.stack([f(p + eps * e) - f(p - eps * e) for e in np.eye(3)], -1)
    g /= np.maximum(np.linalg.norm(g, axis=-1, keepdims=True), 1e-12)
    s2 = (g**2 * np.asarray(psf[::-1]) ** 2).sum(-1) + (g[..., 0] ** 2 + g[..., 1] ** 2) * dx * dx / 12
    vol = 20 + 180 * 0.5 * erfc(d / np.sqrt(2 * np.maximum(s2, 1e-12)))
    gen = np.random.default_rng(rng)
    vol = gen.poisson(vol * photons) / photons + gen.normal(0, noise, vol.shape)
    return np.clip(vol, 0, None).astype(np.float32), centre


def reconstructed(volume, spacing):
    from nemo.surface import reconstruct

    return reconstruct(volume, spacing)  # the defaults of `nemo mesh`


def ellipsoid_sdf(p, abc):
    a = np.asarray(abc, float)
    q = np.sqrt(((p / a) ** 2).sum(-1))
    grad = np.linalg.norm(p / a**2, axis=-1) / np.maximum(q, 1e-12)
    return (q - 1.0) / np.maximum(grad, 1e-12)


def torus_sdf(p, Rt, r):
    return np.hypot(np.hypot(p[..., 0], p[..., 1]) - Rt, p[..., 2]) - r


def torus_HK(p, Rt, r):
    """Analytic H (outward normal) and K of a torus (axis z) at the nearest surface points."""
    rho = np.hypot(p[:, 0], p[:, 1])
    cosv = (rho - Rt) / np.maximum(np.hypot(rho - Rt, p[:, 2]), 1e-12)
    den = r * (Rt + r * cosv)
    return (Rt + 2 * r * cosv) / (2 * den), cosv / den


def median_rel_errors(df, H_true, K_true):
    ok = df["H"].notna().to_numpy()
    eh = np.median(np.abs(df["H"].to_numpy()[ok] / H_true[ok] - 1))
    ek = np.median(np.abs(df["K"].to_numpy()[ok] / K_true[ok] - 1))
    return eh, ek


BIG_ELL = (60.0, 40.0, 30.0)


@pytest.fixture(scope="module")
def imaged_ellipsoid():
    """Ellipsoid 60 × 40 × 30 µm, 1 µm pixels, dz = 2 µm, PSF σ (1.2, 0.4, 0.4) µm, SNR ≈ 20."""
    vol, c = render(lambda p: ellipsoid_sdf(p, BIG_ELL), BIG_ELL, (2.0, 1.0, 1.0), (1.2, 0.4, 0.4))
    return reconstructed(vol, (2.0, 1.0, 1.0)), c


@pytest.mark.parametrize("R, spacing", [(6.0, ISO), (15.0, ANISO), (10.0, (1.0, 0.4, 0.4))],
                         ids=["R6-iso", "R15-dz2", "R10-0.4um"])
def test_default_radius_spheres(R, spacing):
    from nemo.morphology import default_radius

    mesh = sphere_mesh(R, spacing)
    radius, info = default_radius(mesh)
    # R = 6 µm is only 6.3 edges: the radius of 4 edges (the fewest) is 0.63 R there
    assert info["limited_by"] in (("min_edges",) if R < 8 else ("stability", "size")) and info["rim_cap"] is None
    assert info["curvature_radius"] == pytest.approx(R, rel=0.05)
    assert radius <= 0.7 * R and radius == info["radius"]
    df = curvature(mesh, radius, n_samples=3000, rng=0)
    assert df.attrs["fit"] == "quartic"
    assert abs(np.median(df["H"]) * R - 1) < 0.015
    assert np.mean(np.abs(df["H"] * R - 1)) < 0.025
    json.dumps(info)


def test_default_radius_droplets():
    """Issue 12: droplets R ≈ 10 µm, 0.4 µm pixels and 1 µm planes, σxy 0.15–0.2 µm, σz 0.5–0.6 µm:
    mean |H R − 1| ≤ 0.025 with no radius given (the old 15 edges ≤ 0.5 R_obj gave 0.014–0.018
    on these noisy images, 0.04–0.07 on worse-rendered ones; see docs/validation.md)."""
    from nemo.morphology import default_radius

    for i, (R, sxy, sz) in enumerate([(10.0, 0.15, 0.5), (9.3, 0.2, 0.6)]):
        vol, c = render(lambda p, R=R: np.linalg.norm(p, axis=-1) - R, (R, R, R), (1.0, 0.4, 0.4),
                        (sz, sxy, sxy), rng=i)
        mesh = reconstructed(vol, (1.0, 0.4, 0.4))
        radius, info = default_radius(mesh)
        df = curvature(mesh, radius, rng=0)
        assert np.mean(np.abs(df["H"] * R - 1)) <= 0.025


def test_default_radius_widens_on_a_noisy_wall():
    """A ball of R = 15 µm at SNR ≈ 5 (0.5 µm voxels): at the floor radius (4 edges) the fits
    read the wall's roughness (|H R − 1| ≈ 2.8 there); the pilot's curvature keeps changing with
    the radius up to its top (0.6 × the size), so the radius goes there, and a fit there is within
    5 % of 1/R per vertex (the former rule, 15 edges, read 6.5 %)."""
    from nemo.morphology import default_radius, mean_edge_length

    R = 15.0
    vol, _ = render(lambda p: np.linalg.norm(p, axis=-1) - R, (R, R, R), (0.5, 0.5, 0.5), (1.0, 0.4, 0.4),
                    noise=36.0, rng=1)
    mesh = reconstructed(vol, (0.5, 0.5, 0.5))
    radius, info = default_radius(mesh)
    h = mean_edge_length(mesh)
    assert info["limited_by"] == "size" and radius > 15 * h and info["curvature_radius"] > 0.75 * R, info
    err = np.nanmedian(np.abs(curvature(mesh, radius, rng=0)["H"] * R - 1))
    err_floor = np.nanmedian(np.abs(curvature(mesh, 4 * h, rng=0, smooth=0)["H"] * R - 1))  # the fits there
    assert err < 0.05 and err_floor > 1.0, (err, err_floor)


def test_default_radius_on_a_noisy_ellipsoid_beats_a_fixed_number_of_edges():
    """Ellipsoid 60 × 40 × 30 µm at dz = 2 dx, PSF σ 2.5 / 1 / 1 µm, shot + Gaussian noise (SNR
    ≈ 7): the noise, not the shape, limits a fit of 15 edges (the former default: H ≈ 6 %,
    K ≈ 13 %); the radius where the curvature is stablest (19 edges) brings them to 3.1–3.3 % and
    7.2–7.7 % over seeds 1–3 (still above issue 12's 2 / 3 %: the noise's share)."""
    from nemo.morphology import default_radius, mean_edge_length

    vol, c = render(lambda p: ellipsoid_sdf(p, BIG_ELL), BIG_ELL, (2.0, 1.0, 1.0), (2.5, 1.0, 1.0),
                    noise=18.0, photons=2.0, rng=3)
    mesh = reconstructed(vol, (2.0, 1.0, 1.0))
    H_true, K_true = ellipsoid_HK(closest_on_ellipsoid(np.asarray(mesh.vertices) - c, BIG_ELL), BIG_ELL)
    radius, info = default_radius(mesh)
    h = mean_edge_length(mesh)
    eh, ek = median_rel_errors(curvature(mesh, radius, rng=0, smooth=0), H_true, K_true)  # the fits alone
    eh15, ek15 = median_rel_errors(curvature(mesh, 15 * h, rng=0, smooth=0), H_true, K_true)
    assert radius > 16 * h and eh < 0.7 * eh15 and ek < 0.7 * ek15, (info, eh, ek, eh15, ek15)
    assert eh < 0.04 and ek < 0.09, (eh, ek)


def test_averaging_the_fits_over_the_surface_on_a_noisy_ellipsoid(ellipsoids):
    """The same noisy ellipsoid (SNR ≈ 7, z-PSF): where the noise dominates the fits (r = 16 µm,
    ~15 edges: H 5.7 %, K 13 %) the default averaging cuts both by 40 %; at the default radius it
    still lowers them; on the clean ellipsoids it does not raise them."""
    from nemo.morphology import DEFAULT_SMOOTH, default_radius

    vol, c = render(lambda p: ellipsoid_sdf(p, BIG_ELL), BIG_ELL, (2.0, 1.0, 1.0), (2.5, 1.0, 1.0),
                    noise=18.0, photons=2.0, rng=3)
    mesh = reconstructed(vol, (2.0, 1.0, 1.0))
    H_true, K_true = ellipsoid_HK(closest_on_ellipsoid(np.asarray(mesh.vertices) - c, BIG_ELL), BIG_ELL)
    radius, _ = default_radius(mesh)
    for r, factor in ((16.0, 0.65), (radius, 0.9)):
        raw = median_rel_errors(curvature(mesh, r, rng=0, smooth=0), H_true, K_true)
        df = curvature(mesh, r, rng=0)
        assert df.attrs["smooth"] == DEFAULT_SMOOTH
        averaged = median_rel_errors(df, H_true, K_true)
        assert averaged[0] < factor * raw[0] and averaged[1] < factor * raw[1], (r, raw, averaged)
    noisy_scatter = df.attrs["fit_scatter_H"] / np.median(H_true)  # the fits' noise, relative
    for spacing, mesh in ellipsoids.items():
        H_true, K_true = ellipsoid_HK(closest_on_ellipsoid(np.asarray(mesh.vertices), ELL), ELL)
        radius, _ = default_radius(mesh)
        raw = median_rel_errors(curvature(mesh, radius, rng=0, smooth=0), H_true, K_true)
        df = curvature(mesh, radius, rng=0)
        averaged = median_rel_errors(df, H_true, K_true)
        assert averaged[0] <= raw[0] and averaged[1] <= raw[1], (spacing, raw, averaged)
        assert df.attrs["fit_scatter_H"] / np.median(H_true) < noisy_scatter / 2


@pytest.mark.parametrize("sigma", [2.0, 3.0])
def test_smooth_on_surface_is_the_heat_kernel_on_a_sphere(sigma):
    """On a sphere the spherical harmonics Y_l decay under a Gaussian average of width σ by
    exp(−l(l + 1) σ² / 2R²); the debiased average 2 G_σ − G_√2σ by 2 e^−b − e^−2b (no σ² term)."""
    from nemo.morphology import smooth_on_surface

    R = 10.0
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=R)
    z = np.asarray(mesh.vertices)[:, 2]
    for degree, f in ((1, z), (2, 3 * z**2 - R**2)):
        b = degree * (degree + 1) / 2 * sigma**2 / R**2
        for debias, expected in ((False, np.exp(-b)), (True, 2 * np.exp(-b) - np.exp(-2 * b))):
            smoothed, products = smooth_on_surface(mesh, f, sigma, debias=debias)
            assert products > 1
            assert np.sum(smoothed * f) / np.sum(f * f) == pytest.approx(expected, abs=1e-3), (degree, debias)


def test_smooth_on_surface_does_not_drift_on_an_irregular_mesh(ellipsoids):
    """A marching-cubes mesh's vertices are uneven: a plain neighbour average drifts towards the
    denser ones and shifts a sloped field (0.4 % of H at σ = 1 µm, debiased); the tilted walk
    keeps the exact H of the ellipsoid within 0.15 % (0.05 %)."""
    from nemo.morphology import smooth_on_surface

    mesh = ellipsoids[ISO]
    H_true, _ = ellipsoid_HK(closest_on_ellipsoid(np.asarray(mesh.vertices), ELL), ELL)
    smoothed, _ = smooth_on_surface(mesh, H_true, 1.0, debias=True)
    assert np.median(np.abs(smoothed / H_true - 1)) < 1.5e-3


def test_smooth_on_surface_keeps_nan_and_objects_apart():
    """NaN values take no part and stay NaN; two objects never mix; σ = 0 changes nothing."""
    from nemo.morphology import smooth_on_surface

    a = trimesh.creation.icosphere(subdivisions=3, radius=5.0)
    b = trimesh.creation.icosphere(subdivisions=3, radius=5.0)
    b.apply_translation((10.5, 0, 0))  # 0.5 apart: a Euclidean ball would reach across
    both = trimesh.util.concatenate([a, b])
    values = np.concatenate([np.full(len(a.vertices), 1.0), np.full(len(b.vertices), 3.0)])
    values[: len(a.vertices)][a.vertices[:, 2] > 0] = np.nan
    smoothed, products = smooth_on_surface(both, np.stack([values, 2 * values], axis=1), 4.0, debias=True)
    assert products > 10
    assert np.array_equal(np.isnan(smoothed[:, 0]), np.isnan(values))
    assert np.allclose(smoothed[~np.isnan(values), 0], values[~np.isnan(values)], atol=1e-5)
    assert np.allclose(smoothed[:, 1], 2 * smoothed[:, 0], equal_nan=True)
    same, products = smooth_on_surface(both, values, 0.0)
    assert products == 0 and np.array_equal(same, values, equal_nan=True)
    for smooth in (-0.1, np.inf, np.nan, 3.0):
        with pytest.raises(NemoError, match="smoothing"):
            curvature(a, 2.0, smooth=smooth)
    with pytest.raises(NemoError, match="width"):
        smooth_on_surface(a, np.ones(len(a.vertices)), np.nan)
    with pytest.raises(NemoError, match="one row per vertex"):
        smooth_on_surface(a, np.ones(3), 1.0)


def test_smooth_on_surface_stays_within_the_values_at_a_large_width(ellipsoids):
    """The walk is not reversible: one Chebyshev series over ~1300 mean steps (σ = 20 edges)
    grew like 1.08^k and returned values 10⁴ × outside the input. A Gaussian average of values
    in [0, 1] stays in [0, 1]; the debiased one stays near a smooth field."""
    from nemo.morphology import smooth_on_surface

    mesh = ellipsoids[ISO]
    edge = float(np.mean(mesh.edges_unique_length))
    values = np.random.default_rng(0).random(len(mesh.vertices))
    smoothed, _ = smooth_on_surface(mesh, values, 20 * edge)
    assert smoothed.min() > -1e-4 and smoothed.max() < 1 + 1e-4
    x = np.asarray(mesh.vertices)[:, 0] / 30.0  # a smooth field, ±1 over the ellipsoid
    debiased, _ = smooth_on_surface(mesh, x, 10 * edge, debias=True)
    assert np.abs(debiased - x).max() < 0.1


def test_wild_fits_are_clipped_before_the_average(monkeypatch):
    """A cap of a rough SNR-5 ball (R 15 µm): a few wild fits (K of −100 / R²) would spread
    over the averaging's width (median K error 30 %, worse than the fits alone); clipped at
    3 robust SDs of their residual they do not (10 %)."""
    import nemo.morphology as nm
    import nemo.surface as ns
    from nemo.mesh import make_mesh

    R = 15.0
    vol, _ = render(lambda p: np.linalg.norm(p, axis=-1) - R, (R, R, R), (0.5, 0.5, 0.5), (1.0, 0.4, 0.4),
                    noise=36.0, rng=1)
    # the surface at the histogram's half level (the fixture measured): corrected from the walls' profiles
    # (session 32) this ball's surface is smoother and has fewer wild fits (unclipped 18 %, clipped 12 %)
    monkeypatch.setattr(ns, "EDGE_CHECK_MIN_CORRECTION", np.inf)
    ball = reconstructed(vol, (0.5, 0.5, 0.5))
    keep = np.flatnonzero(ball.triangles_center[:, 2] - ball.vertices[:, 2].mean() > 3.0)
    cap = ball.submesh([keep], append=True)
    cap = make_mesh(cap.vertices, cap.faces, orient_outward=False)
    radius, _ = nm.default_radius(cap)

    def k_error():  # off the rim band (its smaller fits are noisier)
        df = curvature(cap, radius, rng=0)
        K = df["K"][df["fit_radius"] == radius].to_numpy()
        return np.nanmedian(np.abs(K * R * R - 1))

    clipped = k_error()
    scatter = curvature(cap, radius, rng=0).attrs["fit_scatter_H"]  # the fits' noise: a few % of 1/R
    assert 0.01 / R < scatter < 0.2 / R
    monkeypatch.setattr(nm, "OUTLIER_CLIP", np.inf)
    assert clipped < 0.13 and k_error() > 2 * clipped


def test_default_radius_refuses_an_unwelded_triangle_soup():
    """Every vertex on the rim (no face shares a vertex): an error naming the fix, not a hang."""
    from nemo.morphology import default_radius

    mesh = sphere_mesh(8.0)
    tri = mesh.vertices[mesh.faces].reshape(-1, 3)
    soup = trimesh.Trimesh(tri, np.arange(len(tri)).reshape(-1, 3), process=False)
    with pytest.raises(NemoError, match="merge the coincident vertices"):
        default_radius(soup)


def test_the_ladder_and_its_stablest_pair():
    from nemo.morphology import _ladder, _ladder_change, _stablest

    radii = _ladder(1.0, 5.0)  # 1, √2, 2, 2√2, 4 and the top 5
    assert radii[:5] == pytest.approx([1, 2**0.5, 2, 8**0.5, 4]) and radii[-1] == 5.0
    assert _ladder(1.0, 4.3) == pytest.approx([1, 2**0.5, 2, 8**0.5, 4])  # a top within × 1.1: no stub
    assert _ladder(1.0, 1.2) == pytest.approx([1, 1.2]) and _ladder(1.0, 0.9) == [1.0]
    assert _stablest([1, 2, 3, 4, 5], [3.0, 1.0, 2.0, 4.0], "size", "min_edges") == (pytest.approx(6**0.5), 1,
                                                                                      "stability")
    assert _stablest([1, 2, 3], [3.0, 1.0], "rim", "min_edges") == (3, 2, "rim")  # still falling: the top
    assert _stablest([1.0], [], "size", "min_edges") == (1.0, 0, "min_edges")
    assert _stablest([1, 2], [np.nan], "size", "rim") == (1, 0, "rim")
    # the change per √2: the quantile of |Δ(k1, k2)| over the probes, scaled for a shorter step
    ks = [np.zeros((4, 2)), np.array([[0, 0], [0, 0], [0, 0], [4.0, 0]]), np.full((4, 2), np.nan),
          np.array([[0, 0], [0, 0], [0, 0], [4.0, 3.0]])]
    change = _ladder_change(ks, [1.0, 2**0.5, 2**0.75, 2**0.875], 0.25)
    assert change[0] == pytest.approx(1.0) and np.isnan(change[1])  # 75th percentile of 0, 0, 0, 4
    # a step of 2^(1/8) is a quarter of √2: its change (75th percentile of 0, 0, 0, 3) counts × 4
    ks[2] = ks[1].copy()
    assert _ladder_change(ks, [1.0, 2**0.5, 2**0.75, 2**0.875], 0.25)[2] == pytest.approx(0.75 * 4)


def test_the_climb_stops_on_the_shape_not_on_a_rough_walls_rise():
    """Ladders measured on the validation meshes: a shape's change grows ≥ 2 × within two rungs of
    its smallest (the climb stops); a rough wall's rises by 1.2–1.6 × and falls again (it goes on)."""
    from nemo.morphology import _climb_settled

    assert _climb_settled([0.0024, 0.0012, 0.0014, 0.0070])  # torus 45 / 15, noise-free
    assert _climb_settled([0.0727, 0.0420, 0.0202, 0.0112, 0.0212, 0.0383])  # the same at SNR 10
    assert _climb_settled([0.0021, 0.0008, 0.0003, 0.0002, 0.0008, 0.0018])  # ellipsoid, noise-free
    assert not _climb_settled([0.0489, 0.0569, 0.0585])  # SNR-3 vesicle wall: then 0.04, 0.007, 0.003
    assert not _climb_settled([0.0311, 0.0437, 0.0493])
    assert not _climb_settled([0.0536, 0.0622, 0.0569])  # not grown twice in a row
    assert not _climb_settled([0.01, np.nan, 0.02])  # too few finite changes


def test_default_radius_of_a_rough_vesicle_wall_at_snr_3(tmp_path):
    """The SNR-3 vesicle of the validation protocol (R 80 µm, dz 2.5 dx, PSF 2.5 / 1 / 1 µm, its
    rotation 2): the pilot's change rises from 5 to 14 µm and then falls tenfold. Stopping at the
    rise gave a radius of 5.9 µm and |H R − 1| ≈ 1.9 (K of the wrong sign); the climb now goes on
    to the top. Measured: 39.5 µm, |H R − 1| 0.012."""
    from nemo import stages
    from nemo.cli import main as nemo_main
    from nemo.io import read_stack

    image = tmp_path / "v.tif"
    assert nemo_main(["synth", str(image), "--radius", "80", "--spacing", "2.5", "1", "1", "--blur", "2.5", "1", "1",
                      "--photons", "12.5", "--noise", "36.06", "--rotate-random", "2", "--seed", "2"]) == 0
    volume, info = read_stack(image, t=0, c=0)
    meshes, _ = stages.mesh(volume, info.spacing)
    inner = meshes["inner"]
    df, p = stages.curvature(inner)
    centre = np.asarray(inner.vertices).mean(axis=0)
    R = np.linalg.norm(np.asarray(inner.vertices) - centre, axis=1).mean()
    err = np.median(np.abs(df["H"] * R - 1))
    assert p["radius"] > 20 and err < 0.03, (p["radius_from"], err)


def test_default_radius_ellipsoid_dz2_targets(imaged_ellipsoid):
    """Issue 12: ellipsoid 60 × 40 × 30 µm at dz = 2 dx: median relative error of H ≤ 2 %,
    K ≤ 3 % at the default radius; "auto" takes the quartic fit there and it beats the
    quadratic fit at the quadratic's own default radius."""
    from nemo.morphology import default_radius

    mesh, c = imaged_ellipsoid
    H_true, K_true = ellipsoid_HK(closest_on_ellipsoid(np.asarray(mesh.vertices) - c, BIG_ELL), BIG_ELL)
    radius, info = default_radius(mesh)
    assert info["limited_by"] in ("stability", "size"), info
    df = curvature(mesh, radius, n_samples=6000, rng=0)
    assert df.attrs["fit"] == "quartic"
    eh, ek = median_rel_errors(df, H_true, K_true)
    assert eh <= 0.02 and ek <= 0.03, (eh, ek)
    r_quad, _ = default_radius(mesh, fit="quadratic")
    assert r_quad < radius
    eh_q, _ = median_rel_errors(curvature(mesh, r_quad, n_samples=6000, rng=0, fit="quadratic"), H_true, K_true)
    assert eh < eh_q


def test_user_radius_8um_on_the_ellipsoid_dz2_targets():
    """Issue 12: the 60 × 40 × 30 µm ellipsoid at dz = 2 dx (noise-free render, PSF σ 1.2 / 0.4 µm)
    with a user radius of 8 µm: H ≤ 2 %, K ≤ 3 %. Marching cubes alone left terraces of linear
    interpolation between the 2 µm planes near the poles (H 2.2 %, K 4.6 %); the snap onto the
    cubic-spline iso-surface (nemo.refine.snap_to_level) removes them."""
    vol, c = render(lambda p: ellipsoid_sdf(p, BIG_ELL), BIG_ELL, (2.0, 1.0, 1.0), (1.2, 0.4, 0.4), noise=0.0,
                    photons=1e9, rng=1)
    mesh = reconstructed(vol, (2.0, 1.0, 1.0))
    assert mesh.metadata["nemo_surface"]["snapped"] > 0.9 * len(mesh.vertices)
    H_true, K_true = ellipsoid_HK(closest_on_ellipsoid(np.asarray(mesh.vertices) - c, BIG_ELL), BIG_ELL)
    df = curvature(mesh, 8.0, rng=0)
    eh, ek = median_rel_errors(df, H_true, K_true)
    assert eh <= 0.02 and ek <= 0.03, (eh, ek)


def test_default_radius_torus_targets():
    """Issue 12: torus R 50 / r 18 µm at dz = 1.5 dx: median relative error H ≤ 3 %, K ≤ 5 %
    (15 edges = 15.6 µm ≈ 0.9 r gave H 3.2 %; the stablest radius is 14 µm: 2.0 / 3.6 %)."""
    from nemo.morphology import default_radius

    Rt, r = 50.0, 18.0
    vol, c = render(lambda p: torus_sdf(p, Rt, r), (Rt + r, Rt + r, r), (1.5, 1.0, 1.0), (0.9, 0.4, 0.4))
    mesh = reconstructed(vol, (1.5, 1.0, 1.0))
    radius, info = default_radius(mesh)
    assert info["curvature_radius"] == pytest.approx(r, rel=0.05) and radius < r
    df = curvature(mesh, radius, n_samples=6000, rng=0)
    H_true, K_true = torus_HK(np.asarray(mesh.vertices) - c, Rt, r)
    eh, ek = median_rel_errors(df, H_true, K_true)
    assert eh <= 0.03 and ek <= 0.05, (eh, ek)
    res = measure(mesh, df)
    assert res["euler_characteristic"] == 0 and abs(res["integral_K_fit"]) < 0.03 * 4 * np.pi


def test_default_radius_rotation_invariant(imaged_ellipsoid):
    from nemo.morphology import default_radius

    mesh, _ = imaged_ellipsoid
    rot = rotation(np.random.default_rng(3))
    turned = make_mesh(np.asarray(mesh.vertices) @ rot.T + (40.0, -7.0, 3.0), mesh.faces, orient_outward=False)
    r0, info0 = default_radius(mesh)
    r1, info1 = default_radius(turned)
    assert r1 == pytest.approx(r0, rel=1e-6)
    assert info1["curvature_radius"] == pytest.approx(info0["curvature_radius"], rel=1e-6)


def test_default_radius_rotated_image_gives_the_same_errors():
    """The ellipsoid turned in the image (a different voxelisation): same radius within 5 %,
    errors within the targets."""
    from nemo.morphology import default_radius

    abc = (30.0, 20.0, 15.0)
    rot = rotation(np.random.default_rng(8))
    vol, c = render(lambda p: ellipsoid_sdf(p, abc), (30.0, 30.0, 30.0), (1.0, 0.5, 0.5), (0.6, 0.2, 0.2), rot=rot)
    mesh = reconstructed(vol, (1.0, 0.5, 0.5))
    vol0, c0 = render(lambda p: ellipsoid_sdf(p, abc), (30.0, 30.0, 30.0), (1.0, 0.5, 0.5), (0.6, 0.2, 0.2))
    r0, _ = default_radius(reconstructed(vol0, (1.0, 0.5, 0.5)))
    radius, _ = default_radius(mesh)
    assert radius == pytest.approx(r0, rel=0.05)
    q = (np.asarray(mesh.vertices) - c) @ rot  # back to the ellipsoid's frame
    H_true, K_true = ellipsoid_HK(closest_on_ellipsoid(q, abc), abc)
    eh, ek = median_rel_errors(curvature(mesh, radius, n_samples=4000, rng=0), H_true, K_true)
    assert eh <= 0.02 and ek <= 0.03, (eh, ek)


def test_default_radius_open_cap_independent_of_the_cut(sphere15):
    """A cap of a sphere cut by a plane gets the radius of the whole sphere, however much of it
    is cut; a short stack (a thin band) gets a radius that leaves its middle measurable."""
    from nemo.morphology import default_radius

    R = 15.0
    whole, _ = default_radius(sphere15)
    radii = []
    for z_cut in (-4.0, 0.0, 3.0):  # caps 19, 15 and 12 µm high
        keep = np.flatnonzero(sphere15.triangles_center[:, 2] > z_cut)
        sub = sphere15.submesh([keep], append=True)
        cap = make_mesh(sub.vertices, sub.faces, orient_outward=False)
        radius, info = default_radius(cap)
        assert info["rim_cap"] is not None and info["limited_by"] == "stability", info
        radii.append(radius)
    assert max(radii) / min(radii) < 1.03 and radii[0] == pytest.approx(whole, rel=0.03)
    # a band |z| < 7 µm of the sphere (a short stack): the old min(15 edges, 0.5 R_obj ≈ 6.8 µm)
    # left every vertex NaN; half the largest rim distance (3.5 µm) leaves the middle
    band = sphere15.submesh([np.flatnonzero(np.abs(sphere15.triangles_center[:, 2]) < 7.0)], append=True)
    band = make_mesh(band.vertices, band.faces, orient_outward=False)
    radius, info = default_radius(band)
    assert info["limited_by"] == "rim" and radius == pytest.approx(3.5, abs=0.3)
    df = curvature(band, radius, rng=0)
    assert df["H"].notna().sum() > 50
    assert abs(np.nanmedian(df["H"]) * R - 1) < 0.05


def test_open_surface_rim_band_is_fitted_at_smaller_radii(ellipsoids, monkeypatch):
    """An ellipsoid (30 × 22 × 16 µm) cut open by a plane (a tissue cut by the field): a fit of
    10 µm within 10 µm of the rim would be one-sided, so those vertices are fitted at the largest
    radius 10 × 2^(−k/4) whose ball stays off the rim, down to 6 edges and half the radius (NaN
    closer). The band's H and K follow the exact values (noise-free: a smaller fit is as exact),
    and the interior is what it is without the band (no averaging). A wild fit in the band (a
    mesh defect at the rim) is clipped to the interior's range before the average."""
    import nemo.morphology as nm
    from nemo.geometry import rim
    from nemo.mesh import make_mesh, mean_edge_length

    half = ellipsoids[ISO].submesh([np.flatnonzero(ellipsoids[ISO].triangles_center[:, 2] > 4.0)], append=True)
    cap = make_mesh(half.vertices, half.faces, orient_outward=False)
    radius, edge = 10.0, mean_edge_length(cap)
    smallest = max(6 * edge, radius / 2)
    df = curvature(cap, radius, rng=0, smooth=0)
    v = np.asarray(cap.vertices)
    d_rim = rim(cap.faces, len(v), v)["distance"]
    H0, K0 = ellipsoid_HK(closest_on_ellipsoid(v, ELL), ELL)
    band = (d_rim < radius) & (d_rim > smallest)
    assert band.sum() > 100 and df["H"][band].notna().all()
    assert (df["fit_radius"][band] < radius).all() and (df["fit_radius"][band] >= smallest - 1e-9).all()
    fitted = band & df["sampled"].to_numpy()
    assert fitted.sum() > 30 and (df["fit_radius"][fitted] < d_rim[fitted]).all()  # the balls stay off the rim
    assert np.median(np.abs(df["H"][band] / H0[band] - 1)) < 0.02
    assert np.median(np.abs(df["K"][band] / K0[band] - 1)) < 0.04
    assert df["H"][d_rim < smallest].isna().all()
    assert df.attrs["rim_vertices"] == int(df["H"].isna().sum()) < df.attrs["rim_band"]
    assert sum(df.attrs["rim_fits"].values()) == int(df["sampled"][d_rim <= radius].sum()) > 30
    assert set(df.attrs["rim_fits"]) <= {df.attrs["fit"], "quadratic"}
    assert (df["fit_radius"][d_rim > radius] == radius).all()
    averaged = curvature(cap, radius, rng=0)
    assert np.median(np.abs(averaged["H"][band] / H0[band] - 1)) < 0.02

    with monkeypatch.context() as m:  # no band fits (the floor above the radius): the old NaN band
        m.setattr(nm, "RIM_MIN_FRACTION", 2.0)
        without = curvature(cap, radius, rng=0, smooth=0)
    assert without["H"][d_rim <= radius].isna().all()
    assert np.array_equal(df["H"][d_rim > radius], without["H"][d_rim > radius])

    real = nm._fit_samples

    def one_wild(vertices, normals, tree, where, r, kind, chunk):  # the first band fit reads −1000
        out, d1, d2 = real(vertices, normals, tree, where, r, kind, chunk)
        if r < radius:
            out["H"][0] = out["K"][0] = -1000.0
        return out, d1, d2

    monkeypatch.setattr(nm, "_fit_samples", one_wild)
    wild = curvature(cap, radius, rng=0)
    inside = (d_rim > radius) & np.isfinite(H0)
    assert np.median(np.abs(wild["H"][inside] / H0[inside] - 1)) < 0.02
    assert np.abs(wild["H"][band]).max() < 10 * np.abs(H0).max()

    def one_degenerate(vertices, normals, tree, where, r, kind, chunk):  # the first band fit fails
        out, d1, d2 = real(vertices, normals, tree, where, r, kind, chunk)
        if r < radius:
            for key in ("H", "K", "k1", "k2"):
                out[key][0] = np.nan
        return out, d1, d2

    monkeypatch.setattr(nm, "_fit_samples", one_degenerate)
    with pytest.warns(NemoWarning, match=r"fits near the open rim were degenerate"):
        curvature(cap, radius, rng=0, smooth=0)


def test_default_radius_keeps_half_of_a_rough_open_patch():
    """A flat 100 × 100 µm patch with 0.2 µm roughness (a tissue cut by the field): the
    curvature keeps falling with the radius up to the rim cap (25 µm, which leaves 75 % of the
    vertices without a fit at that radius), so the radius stops at the median distance to the
    rim; H ≈ 0. The rim band is fitted at smaller radii, down to half the radius: 70 % of the
    vertices have H (50-60 % before), and the band's H is ≈ 0 too."""
    from nemo.morphology import default_radius

    x, y = np.meshgrid(np.arange(101.0), np.arange(101.0))
    z = np.random.default_rng(0).normal(0, 0.2, x.shape)
    a = (np.arange(100)[:, None] * 101 + np.arange(100)[None, :]).ravel()
    faces = np.concatenate([np.stack([a, a + 1, a + 101], 1), np.stack([a + 1, a + 102, a + 101], 1)])
    patch = trimesh.Trimesh(np.stack([x.ravel(), y.ravel(), z.ravel()], 1), faces, process=False)
    radius, info = default_radius(patch)
    assert info["limited_by"] == "coverage" and 10.0 < radius < info["rim_cap"] == pytest.approx(25.0, rel=0.02)
    df = curvature(patch, radius, rng=0)
    at_radius = df["fit_radius"] == radius
    assert 0.5 < at_radius.mean() < 0.6 and df["H"].notna().mean() > 0.65
    assert df["fit_radius"][~at_radius].dropna().between(radius / 2, radius).all()
    assert abs(np.nanmedian(df["H"])) < 1e-3 and np.nanpercentile(np.abs(df["H"]), 90) < 0.01
    band = df["H"][~at_radius].dropna()
    assert abs(np.median(band)) < 2e-3 and np.percentile(np.abs(band), 90) < 0.02


def test_default_radius_of_several_objects_in_one_mesh():
    """Four rough balls of R = 8 µm (0.15 µm vertex jitter: the change keeps falling to the top)
    in one mesh: the top is 0.6 × the size of the largest piece, as for one ball (5.1 µm), not of
    the whole mesh (6.9 µm here; 2.1 R on nine balls)."""
    from nemo.morphology import default_radius

    rng = np.random.default_rng(0)
    balls = []
    for k in range(4):
        ball = sphere_mesh(8.0)
        ball.vertices = ball.vertices + rng.normal(0.0, 0.15, ball.vertices.shape) + (40.0 * k, 0.0, 0.0)
        balls.append(ball)
    r_one, _ = default_radius(balls[0])
    r_all, info = default_radius(trimesh.util.concatenate(balls))
    assert r_all <= 0.6 * 8.0 * 1.1 and r_all == pytest.approx(r_one, rel=0.05), info


def test_default_radius_bad_input(sphere15):
    from nemo.morphology import default_radius

    with pytest.raises(NemoError, match="fit"):
        default_radius(sphere15, fit="cubic")
    with pytest.raises(NemoError, match="fraction"):
        default_radius(sphere15, fraction=0.0)
    with pytest.raises(NemoError, match="fraction"):
        default_radius(sphere15, fraction=None)
    with pytest.raises(NemoError, match="fraction"):
        default_radius(sphere15, fraction=True)
    # a numpy scalar (e.g. read from an array) is a number like any other
    assert default_radius(sphere15, fraction=np.float32(0.5), rng=0)[0] == default_radius(sphere15, fraction=0.5, rng=0)[0]
    with pytest.raises(NemoError, match="quantile"):
        default_radius(sphere15, quantile=1.0)
    with pytest.raises(NemoError, match="min_edges"):
        default_radius(sphere15, min_edges=0.0)
    with pytest.raises(NemoError, match="min_edges"):
        default_radius(sphere15, min_edges=40.0)
    with pytest.raises(NemoError, match="at least 10"):
        default_radius(sphere15, n_probe=3)
    with pytest.raises(NemoError):
        default_radius(trimesh.Trimesh(vertices=np.zeros((3, 3)), faces=[[0, 1, 2]], process=False))


def test_a_mesh_too_coarse_for_any_radius_says_so():
    """An icosahedron: 5 neighbours per vertex whatever the radius; not 'use a larger radius'."""
    ico = trimesh.creation.icosahedron()
    with pytest.warns(NemoWarning, match="too coarse for a curvature fit at 12 of 12") as caught:
        df = curvature(ico, 10.0, rng=0)
    assert df["H"].isna().all() and not any("use a larger radius" in str(w.message) for w in caught)
