"""Tangential Q-tensor average and inter-layer alignment against analytic fields."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import trimesh

from nemo.errors import NemoError, NemoWarning
from nemo.geometry import axis_frames
from nemo.mesh import load_mesh, make_mesh, save_mesh, vertex_normals
from nemo.order import alignment, lift_q, order, tangential_eig
from nemo.tables import read_provenance, read_table, write_table

R = 30.0


def sphere_mesh(radius=R, subdivisions=4):
    ico = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return make_mesh(ico.vertices, ico.faces)


def e_phi(p):
    """Unit azimuthal direction; undefined on the z axis (the +1 defects at the poles)."""
    e = np.c_[-p[:, 1], p[:, 0], np.zeros(len(p))]
    norm = np.linalg.norm(e, axis=1, keepdims=True)
    assert norm.min() > 0, "e_phi is undefined at the poles"
    return e / norm


def directors_table(mesh, vertices, n):
    p = mesh.vertices[vertices]
    return pd.DataFrame({"vertex": vertices, "x": p[:, 0], "y": p[:, 1], "z": p[:, 2],
                         "nx": n[:, 0], "ny": n[:, 1], "nz": n[:, 2], "coherency": 1.0})


def tangent_angle_field(mesh, vertices, theta):
    """Directors cos θ t1 + sin θ t2 in the axis frames of the given vertices."""
    t1, t2 = axis_frames(np.asarray(mesh.vertex_normals)[vertices])
    return np.cos(theta)[:, None] * t1 + np.sin(theta)[:, None] * t2


def nematic_angle_deg(a, b):
    a = a / np.linalg.norm(a, axis=1, keepdims=True)
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    return np.rad2deg(np.arccos(np.clip(np.abs(np.einsum("ij,ij->i", a, b)), 0, 1)))


def test_lift_q_is_tangential_traceless_and_frame_free(rng):
    normals = rng.standard_normal((50, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    t1, t2 = axis_frames(normals)
    theta = rng.uniform(-np.pi, np.pi, 50)
    n = np.cos(theta)[:, None] * t1 + np.sin(theta)[:, None] * t2
    q6 = lift_q(n, normals)
    q = np.zeros((50, 3, 3))
    for k, (i, j) in enumerate(((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))):
        q[:, i, j] = q[:, j, i] = q6[:, k]
    np.testing.assert_allclose(np.trace(q, axis1=1, axis2=2), 0, atol=1e-12)
    np.testing.assert_allclose(np.einsum("tij,tj->ti", q, normals), 0, atol=1e-12)
    # equals q_ij t_i ⊗ t_j with q = n nᵀ − ½ I₂ in the local basis (paper eq. Q_lifted)
    c, s = np.cos(theta), np.sin(theta)
    q2 = np.stack([np.stack([c * c - 0.5, c * s], -1), np.stack([c * s, s * s - 0.5], -1)], -2)
    basis = np.stack([t1, t2], 1)  # (P, 2, 3)
    np.testing.assert_allclose(np.einsum("pab,pai,pbj->pij", q2, basis, basis), q, atol=1e-12)
    # head-tail symmetry
    np.testing.assert_array_equal(lift_q(-n, normals), q6)
    s_val, n_avg = tangential_eig(q6, normals)
    np.testing.assert_allclose(s_val, 1.0, atol=1e-12)
    assert nematic_angle_deg(n_avg, n).max() < 1e-5


def test_tangential_eig_is_nan_without_a_tangent_plane():
    n = np.array([[1.0, 0, 0], [1.0, 0, 0]])
    normals = np.array([[0, 0, 1.0], [0, 0, 0.0]])
    s, director = tangential_eig(lift_q(n, np.array([[0, 0, 1.0], [0, 0, 1.0]])), normals)
    assert s[0] == pytest.approx(1.0) and np.isnan(s[1]) and np.isnan(director[1]).all()


@pytest.mark.parametrize("spread_deg", [0.0, 20.0, 45.0, 80.0])
def test_order_parameter_of_a_known_angle_distribution(spread_deg, rng):
    """Angles uniform in ±Δ around a mean: S = sin(2Δ)/(2Δ), director along the mean."""
    mesh = sphere_mesh(subdivisions=5)
    nv = len(mesh.vertices)
    d = np.deg2rad(spread_deg)
    vert = np.arange(nv)
    theta0 = 0.7
    # a deterministic, evenly spread set of angles per neighbourhood (low-discrepancy sequence)
    frac = (vert * 0.6180339887498949) % 1.0
    theta = theta0 + (2 * frac - 1) * d
    n = tangent_angle_field(mesh, vert, theta)
    # the directors only share a reference direction in a region where the axis frame is smooth
    target = int(np.argmin(np.linalg.norm(mesh.vertices - np.array([0, 0, R]), axis=1)))
    out = order(mesh, directors_table(mesh, vert, n), radius=4.0, targets=np.array([target]))
    expect = 1.0 if d == 0 else np.sin(2 * d) / (2 * d)
    assert out["S"].iloc[0] == pytest.approx(expect, abs=0.03)
    ref = tangent_angle_field(mesh, np.array([target]), np.array([theta0]))
    if spread_deg < 80:
        assert nematic_angle_deg(out[["nx", "ny", "nz"]].to_numpy(), ref)[0] < 2.0


def test_latitude_circles_give_s_one_along_e_phi():
    mesh = sphere_mesh()
    rng = np.random.default_rng(0)
    vert = np.sort(rng.choice(len(mesh.vertices), 1500, replace=False))
    vert = vert[np.hypot(mesh.vertices[vert, 0], mesh.vertices[vert, 1]) > 1e-6 * R]  # no director at a pole
    n = e_phi(mesh.vertices[vert])
    flip = rng.random(len(vert)) < 0.5
    n[flip] *= -1  # head-tail symmetry: signs must not matter
    out = order(mesh, directors_table(mesh, vert, n), radius=6.0)
    assert len(out) == len(mesh.vertices) and out["count"].sum() > 0
    assert out["S"].notna().all()  # every target has directors within 6 µm
    p = out[["x", "y", "z"]].to_numpy()
    band = np.abs(p[:, 2]) < 0.8 * R
    # e_φ turns by ~ r tan(latitude) / R across a disc: S ≈ 1 near the equator, a bit less
    # towards the +1 defects at the poles
    assert out["S"][np.abs(p[:, 2]) < 0.5 * R].min() > 0.97
    assert out["S"][band].min() > 0.9
    err = nematic_angle_deg(out[["nx", "ny", "nz"]].to_numpy()[band], e_phi(p[band]))
    assert err[np.abs(p[band, 2]) < 0.5 * R].max() < 2.0 and np.median(err) < 1.0
    # the +1 defects at the poles show as low S
    pole = np.abs(p[:, 2]) > 0.999 * R
    assert out["S"][pole].max() < 0.5
    # same result with all signs flipped
    again = order(mesh, directors_table(mesh, vert, -n), radius=6.0)
    np.testing.assert_allclose(again["S"], out["S"], atol=1e-12)


def test_isotropic_directors_have_low_order(rng):
    mesh = sphere_mesh()
    vert = np.arange(len(mesh.vertices))
    n = tangent_angle_field(mesh, vert, rng.uniform(0, np.pi, len(vert)))
    out = order(mesh, directors_table(mesh, vert, n), radius=10.0, targets="directors")
    assert out["count"].min() > 60
    assert out["S"].median() < 0.2 and np.percentile(out["S"], 95) < 0.3


def test_isotropic_noise_layer_has_low_order(rng):
    """Directors measured on smooth isotropic noise, averaged over many patches: S < 0.2."""
    from scipy import ndimage
    from scipy.spatial import Delaunay

    from nemo.directors import directors

    g = np.arange(0, 160.0 + 1e-9, 1.0)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2) + 0.3 * rng.uniform(-1, 1, (len(g) ** 2, 2))
    mesh = make_mesh(np.c_[xy, np.zeros(len(xy))], Delaunay(xy).simplices, orient_outward=False)
    noise = ndimage.gaussian_filter(rng.standard_normal((180, 180)), 1.5)
    intensity = ndimage.map_coordinates(noise, (xy[:, 1] + 10, xy[:, 0] + 10), order=1)
    dirs = directors(mesh, intensity, patch_radius=4.0, rng=0)
    out = order(mesh, dirs, radius=24.0, targets="directors")
    inner = np.all((out[["x", "y"]].to_numpy() > 30) & (out[["x", "y"]].to_numpy() < 130), axis=1)
    assert out["S"][inner].median() < 0.2


def test_empty_neighbourhoods_are_nan_and_bad_input():
    mesh = sphere_mesh()
    vert = np.flatnonzero(mesh.vertices[:, 2] > 0.9 * R)
    table = directors_table(mesh, vert, e_phi(mesh.vertices[vert] + [1e-3, 0, 0]))
    with pytest.warns(NemoWarning, match="no director within"):
        out = order(mesh, table, radius=3.0)
    south = mesh.vertices[:, 2] < 0
    assert out["S"][south].isna().all() and (out["count"][south] == 0).all()
    assert out["S"][~south].notna().any()
    with pytest.raises(NemoError, match="radius"):
        order(mesh, table, radius=0)
    with pytest.raises(NemoError, match="another mesh"):
        order(sphere_mesh(subdivisions=2), table, radius=3.0)
    with pytest.raises(NemoError, match="targets"):
        order(mesh, table, radius=3.0, targets="some")


def test_alignment_parallel_orthogonal_and_45(rng):
    mesh = sphere_mesh()
    va = np.sort(rng.choice(len(mesh.vertices), 800, replace=False))
    vb = np.sort(rng.choice(len(mesh.vertices), 900, replace=False))
    theta_a = rng.uniform(0, np.pi, len(mesh.vertices))  # an arbitrary field θ(vertex)
    a = directors_table(mesh, va, tangent_angle_field(mesh, va, theta_a[va]))
    for delta, expect in ((0.0, 1.0), (np.pi / 2, -1.0), (np.pi / 4, 0.0)):
        # B: the same field rotated by delta, at A's vertices and others, moved radially 6 µm
        # out and tilted out of A's tangent plane (the projection must remove the tilt); the
        # nearest B of each A director is then the one right above it
        vbb = np.union1d(va, vb)
        nb = tangent_angle_field(mesh, vbb, theta_a[vbb] + delta)
        b_full = directors_table(mesh, vbb, nb + 0.3 * np.asarray(mesh.vertex_normals)[vbb])
        b_full[["x", "y", "z"]] = mesh.vertices[vbb] * (R + 6) / R
        out = alignment(a, b_full, mesh_a=mesh)
        assert len(out) == len(a) and (out["vertex"].to_numpy() == va).all()
        np.testing.assert_allclose(out["c"], expect, atol=1e-9)
        assert np.allclose(out["distance"], 6.0)
        # head-tail symmetric
        flipped = b_full.copy()
        flipped[["nx", "ny", "nz"]] *= -1
        np.testing.assert_allclose(alignment(a, flipped, mesh_a=mesh)["c"], expect, atol=1e-9)


def test_averaged_alignment_is_not_pulled_to_zero_by_noise(rng):
    """Two orthogonal layers (θ and θ + 90°) whose directors each carry ±45° of uniform angle noise:
    each director's c = cos 2Δθ averages to cos 2ε_A · cos 2ε_B ≈ 0.41 of −1 (the mean reads about
    −0.4, as if the layers met at 57°); c_avg between the order tables' averaged directors reads the
    90° (its S_A · S_B-weighted mean ≤ −0.95), and both order tables are needed for it."""
    from nemo.summary import c_avg_means

    mesh = sphere_mesh()
    p = np.asarray(mesh.vertices)
    off_poles = np.flatnonzero(np.abs(p[:, 2]) < 0.8 * R)  # parallels and meridians: +1 defects at the poles

    def layer(base, n):  # directors along ``base`` (parallels: 0, meridians: 90°) ± 45° of noise
        v = np.sort(rng.choice(off_poles, n, replace=False))
        e = e_phi(p[v])
        angle = base + rng.uniform(-np.pi / 4, np.pi / 4, n)
        return directors_table(mesh, v, np.cos(angle)[:, None] * e + np.sin(angle)[:, None] * np.cross(p[v] / R, e))

    a, b = layer(0.0, 1500), layer(np.pi / 2, 1500)
    oa, ob = (order(mesh, t, radius=8.0, targets=off_poles) for t in (a, b))
    out = alignment(a, b, mesh_a=mesh, order_a=oa, order_b=ob)
    assert -0.55 < out["c"].mean() < -0.25, out["c"].mean()
    assert c_avg_means(out)["c_avg_mean"] <= -0.95 and c_avg_means(out)["c_avg_median"] <= -0.97
    assert np.all((out["weight"] > 0) & (out["weight"] <= 1))
    plain = alignment(a, b, mesh_a=mesh)  # without the order tables: the paper's c only
    assert plain["c_avg"].isna().all() and np.isnan(c_avg_means(plain)["c_avg_mean"])
    with pytest.raises(NemoError, match="both layers' order tables"):
        alignment(a, b, mesh_a=mesh, order_a=oa)


def test_alignment_checks_normals_and_max_distance():
    def table(x):
        return pd.DataFrame({"vertex": np.arange(len(x)), "x": x, "y": 0.0, "z": 0.0,
                             "nx": 1.0, "ny": 0.0, "nz": 0.0, "coherency": 1.0})

    # two of A's three directors have B's one within max_distance; the median match (0.5) is well
    # inside A's extent, so the tables overlap
    a, b = table(np.array([0.0, 0.4, 10.0])), table(np.array([0.5]))
    with pytest.raises(NemoError, match="normals_a"):
        alignment(a, b, normals_a=np.zeros((5, 3)))  # not one normal per director of A
    c = alignment(a, b, max_distance=2.0)["c"].to_numpy()
    assert c[:2] == pytest.approx([1.0, 1.0]) and np.isnan(c[2])


def _two_layer_vesicle(rotation):
    from nemo.peel import peel
    from nemo.surface import reconstruct, split_mesh
    from nemo.synthetic import vesicle

    data, truth = vesicle(radius=50.0, layer_depth=3.0, second_layer_depth=9.0,
                          second_layer_rotation=rotation, seed=1)
    vol = data[0, :, 0]
    assert data.shape[2] == 1  # both layers in one channel
    whole = reconstruct(vol, (1.0, 1.0, 1.0), step=2, keep="all")
    inner, _ = split_mesh(whole, by="centre")
    normals = vertex_normals(inner)
    low = peel(vol, (1, 1, 1), inner.vertices, normals, 0.5, 5.5, 11)
    high = peel(vol, (1, 1, 1), inner.vertices, normals, 6.5, 11.5, 11)
    return inner, low, high


@pytest.mark.parametrize("rotation,sign", [(90.0, -1), (0.0, +1)])
def test_two_fibre_layers_in_one_channel(rotation, sign, wide_scale):
    """Two layers 6 µm apart in one channel, peeled at two depths: mean c ≤ −0.9 / ≥ +0.9."""
    from nemo.directors import directors

    inner, low, high = _two_layer_vesicle(rotation)
    scale = wide_scale(inner, 10.0)  # the paper's integration over half the patch
    da = directors(inner, low, patch_radius=10.0, rng=0, **scale)
    db = directors(inner, high, patch_radius=10.0, rng=1, **scale)  # other centres than A
    c = alignment(da, db, mesh_a=inner)["c"].to_numpy()
    if sign < 0:
        assert c.mean() <= -0.9, c.mean()
    else:
        assert c.mean() >= 0.9, c.mean()


def test_cli_order_and_align(tmp_path, run_cli):
    mesh = sphere_mesh()
    mpath = tmp_path / "s.ply"
    save_mesh(mesh, mpath)
    vert = np.arange(0, len(mesh.vertices), 3)
    da = directors_table(mesh, vert, e_phi(mesh.vertices[vert] + [1e-3, 0, 0]))
    db = da.copy()
    db[["nx", "ny", "nz"]] = np.cross(mesh.vertices[vert] / R, da[["nx", "ny", "nz"]].to_numpy())  # ⟂ in-plane
    pa, pb = tmp_path / "a.parquet", tmp_path / "b.parquet"
    write_table(da, pa)
    write_table(db, pb)
    out = tmp_path / "order.parquet"
    code, stdout, err = run_cli("order", mpath, pa, "-o", out, "--radius", "5")
    assert code == 0, err
    o = read_table(out, kind="order")
    assert len(o) == len(mesh.vertices) and "S mean" in stdout
    code, stdout, err = run_cli("order", mpath, pa, "-o", out, "--radius", "5", "--targets", "directors")
    assert code == 0 and len(read_table(out, kind="order")) == len(vert)
    al = tmp_path / "align.parquet"
    code, stdout, err = run_cli("align", pa, pb, "-o", al, "--mesh", mpath)
    assert code == 0, err
    assert "mean c = -1.000" in stdout and "[-1.0, -0.8)" in stdout
    assert np.allclose(read_table(al, kind="align")["c"], -1.0)
    code, stdout, err = run_cli("align", pa, pa, "-o", al)
    assert code == 0 and "mean c = +1.000" in stdout
    ob = tmp_path / "order_b.parquet"
    assert run_cli("order", mpath, pb, "-o", ob, "--radius", "5", "--targets", "directors")[0] == 0
    code, stdout, err = run_cli("align", pa, pb, "-o", al, "--mesh", mpath, "--order-a", out, "--order-b", ob)
    assert code == 0 and "averaged directors: c_avg = -1.000" in stdout, stdout + err
    assert np.allclose(read_table(al, kind="align")["c_avg"], -1.0)
    code, _, err = run_cli("align", pa, pb, "-o", al, "--order-a", out)
    assert code == 2 and "both --order-a and --order-b" in err
    code, _, err = run_cli("order", mpath, tmp_path / "nothing.parquet", "-o", out, "--radius", "5")
    assert code == 2 and "not found" in err
    layer = tmp_path / "layer.parquet"
    write_table(pd.DataFrame({"vertex": [0], "intensity": [1.0]}), layer)
    code, _, err = run_cli("order", mpath, layer, "-o", out, "--radius", "5")
    assert code == 2 and "lacks column" in err


def test_alignment_refuses_tables_that_do_not_overlap(tmp_path, run_cli):
    """Two layers of different objects (or frames, or units) are an error, not one number."""
    mesh = sphere_mesh()
    vert = np.arange(0, len(mesh.vertices), 3)
    da = directors_table(mesh, vert, e_phi(mesh.vertices[vert] + [1e-3, 0, 0]))
    near = da.copy()
    near[["x", "y", "z"]] *= (R + 0.4 * R) / R  # a second wall 0.4 R outside: still the same object
    assert np.isfinite(alignment(da, near, mesh_a=mesh)["c"]).all()
    thick = da.copy()
    thick[["x", "y", "z"]] *= 1.75  # a thick shell: walls R and 1.75 R from the centre
    assert np.isfinite(alignment(da, thick)["c"]).all()
    cap = da[da["z"] > 0.6 * R]  # B covers only a cap of A: NaN elsewhere with max_distance
    assert np.isnan(alignment(da, cap, max_distance=2.0)["c"]).mean() > 0.5
    far = da.copy()
    far["x"] += 836.0
    with pytest.raises(NemoError, match="do not overlap"):
        alignment(da, far, mesh_a=mesh)
    pa, pb = tmp_path / "a.parquet", tmp_path / "b.parquet"
    write_table(da, pa)
    write_table(far, pb)
    code, _, err = run_cli("align", pa, pb, "-o", tmp_path / "al.parquet")
    assert code == 2 and "nemo align: error: the two director tables do not overlap" in err


def test_cli_order_refuses_directors_from_another_mesh(meshed_shell, tmp_path, run_cli, cli_error):
    """Directors of the inner half averaged on the whole mesh."""
    shell = meshed_shell
    n_inner = len(load_mesh(shell / "m.inner.ply").vertices)
    code, _, err = run_cli("peel", shell / "shell.tif", shell / "m.inner.ply", "-o", tmp_path / "layer.parquet",
                           "--range", "0", "2")
    assert code == 0, err
    code, _, err = run_cli("directors", shell / "m.inner.ply", tmp_path / "layer.parquet", "-o",
                           tmp_path / "d_inner.parquet", "--patch-radius", "3", "--n-patches", "100")
    assert code == 0, err
    assert read_provenance(tmp_path / "d_inner.parquet")["n_vertices"] == n_inner
    code, _, err = run_cli("order", shell / "m.ply", tmp_path / "d_inner.parquet", "-o", tmp_path / "o.parquet",
                           "--radius", "5")
    cli_error(code, err, "vertices")
    assert not (tmp_path / "o.parquet").exists()
    # and on its own mesh the same table is accepted
    code, _, err = run_cli("order", shell / "m.inner.ply", tmp_path / "d_inner.parquet", "-o",
                           tmp_path / "o.parquet", "--radius", "5")
    assert code == 0, err


# ----------------------------------------------------------------------------- coherency weights


def plane_mesh(size=40.0, step=1.0):
    """Flat square grid in z = 0 (normals +z, one tangent frame everywhere)."""
    g = np.arange(0.0, size + 1e-9, step)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    from scipy.spatial import Delaunay

    return make_mesh(np.c_[xy, np.zeros(len(xy))], Delaunay(xy).simplices, orient_outward=False)


def planar_table(mesh, vertices, theta, coherency):
    n = np.c_[np.cos(theta), np.sin(theta), np.zeros(len(theta))]
    table = directors_table(mesh, vertices, n)
    table["coherency"] = coherency
    return table


@pytest.mark.parametrize("f, w", [(0.25, 0.0), (0.4, 0.1), (0.5, 0.3), (0.75, 0.2)])
def test_coherency_weights_of_a_mixture_match_the_prediction_exactly(f, w):
    """Aligned directors (coherency 1) and a fraction f of evenly spread ones (coherency w) at one
    point: the spread ones sum to a zero tensor, so S = 1 − f unweighted and
    (1 − f) / (1 − f + f w) weighted, exactly; the director stays the aligned one."""
    mesh = plane_mesh(10.0)
    centre = int(np.argmin(np.linalg.norm(mesh.vertices - [5, 5, 0], axis=1)))
    n_all = 120
    n_rand = int(round(f * n_all))
    theta = np.r_[np.full(n_all - n_rand, 0.3), np.pi * np.arange(n_rand) / n_rand]
    coh = np.r_[np.ones(n_all - n_rand), np.full(n_rand, w)]
    table = planar_table(mesh, np.full(n_all, centre), theta, coh)
    plain = order(mesh, table, radius=1.5, targets=np.array([centre]))
    weighted = order(mesh, table, radius=1.5, targets=np.array([centre]), weights="coherency")
    assert plain["S"].iloc[0] == pytest.approx(1 - f, abs=1e-12)
    assert weighted["S"].iloc[0] == pytest.approx((1 - f) / (1 - f + f * w), abs=1e-12)
    assert weighted["count"].iloc[0] == plain["count"].iloc[0] == n_all
    ref = np.array([[np.cos(0.3), np.sin(0.3), 0.0]])
    for out in (plain, weighted):
        assert nematic_angle_deg(out[["nx", "ny", "nz"]].to_numpy(), ref)[0] < 1e-6


def test_coherency_weights_keep_a_noisy_uniform_field_ordered(rng):
    """A uniform field with a fraction f = 0.4 of random directors of coherency w = 0.1 mixed in
    at random vertices: the weighted S stays near the clean 1 (prediction 0.6 / 0.64 = 0.94),
    the unweighted one drops to 1 − f = 0.6 (plus the sampling bias of ~ 120 random tensors)."""
    f, w = 0.4, 0.1
    mesh = plane_mesh(60.0)
    nv = len(mesh.vertices)
    vert = np.arange(nv)
    noisy = rng.random(nv) < f
    theta = np.where(noisy, rng.uniform(0, np.pi, nv), 0.3)
    table = planar_table(mesh, vert, theta, np.where(noisy, w, 1.0))
    inner = np.all(np.abs(mesh.vertices[:, :2] - 30.0) < 15.0, axis=1)
    kw = dict(radius=10.0, targets=vert[inner])
    clean = order(mesh, planar_table(mesh, vert, np.full(nv, 0.3), 1.0), **kw)
    plain = order(mesh, table, **kw)
    weighted = order(mesh, table, weights="coherency", **kw)
    assert clean["S"].min() == pytest.approx(1.0, abs=1e-9)
    # finite-sample bias: |Σ random tensors| ~ sqrt(π/4 · f N) / 2 over N ≈ 310 directors
    assert np.median(plain["S"]) == pytest.approx(1 - f, abs=0.03)
    assert np.median(weighted["S"]) == pytest.approx((1 - f) / (1 - f + f * w), abs=0.01)
    assert np.median(weighted["S"]) > 0.92 and weighted["S"].min() > 0.9


def test_weights_none_is_the_plain_mean_and_ignores_coherency(rng):
    """weights='none' (the library's default) is the paper's mean: the coherency changes nothing, and the
    coherency weights with every coherency 1 give the same numbers exactly."""
    mesh = sphere_mesh()
    vert = np.arange(len(mesh.vertices))
    table = directors_table(mesh, vert, tangent_angle_field(mesh, vert, rng.uniform(0, 0.8, len(vert))))
    base = order(mesh, table, radius=5.0)
    assert order(mesh, table, radius=5.0, weights="none").equals(base)
    assert order(mesh, table, radius=5.0, weights="coherency").equals(base)  # every coherency 1
    varied = table.assign(coherency=rng.uniform(0, 1, len(vert)))
    assert order(mesh, varied, radius=5.0).equals(base)
    assert not order(mesh, varied, radius=5.0, weights="coherency")["S"].equals(base["S"])


def test_zero_weights_give_nan_and_bad_weights():
    mesh = plane_mesh(20.0)
    vert = np.arange(len(mesh.vertices))
    west = mesh.vertices[:, 0] < 10.0
    coh = np.where(west, 0.0, 0.8)
    coh[np.flatnonzero(west)[:3]] = np.nan  # unknown coherency: weight 0 as well
    table = planar_table(mesh, vert, np.full(len(vert), 0.3), coh)
    with pytest.warns(NemoWarning, match="weight 0"):
        out = order(mesh, table, radius=2.0, weights="coherency")
    far_west = mesh.vertices[:, 0] < 7.5
    assert out["S"][far_west].isna().all() and out[["nx", "ny", "nz"]][far_west].isna().all().all()
    assert (out["count"][far_west] > 0).all()
    np.testing.assert_allclose(out["S"][~far_west], 1.0, atol=1e-9)  # any weight > 0 gives S = 1
    assert order(mesh, table, radius=2.0)["S"].notna().all()  # unweighted: no NaN
    with pytest.raises(NemoError, match="weights"):
        order(mesh, table, radius=2.0, weights="intensity")
    with pytest.warns(NemoWarning, match="no `coherency` column"):
        plain = order(mesh, table.drop(columns="coherency"), radius=2.0, weights="coherency")
    assert plain["S"].notna().all()


def test_cli_order_weights_are_recorded(tmp_path, run_cli):
    mesh = sphere_mesh()
    mpath, dpath, out = tmp_path / "s.ply", tmp_path / "d.parquet", tmp_path / "o.parquet"
    save_mesh(mesh, mpath)
    vert = np.arange(0, len(mesh.vertices), 2)
    table = directors_table(mesh, vert, e_phi(mesh.vertices[vert] + [1e-3, 0, 0]))
    write_table(table.assign(coherency=np.linspace(0.2, 1.0, len(vert))), dpath)
    for weights in ("none", "coherency"):
        code, _, err = run_cli("order", mpath, dpath, "-o", out, "--radius", "5", "--weights", weights)
        assert code == 0, err
        assert read_provenance(out)["parameters"]["weights"] == weights
    code, _, err = run_cli("order", mpath, dpath, "-o", out, "--radius", "5")  # the config's default
    assert code == 0 and read_provenance(out)["parameters"]["weights"] == "none"
