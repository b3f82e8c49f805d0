"""Directors and tangent frames against analytic fields (flat, cylinder, sphere, vesicle)."""

from __future__ import annotations

import warnings

import numpy as np
import orientationpy
import pandas as pd
import pytest
import trimesh
from scipy.spatial import Delaunay

from nemo.directors import (
    default_n_patches,
    default_patch_radius,
    directors,
    fibre_angle,
    structure_tensor_centre,
)
from nemo.errors import NemoError
from nemo.mesh import load_mesh, make_mesh, mean_edge_length, save_mesh, vertex_normals
from nemo.tables import read_provenance, read_table, write_table

WAVELENGTH = 6.0  # stripe period (µm); meshes have ~1 µm edges


def angle_between_deg(n, e):
    """Unsigned nematic angle (degrees) between rows of n and e."""
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    e = e / np.linalg.norm(e, axis=1, keepdims=True)
    return np.rad2deg(np.arccos(np.clip(np.abs(np.einsum("ij,ij->i", n, e)), 0, 1)))


# ------------------------------------------------------------------ structure tensor vs OrientationPy


def _stripes(shape, alpha, period, rng, noise=0.3):
    """Stripes along (cos α, sin α) in (column, row) coordinates, plus noise."""
    r, c = np.mgrid[0 : shape[0], 0 : shape[1]].astype(float)
    img = np.cos(2 * np.pi * (-np.sin(alpha) * c + np.cos(alpha) * r) / period)
    return img + noise * rng.standard_normal(shape)


@pytest.mark.parametrize("shape,sigma", [((41, 41), 5.0), ((30, 37), 2.0), ((25, 25), 8.0)])
def test_structure_tensor_agrees_with_orientationpy(shape, sigma, rng):
    alphas = np.deg2rad(np.arange(-85, 91, 7.5))
    images = np.stack([_stripes(shape, a, 5.0, rng) for a in alphas])
    images[-1] = rng.standard_normal(shape)  # one isotropic image as well
    theta, coherency = fibre_angle(structure_tensor_centre(images, sigma))
    for k, img in enumerate(images):
        grad = orientationpy.computeGradient(img, mode="gaussian")
        st = orientationpy.computeStructureTensor(grad, sigma=sigma)
        cy, cx = shape[0] // 2, shape[1] // 2
        th_opy = orientationpy.computeOrientation(st)["theta"][cy, cx]
        diff = (np.rad2deg(theta[k]) + th_opy + 90.0) % 180.0 - 90.0  # OrientationPy's y is up
        assert abs(diff) < 0.5, (k, th_opy, np.rad2deg(theta[k]))
        j = st[:, cy, cx]
        np.testing.assert_allclose(structure_tensor_centre(img, sigma)[0], j, rtol=1e-9, atol=1e-12)
    # and the angles are the stripes' (ground truth), coherency high for stripes
    clean = np.stack([_stripes(shape, a, 5.0, rng, noise=0.05) for a in alphas])
    theta, coherency = fibre_angle(structure_tensor_centre(clean, sigma))
    err = (np.rad2deg(theta - alphas) + 90) % 180 - 90
    assert np.abs(err).max() < 1.0
    assert coherency.min() > 0.8


# ------------------------------------------------------------------ meshes


def flat_mesh(size=60.0, spacing=1.0, seed=0):
    rng = np.random.default_rng(seed)
    g = np.arange(0, size + 1e-9, spacing)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    xy = xy + 0.3 * spacing * rng.uniform(-1, 1, xy.shape)  # irregular triangulation
    tri = Delaunay(xy)
    return make_mesh(np.c_[xy, np.zeros(len(xy))], tri.simplices, orient_outward=False)


def cylinder_mesh(radius=15.0, length=60.0, spacing=1.0):
    n_phi = int(round(2 * np.pi * radius / spacing))
    n_z = int(round(length / spacing)) + 1
    phi = np.arange(n_phi) * 2 * np.pi / n_phi
    z = np.linspace(0, length, n_z)
    P, Z = np.meshgrid(phi, z)
    V = np.c_[radius * np.cos(P.ravel()), radius * np.sin(P.ravel()), Z.ravel()]
    idx = np.arange(n_z * n_phi).reshape(n_z, n_phi)
    a, b = idx[:-1], np.roll(idx, -1, axis=1)[:-1]
    c, d = idx[1:], np.roll(idx, -1, axis=1)[1:]
    faces = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])
    return make_mesh(V, faces, orient_outward=False)


def sphere_mesh(radius=30.0, subdivisions=5):
    ico = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return make_mesh(ico.vertices, ico.faces)


def flat_stripes(alpha_deg: float):
    """Stripes along direction α on a flat mesh: mesh, intensity, the true direction, centres."""
    mesh = flat_mesh()
    v = mesh.vertices
    a = np.deg2rad(alpha_deg)
    e = np.array([np.cos(a), np.sin(a), 0.0])
    intensity = np.cos(2 * np.pi * (v @ np.array([-np.sin(a), np.cos(a), 0.0])) / WAVELENGTH)
    inner = np.flatnonzero(np.all((v[:, :2] > 15) & (v[:, :2] < 45), axis=1))
    return mesh, intensity, e, inner[:: max(1, len(inner) // 150)]


@pytest.mark.parametrize("alpha_deg", [0.0, 30.0, 72.0, 90.0, 135.0])
def test_flat_stripes_known_angle(alpha_deg, wide_scale):
    mesh, intensity, e, centres = flat_stripes(alpha_deg)
    df = directors(mesh, intensity, patch_radius=6.0, centres=centres, **wide_scale(mesh, 6.0))
    assert len(df) == len(centres) and (df["vertex"].to_numpy() == centres).all()
    err = angle_between_deg(df[["nx", "ny", "nz"]].to_numpy(), np.tile(e, (len(df), 1)))
    assert err.max() < 2.0, err.max()
    assert df["coherency"].median() > 0.8
    np.testing.assert_allclose(np.linalg.norm(df[["nx", "ny", "nz"]], axis=1), 1.0)
    np.testing.assert_allclose(df[["x", "y", "z"]].to_numpy(), mesh.vertices[centres])


@pytest.mark.parametrize("alpha_deg", [0.0, 72.0, 135.0])
def test_flat_stripes_at_the_default_scale(alpha_deg):
    """The library's default (σ = 4 px of ¼ edge): measured median 0.4-0.7°, max 2.3-3.8°."""
    mesh, intensity, e, centres = flat_stripes(alpha_deg)
    df = directors(mesh, intensity, patch_radius=6.0, centres=centres)
    err = angle_between_deg(df[["nx", "ny", "nz"]].to_numpy(), np.tile(e, (len(df), 1)))
    assert np.median(err) < 1.0 and err.max() < 5.0, (np.median(err), err.max())


def test_director_noise_is_the_spread_between_neighbouring_directors(rng):
    """Directors on a 1 µm grid, all along x but each turned by an independent Gaussian angle of
    s degrees: two of them differ by N(0, 2 s²), whose median |·| is 0.6745 √2 s. Pairs closer or
    farther than 2-3.5 scales do not count; too few pairs give no estimate."""
    from nemo.directors import NOISE_MIN_PAIRS, director_noise

    g = np.arange(40.0)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    s = 6.0
    a = np.deg2rad(s) * rng.standard_normal(len(xy))
    df = pd.DataFrame({"x": xy[:, 0], "y": xy[:, 1], "z": 0.0, "nx": np.cos(a), "ny": np.sin(a), "nz": 0.0})
    noise, n_pairs = director_noise(df, scale=1.0)
    assert noise == pytest.approx(0.6745 * np.sqrt(2) * s, rel=0.05) and n_pairs > 1000
    # head-tail symmetric: flipping half of the directors changes nothing
    flipped = df.assign(nx=np.where(xy[:, 0] % 2, -df["nx"], df["nx"]), ny=np.where(xy[:, 0] % 2, -df["ny"], df["ny"]))
    assert director_noise(flipped, scale=1.0)[0] == pytest.approx(noise)
    # only pairs 2-3.5 scales apart count: 60 directors along x at x = 0 and 60 at x = 2.5 agree;
    # 60 along y at x = 1 (1 and 1.5 from them) and 60 along y at x = 7 (4.5 and 7) are nobody's pair
    def cluster(x, along_x):
        return pd.DataFrame({"x": x, "y": 0.0, "z": 0.0, "nx": float(along_x), "ny": float(not along_x), "nz": 0.0},
                            index=range(60))

    clusters = pd.concat([cluster(0.0, True), cluster(2.5, True), cluster(1.0, False), cluster(7.0, False)])
    assert director_noise(clusters, scale=1.0) == (pytest.approx(0.0, abs=1e-6), 3600)
    few = df.iloc[:10]
    assert np.isnan(director_noise(few, scale=1.0)[0]) and director_noise(few, scale=1.0)[1] < NOISE_MIN_PAIRS


def test_director_noise_transports_across_a_curved_surface():
    """The azimuthal field e_φ in a sphere's equatorial band (R = 20 µm) is parallel along the
    equator: transported between the tangent planes, neighbours agree (only the band's
    latitude adds a little); as raw 3D vectors they differ by the planes' tilt, d / R (≈ 5°)."""
    from nemo.directors import director_noise

    k = np.arange(20000) + 0.5
    theta, phi = np.arccos(1 - 2 * k / len(k)), np.pi * (1 + 5**0.5) * k
    normals = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], 1)
    band = np.abs(normals[:, 2]) < 0.1
    normals = normals[band]
    e_phi = np.stack([-normals[:, 1], normals[:, 0], np.zeros(len(normals))], 1)
    e_phi /= np.linalg.norm(e_phi, axis=1, keepdims=True)
    df = pd.DataFrame(np.c_[20.0 * normals, e_phi], columns=["x", "y", "z", "nx", "ny", "nz"])
    transported, n_pairs = director_noise(df, scale=1.0, normals=normals)
    raw, _ = director_noise(df, scale=1.0)
    assert n_pairs > 1000 and transported < 1.0 and raw > 3.0, (transported, raw)
    # a second sheet 2 µm inside, facing the other way, with its directors turned 90°: its
    # pairs with the first cross the wall and are left out, so the reading does not change
    back = df.assign(x=18.0 * normals[:, 0], y=18.0 * normals[:, 1], z=18.0 * normals[:, 2],
                     nx=0.0, ny=0.0, nz=1.0)
    both, n_both = director_noise(pd.concat([df, back]), scale=1.0, normals=np.r_[normals, -normals])
    assert both < 1.0 and n_both > 2 * n_pairs - 10, (both, n_both)


def test_noise_aware_sigma_widens_in_proportion_and_is_bounded():
    from nemo.directors import NOISE_MIN_WIDENING, NOISE_SIGMA_MAX_FACTOR, NOISE_TARGET_DEG, SIGMA_PX, noise_aware_sigma

    assert noise_aware_sigma(0.5 * NOISE_TARGET_DEG) == SIGMA_PX == noise_aware_sigma(float("nan"))
    assert noise_aware_sigma(0.99 * NOISE_MIN_WIDENING * NOISE_TARGET_DEG) == SIGMA_PX  # not worth a second pass
    assert noise_aware_sigma(NOISE_MIN_WIDENING * NOISE_TARGET_DEG) == pytest.approx(NOISE_MIN_WIDENING * SIGMA_PX)
    assert noise_aware_sigma(1.5 * NOISE_TARGET_DEG) == pytest.approx(1.5 * SIGMA_PX)
    assert noise_aware_sigma(10 * NOISE_TARGET_DEG) == pytest.approx(NOISE_SIGMA_MAX_FACTOR * SIGMA_PX)
    # the widest scale is two edges whatever the pixel: a pixel 4 × the default's is not widened
    from nemo.directors import PIXEL_PER_EDGE, noise_aware_max_px

    assert noise_aware_max_px(edge=2.0, pixel=PIXEL_PER_EDGE * 2.0) == pytest.approx(NOISE_SIGMA_MAX_FACTOR * SIGMA_PX)
    assert noise_aware_sigma(10 * NOISE_TARGET_DEG, noise_aware_max_px(2.0, 2.0)) == SIGMA_PX
    assert noise_aware_sigma(10 * NOISE_TARGET_DEG, 6.0) == 6.0


def test_noise_coherency_is_a_floor_stripes_clear_and_noise_does_not(rng):
    """White noise reaches ~0.5 at the 90th percentile with the default patches; stripes stay
    far above it, and a layer of (other) noise has its median below it."""
    from nemo.directors import noise_coherency

    mesh, stripes, _, centres = flat_stripes(30.0)
    floor = noise_coherency(mesh, rng=1, patch_radius=6.0)
    assert 0.3 < floor < 0.7, floor
    assert noise_coherency(mesh, rng=1, patch_radius=6.0) == floor  # reproducible
    textured = directors(mesh, stripes + 0.3 * rng.standard_normal(len(stripes)), patch_radius=6.0, centres=centres)
    blank = directors(mesh, rng.standard_normal(len(stripes)), patch_radius=6.0, centres=centres)
    assert textured["coherency"].median() > floor + 0.2 and blank["coherency"].median() < floor


def test_micro_images_cut_to_the_tensor_support_change_nothing(monkeypatch, rng):
    """At the default σ the centre's tensor reads a window narrower than a 12 µm patch: gridding
    only that window gives the directors of the whole patch (noise and NaN holes included)."""
    import nemo.directors as nd

    mesh, intensity, _, centres = flat_stripes(30.0)
    intensity = intensity + 0.5 * rng.standard_normal(len(intensity))
    intensity[rng.random(len(intensity)) < 0.2] = np.nan
    halves = []
    grid = nd.micro_images

    def recording(*args):
        halves.append(args[5])
        return grid(*args)

    monkeypatch.setattr(nd, "micro_images", recording)
    cut = directors(mesh, intensity, patch_radius=12.0, centres=centres)
    monkeypatch.setattr(nd, "support_half_width", lambda *a, **k: 10**6)
    whole = directors(mesh, intensity, patch_radius=12.0, centres=centres)
    assert halves[0] < 0.7 * halves[-1], halves  # the cut happened
    assert (cut["vertex"].to_numpy() == whole["vertex"].to_numpy()).all()
    err = angle_between_deg(cut[["nx", "ny", "nz"]].to_numpy(), whole[["nx", "ny", "nz"]].to_numpy())
    assert err.max() < 1e-3, err.max()
    np.testing.assert_allclose(cut["coherency"], whole["coherency"], atol=1e-5)


@pytest.mark.parametrize("alpha_deg", [0.0, 40.0, 90.0])
def test_cylinder_helical_stripes(alpha_deg):
    rc = 15.0
    mesh = cylinder_mesh(radius=rc)
    v = mesh.vertices
    a = np.deg2rad(alpha_deg)
    phi = np.arctan2(v[:, 1], v[:, 0])
    s = rc * phi  # arc length around the cylinder
    # stripes along e = cos α ẑ + sin α e_φ on the unrolled surface (u = s, w = z)
    intensity = np.cos(2 * np.pi * (np.cos(a) * s - np.sin(a) * v[:, 2]) / WAVELENGTH)
    ok = (np.abs(phi) < 2.0) & (v[:, 2] > 15) & (v[:, 2] < 45)  # away from the seam and the ends
    centres = np.flatnonzero(ok)[::5]
    df = directors(mesh, intensity, patch_radius=5.0, centres=centres)
    p = df[["x", "y", "z"]].to_numpy()
    e_phi = np.c_[-p[:, 1], p[:, 0], np.zeros(len(p))] / rc
    expect = np.cos(a) * np.array([0, 0, 1.0]) + np.sin(a) * e_phi
    err = angle_between_deg(df[["nx", "ny", "nz"]].to_numpy(), expect)
    assert np.median(err) < 1.0 and err.max() < 2.0, (np.median(err), err.max())
    normals = p / np.linalg.norm(p, axis=1, keepdims=True) * np.array([1, 1, 0])
    assert np.abs(np.einsum("ij,ij->i", df[["nx", "ny", "nz"]].to_numpy(), normals)).max() < 0.05


def test_sphere_latitude_circles_and_meridians():
    R = 30.0
    mesh = sphere_mesh(R)
    v = mesh.vertices
    lat = np.arcsin(np.clip(v[:, 2] / R, -1, 1))
    centres = np.flatnonzero(np.abs(v[:, 2]) < 0.8 * R)[::7]
    for field, along_phi in ((np.cos(2 * np.pi * lat * R / WAVELENGTH), True),
                             (np.cos(2 * np.pi * np.arctan2(v[:, 1], v[:, 0]) * 12 / (2 * np.pi)), False)):
        df = directors(mesh, field, patch_radius=5.0, centres=centres)
        p = df[["x", "y", "z"]].to_numpy()
        e_phi = np.c_[-p[:, 1], p[:, 0], np.zeros(len(p))]
        r_hat = p / R
        e_theta = np.cross(e_phi, r_hat)
        expect = e_phi if along_phi else e_theta
        err = angle_between_deg(df[["nx", "ny", "nz"]].to_numpy(), expect)
        assert np.median(err) < 1.0 and np.percentile(err, 95) < 2.0, (along_phi, np.median(err), err.max())


def test_patch_k_and_defaults():
    mesh = sphere_mesh(30.0, subdivisions=4)
    v = mesh.vertices
    lat = np.arcsin(np.clip(v[:, 2] / 30.0, -1, 1))
    intensity = np.cos(2 * np.pi * lat * 30.0 / 8.0)
    df = directors(mesh, intensity, patch_k=80, rng=1)
    assert len(df) > 100
    p = df[["x", "y", "z"]].to_numpy()
    keep = np.abs(p[:, 2]) < 0.8 * 30
    e_phi = np.c_[-p[:, 1], p[:, 0], np.zeros(len(p))]
    assert np.median(angle_between_deg(df[["nx", "ny", "nz"]].to_numpy()[keep], e_phi[keep])) < 2.0
    # default patch count follows the area: 30 per patch area, capped by N
    r = 10 * mean_edge_length(mesh)
    assert default_n_patches(mesh.area, r, len(v)) == min(len(v), round(30 * mesh.area / (np.pi * r**2)))
    assert default_n_patches(4 * np.pi * 200.0**2, 20.0, 10**6) == 12000  # the paper's numbers
    df_default = directors(mesh, intensity, rng=2)
    assert len(df_default) == default_n_patches(mesh.area, default_patch_radius(mesh), len(v))
    # same seed, same result; different seed, other centres
    a = directors(mesh, intensity, patch_radius=6.0, n_patches=50, rng=3)
    b = directors(mesh, intensity, patch_radius=6.0, n_patches=50, rng=3)
    pd.testing.assert_frame_equal(a, b)
    assert not np.array_equal(a["vertex"], directors(mesh, intensity, patch_radius=6.0, n_patches=50, rng=4)["vertex"])


def test_directors_do_not_depend_on_the_frames():
    """3D directors are the same with axis or smooth frames (the frames themselves: test_geometry)."""
    mesh = sphere_mesh(30.0, subdivisions=4)
    lat = np.arcsin(np.clip(mesh.vertices[:, 2] / 30.0, -1, 1))
    intensity = np.cos(2 * np.pi * lat * 30.0 / 7.0 + 0.3 * np.sin(np.arctan2(mesh.vertices[:, 1], mesh.vertices[:, 0]) * 3))
    a = directors(mesh, intensity, patch_radius=6.0, n_patches=300, rng=0, frames="axis")
    b = directors(mesh, intensity, patch_radius=6.0, n_patches=300, rng=0, frames="smooth")
    assert np.median(angle_between_deg(a[["nx", "ny", "nz"]].to_numpy(), b[["nx", "ny", "nz"]].to_numpy())) < 0.5


def test_isotropic_noise_has_no_preferred_direction(rng):
    from scipy import ndimage

    mesh = flat_mesh(size=120.0)
    noise = ndimage.gaussian_filter(rng.standard_normal((140, 140)), 1.5)
    intensity = ndimage.map_coordinates(noise, (mesh.vertices[:, 1] + 10, mesh.vertices[:, 0] + 10), order=1)
    df = directors(mesh, intensity, patch_radius=4.0, n_patches=3000, rng=0)
    theta = np.arctan2(df["ny"], df["nx"])
    assert abs(np.mean(np.exp(2j * theta))) < 0.1
    assert df["coherency"].median() < 0.6


def test_synthetic_vesicle_directors_match_analytic_field(wide_scale):
    """End-to-end smoke test on a small vesicle (R = 50 µm, 10 µm patches: a few fibres per
    patch, measured median 4.3°, 90th percentile 8.5°). The paper-scale accuracy (R = 200 µm,
    20 µm patches, median ≈ 1.5°) is measured by benchmarks/bench_nematics.py."""
    from nemo.peel import peel
    from nemo.surface import reconstruct, split_mesh
    from nemo.synthetic import truth_directors, vesicle

    data, truth = vesicle(radius=50.0, seed=0)
    vol = data[0, :, 0]
    whole = reconstruct(vol, (1.0, 1.0, 1.0), step=2, keep="all")
    inner, _ = split_mesh(whole, by="centre")
    intensity = peel(vol, (1, 1, 1), inner.vertices, vertex_normals(inner), 0, 5, 11)
    df = directors(inner, intensity, patch_radius=10.0, rng=0, **wide_scale(inner, 10.0))
    p = df[["x", "y", "z"]].to_numpy()
    err = angle_between_deg(df[["nx", "ny", "nz"]].to_numpy(), truth_directors(truth, p))
    dirs = np.array([[d["x"], d["y"], d["z"]] for d in truth["defects"] if d["layer"] == 0])
    far = np.min(np.linalg.norm(p[:, None] - dirs[None], axis=2), axis=1) > 10.0
    assert np.median(err[far]) < 5.5 and np.percentile(err[far], 90) < 11.0, (np.median(err[far]), np.percentile(err[far], 90))


def test_bad_input():
    mesh = sphere_mesh(30.0, subdivisions=3)
    n = len(mesh.vertices)
    with pytest.raises(NemoError, match="peel the layer on this mesh"):
        directors(mesh, np.zeros(n + 1), patch_radius=5)
    with pytest.raises(NemoError, match="not both"):
        directors(mesh, np.zeros(n), patch_radius=5, patch_k=20)
    with pytest.raises(NemoError, match="NaN everywhere"):
        directors(mesh, np.full(n, np.nan), patch_radius=5)
    with pytest.raises(NemoError, match="smaller than 2 micro-image pixels"):
        directors(mesh, np.zeros(n), patch_radius=0.5, pixel=1.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        flat = directors(mesh, np.ones(n), patch_radius=8, n_patches=20, rng=0)
    assert len(flat) == 0  # a constant layer has no orientation: no director, not garbage


def test_cli_directors(tmp_path, run_cli):
    mesh = sphere_mesh(30.0, subdivisions=4)
    v = mesh.vertices
    lat = np.arcsin(np.clip(v[:, 2] / 30.0, -1, 1))
    mpath = tmp_path / "s.ply"
    save_mesh(mesh, mpath)
    lpath = tmp_path / "layer.parquet"
    write_table(pd.DataFrame({"vertex": np.arange(len(v)), "intensity": np.cos(2 * np.pi * lat * 30 / 7.0)}), lpath)
    out = tmp_path / "d.parquet"
    code, stdout, err = run_cli("directors", mpath, lpath, "-o", out, "--patch-radius", "6", "--n-patches", "200", "--seed", "1")
    assert code == 0, err
    df = read_table(out, kind="directors")
    assert len(df) == 200 and "median coherency" in stdout
    code, _, err = run_cli("directors", mpath, lpath, "-o", out, "--patch-k", "60", "--frames", "smooth")
    assert code == 0, err
    # no patch size: 0.1 × the object radius (R = 30 µm), at least 8 mean edge lengths
    code, stdout, err = run_cli("directors", mpath, lpath, "-o", out)
    assert code == 0, err
    params = read_provenance(out)["parameters"]
    edge = float(np.mean(mesh.edges_unique_length))
    assert params["patch_radius"] == pytest.approx(max(3.0, 8 * edge), rel=0.01)
    assert params["pixel"] == pytest.approx(max(edge / 4, params["patch_radius"] / 97), rel=0.01)
    small = tmp_path / "small.ply"
    save_mesh(sphere_mesh(30.0, subdivisions=2), small)
    code, _, err = run_cli("directors", small, lpath, "-o", out, "--patch-radius", "6")
    assert code == 2 and "another mesh" in err and "Traceback" not in err


def test_patch_wider_than_the_object_is_refused(tmp_path, run_cli):
    """--patch-radius 1e6 on a 20 µm sphere used to give one director silently."""
    import pandas as pd
    import trimesh

    from nemo.directors import directors
    from nemo.errors import NemoError
    from nemo.mesh import make_mesh, save_mesh
    from nemo.tables import write_table

    ico = trimesh.creation.icosphere(subdivisions=4, radius=20.0)
    mesh = make_mesh(ico.vertices, ico.faces)
    intensity = np.cos(mesh.vertices[:, 0])
    with pytest.raises(NemoError, match="larger than the object"):
        directors(mesh, intensity, patch_radius=1e6)
    mpath, lpath = tmp_path / "s.ply", tmp_path / "layer.parquet"
    save_mesh(mesh, mpath)
    write_table(pd.DataFrame({"vertex": np.arange(len(intensity)), "intensity": intensity}), lpath,
                n_vertices=len(intensity))
    code, _, err = run_cli("directors", mpath, lpath, "--patch-radius", "1e6", "-o", tmp_path / "d.parquet")
    assert code == 2 and "--patch-radius" in err and "larger than the object" in err


def test_micro_image_pixel_and_size_are_bounded(meshed_shell):
    mesh = load_mesh(meshed_shell / "m.inner.ply")
    intensity = np.ones(len(mesh.vertices))
    with pytest.raises(NemoError, match="`pixel`"):
        directors(mesh, intensity, patch_radius=6.0, pixel=0.01)
    # inner wall: object radius 9.94, mean edge 0.92 (pixel ≥ 0.092): 9.5 / 0.095 = 100 px + margin,
    # but only the σ = 4 px window's support is gridded; a window as wide as the patch is refused
    assert len(directors(mesh, intensity + mesh.vertices[:, 0], patch_radius=9.5, pixel=0.095, n_patches=5)) == 5
    with pytest.raises(NemoError, match="micro-images of .* a smaller `sigma`"):
        directors(mesh, intensity, patch_radius=9.5, pixel=0.095, sigma=25.0)
    with pytest.raises(NemoError, match="larger than the object"):
        directors(mesh, intensity, patch_radius=20.0, pixel=0.1)


def test_cli_directors_refuses_a_layer_from_another_mesh(meshed_shell, tmp_path, run_cli, cli_error):
    shell = meshed_shell
    code, _, err = run_cli("peel", shell / "shell.tif", shell / "m.inner.ply", "-o", tmp_path / "layer_inner.parquet",
                           "--range", "0", "2")
    assert code == 0, err
    prov = read_provenance(tmp_path / "layer_inner.parquet")
    assert prov["n_vertices"] == len(load_mesh(shell / "m.inner.ply").vertices)
    # the layer peeled on the inner half given with the whole mesh: refused for its provenance
    code, _, err = run_cli("directors", shell / "m.ply", tmp_path / "layer_inner.parquet", "-o",
                           tmp_path / "d.parquet", "--patch-radius", "3")
    cli_error(code, err, "vertices", "mesh")
    # the same table without provenance (made by another tool): refused for its row count
    layer = read_table(tmp_path / "layer_inner.parquet")
    write_table(layer, tmp_path / "bare.parquet")
    code, _, err = run_cli("directors", shell / "m.ply", tmp_path / "bare.parquet", "-o", tmp_path / "d.parquet",
                           "--patch-radius", "3")
    cli_error(code, err, "rows", "another mesh")
    # and the right pair works
    code, _, err = run_cli("directors", shell / "m.inner.ply", tmp_path / "layer_inner.parquet", "-o",
                           tmp_path / "d_inner.parquet", "--patch-radius", "3", "--n-patches", "100")
    assert code == 0, err
    assert read_provenance(tmp_path / "d_inner.parquet")["n_vertices"] == len(layer)
