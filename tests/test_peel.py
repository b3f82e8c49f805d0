"""Peeling against analytic volumes: Gaussian shells, anisotropic voxels, reductions, CLI."""

from __future__ import annotations

import warnings

import numpy as np
import pandas as pd
import pytest
import tifffile
import trimesh
from scipy import ndimage

from nemo.errors import NemoError, NemoWarning
from nemo.io import write_hyperstack
from nemo.mesh import load_mesh, make_mesh, save_mesh, vertex_normals
from nemo.peel import leaves_image, peel, sample_depths
from nemo.tables import read_table, write_table

R = 20.0        # sphere radius (µm)
W = 1.2         # Gaussian shell half-width (µm)
SPACING = (2.0, 1.0, 1.0)  # dz = 2 dx


def _grid(spacing, extent=34.0):
    dz, dy, dx = spacing
    shape = tuple(int(round(2 * extent / s)) + 1 for s in spacing)
    z, y, x = (np.arange(n) * s for n, s in zip(shape, spacing))
    centre = np.array([x[-1], y[-1], z[-1]]) / 2.0  # x, y, z
    return shape, (z, y, x), centre


def shell_volume(radius_shell, spacing=SPACING, width=W):
    """exp(-(|x - c| - radius_shell)² / 2w²) sampled at voxel centres (x = col·dx ...)."""
    shape, (z, y, x), centre = _grid(spacing)
    zz, yy, xx = np.meshgrid(z, y, x, indexing="ij")
    r = np.sqrt((xx - centre[0]) ** 2 + (yy - centre[1]) ** 2 + (zz - centre[2]) ** 2)
    return np.exp(-((r - radius_shell) ** 2) / (2 * width**2)), centre


def sphere_mesh(centre, radius=R, subdivisions=3):
    ico = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return make_mesh(ico.vertices + centre, ico.faces)


def analytic_normals(mesh, centre):
    v = mesh.vertices - centre
    return v / np.linalg.norm(v, axis=1, keepdims=True)


@pytest.mark.parametrize("interp", ["linear", "cubic"])
@pytest.mark.parametrize("r0", [3.0, 5.5])
def test_profile_peaks_at_shell_depth_anisotropic(interp, r0):
    width = 2.0  # sampled adequately by the 2 µm z planes
    vol, centre = shell_volume(R + r0, width=width)
    mesh = sphere_mesh(centre)
    normals = analytic_normals(mesh, centre)
    _, profile, depths = peel(vol, SPACING, mesh.vertices, normals, -2.0, 10.0, n_samples=97,
                              interp=interp, return_profile=True)
    assert depths[1] - depths[0] == pytest.approx(0.125)
    # sub-sample peak from a parabola through the three top samples
    k = np.argmax(profile, axis=1)
    rows = np.arange(len(k))
    y0, y1, y2 = profile[rows, k - 1], profile[rows, k], profile[rows, k + 1]
    refined = depths[k] + 0.125 * 0.5 * (y0 - y2) / (y0 - 2 * y1 + y2)
    err = np.abs(refined - r0)
    if interp == "cubic":
        assert err.max() < 0.1
    else:
        # a trilinear interpolant peaks on a sample plane: at most dz/2 off where the ray runs
        # along z, much less elsewhere
        assert err.max() <= SPACING[0] / 2 + 0.01
        assert np.median(err) < 0.25  # (a wrong z scale would be off by µm)


def test_mean_and_max_reductions_match_analytic_shell():
    r0 = 2.5
    vol, centre = shell_volume(R + r0, spacing=(1.0, 1.0, 1.0))
    mesh = sphere_mesh(centre)
    normals = analytic_normals(mesh, centre)
    d_min, d_max, n = 0.0, 5.0, 11
    depths = sample_depths(d_min, d_max, n)
    expect = np.exp(-((depths - r0) ** 2) / (2 * W**2))
    mean = peel(vol, (1, 1, 1), mesh.vertices, normals, d_min, d_max, n, reduce="mean", interp="cubic")
    mx = peel(vol, (1, 1, 1), mesh.vertices, normals, d_min, d_max, n, reduce="max", interp="cubic")
    assert np.abs(mean - expect.mean()).max() < 0.01
    assert np.abs(mx - expect.max()).max() < 0.01
    _, prof, _ = peel(vol, (1, 1, 1), mesh.vertices, normals, d_min, d_max, n, return_profile=True)
    lin_mean = peel(vol, (1, 1, 1), mesh.vertices, normals, d_min, d_max, n)
    np.testing.assert_allclose(lin_mean, prof.mean(axis=1))


def test_inward_flag_peels_inside():
    r0 = 4.0
    vol, centre = shell_volume(R - r0, width=2.0)
    mesh = sphere_mesh(centre)
    normals = vertex_normals(mesh)
    assert np.all(np.einsum("ij,ij->i", normals, mesh.vertices - centre) > 0)  # outward
    _, prof_in, depths = peel(vol, SPACING, mesh.vertices, -normals, 0, 8, 33, interp="cubic",
                              return_profile=True)
    assert np.abs(depths[np.argmax(prof_in, axis=1)] - r0).max() <= 0.25 + 1e-9
    outward = peel(vol, SPACING, mesh.vertices, normals, 0, 8, 33)
    inward = peel(vol, SPACING, mesh.vertices, -normals, 0, 8, 33)
    assert inward.min() > 3 * outward.max()


def test_shift_moves_the_range():
    r0 = 5.0
    vol, centre = shell_volume(R + r0, width=2.0)
    mesh = sphere_mesh(centre)
    normals = analytic_normals(mesh, centre)
    n = len(mesh.vertices)
    shifted = peel(vol, SPACING, mesh.vertices, normals, 0, 2, 5, shift=np.full(n, 3.0))
    moved = peel(vol, SPACING, mesh.vertices, normals, 3, 5, 5)
    np.testing.assert_allclose(shifted, moved, atol=1e-12)
    # per-vertex shift: half the vertices shifted onto the shell, the others not
    shift = np.where(np.arange(n) % 2 == 0, r0, 0.0)
    value = peel(vol, SPACING, mesh.vertices, normals, 0, 0, 1, shift=shift, interp="cubic")
    assert value[::2].min() > 0.97 and value[1::2].max() < 0.05
    with pytest.warns(Warning, match="NaN"):
        nan_shift = peel(vol, SPACING, mesh.vertices, normals, 0, 1, 3, shift=np.where(shift > 0, np.nan, 0.0))
    assert np.isnan(nan_shift[::2]).all() and np.isfinite(nan_shift[1::2]).all()


def test_nan_outside_the_volume_and_errors():
    vol, centre = shell_volume(R + 2)
    mesh = sphere_mesh(centre)
    normals = analytic_normals(mesh, centre)
    far = 34.0 - R + 1.0  # beyond the volume's faces along the axes
    with pytest.warns(Warning, match="outside the image"):
        out = peel(vol, SPACING, mesh.vertices, normals, 0, far + 10, 5)
    axis_aligned = np.abs(normals).max(axis=1) > 0.95
    assert np.isnan(out[axis_aligned]).all()
    with pytest.raises(NemoError, match="outside the image"):
        peel(vol, SPACING, mesh.vertices + 1000.0, normals, 0, 1, 3)
    with pytest.raises(NemoError, match="DMIN <= DMAX"):
        peel(vol, SPACING, mesh.vertices, normals, 3, 1)
    with pytest.raises(NemoError, match="3-D"):
        peel(vol[0], SPACING, mesh.vertices, normals, 0, 1)
    with pytest.raises(NemoError, match="reduction"):
        peel(vol, SPACING, mesh.vertices, normals, 0, 1, reduce="median")
    with pytest.raises(NemoError, match="one value per vertex"):
        peel(vol, SPACING, mesh.vertices, normals, 0, 1, shift=np.zeros(3))


def test_cli_peel_profile_shift_inward(tmp_path, run_cli):
    r0 = 3.0
    vol, centre = shell_volume(R + r0, width=2.0)
    img = tmp_path / "shell.tif"
    write_hyperstack(img, (vol * 200).astype(np.uint8), SPACING, axes="ZYX")
    mesh = sphere_mesh(centre)
    mpath = tmp_path / "sphere.ply"
    save_mesh(mesh, mpath)
    out = tmp_path / "layer.parquet"
    code, stdout, err = run_cli("peel", img, mpath, "-o", out, "--range", "0", "6", "--samples", "25",
                                "--interp", "cubic", "--profile")
    assert code == 0, err
    layer = read_table(out, kind="layer")
    assert len(layer) == len(mesh.vertices) and layer["intensity"].notna().all()
    prof = read_table(tmp_path / "layer.profile.parquet", columns=("vertex", "depth", "intensity"))
    assert len(prof) == 25 * len(mesh.vertices)
    peak = prof.loc[prof.groupby("vertex")["intensity"].idxmax(), "depth"].to_numpy()
    assert np.abs(peak - r0).max() <= 0.5
    # --shift FIELDS:COLUMN × --shift-fraction moves the range onto the shell
    fields = tmp_path / "fields.parquet"
    write_table(pd.DataFrame({"vertex": np.arange(len(mesh.vertices)), "thickness": np.full(len(mesh.vertices), 2 * r0)}), fields)
    out2 = tmp_path / "shifted.parquet"
    code, _, err = run_cli("peel", img, mpath, "-o", out2, "--range", "0", "0", "--samples", "1",
                           "--shift", f"{fields}:thickness", "--shift-fraction", "0.5", "--reduce", "max")
    assert code == 0, err
    shifted = read_table(out2, kind="layer")["intensity"].to_numpy()
    assert shifted.min() > 0.85 * 200  # on the shell (unshifted: exp(-9/8) × 200 ≈ 65)
    # --inward looks inside, where the image is dark
    out3 = tmp_path / "inward.parquet"
    code, _, err = run_cli("peel", img, mpath, "-o", out3, "--range", "0", "6", "--inward",
                           "--interp", "cubic")
    assert code == 0, err
    tau = sample_depths(0, 6, 11)
    expect_in = (200 * np.exp(-((r0 + tau) ** 2) / (2 * 2.0**2))).mean()
    expect_out = (200 * np.exp(-((tau - r0) ** 2) / (2 * 2.0**2))).mean()
    inward = read_table(out3)["intensity"].to_numpy()
    assert np.abs(inward - expect_in).max() < 1.5  # uint8 rounding, mesh normals
    code, _, err = run_cli("peel", img, mpath, "-o", out3, "--range", "0", "6", "--interp", "cubic")
    assert np.abs(read_table(out3)["intensity"].to_numpy() - expect_out).max() < 1.5


def test_cli_peel_bad_input(tmp_path, run_cli):
    vol, centre = shell_volume(R + 2)
    img = tmp_path / "shell.tif"
    write_hyperstack(img, (vol * 200).astype(np.uint8), SPACING, axes="ZYX")
    mpath = tmp_path / "sphere.ply"
    save_mesh(sphere_mesh(centre), mpath)
    code, _, err = run_cli("peel", img, tmp_path / "missing.ply", "-o", tmp_path / "l.parquet", "--range", "0", "5")
    assert code == 2 and "mesh file not found" in err and "Traceback" not in err
    code, _, err = run_cli("peel", img, mpath, "-o", tmp_path / "l.parquet", "--range", "5", "0")
    assert code == 2 and "DMIN" in err
    code, _, err = run_cli("peel", img, mpath, "-o", tmp_path / "l.parquet", "--range", "0", "5",
                           "--shift", "nofile.parquet")
    assert code == 2 and "COLUMN" in err
    code, _, err = run_cli("peel", img, mpath, "-o", tmp_path / "l.parquet", "--range", "0", "5",
                           "--spacing", "0.01", "0.01", "0.01")
    assert code == 2 and "outside the image" in err


def test_a_foreign_mesh_at_the_wrong_scale_is_warned_about(tmp_path, run_cli):
    """A mesh made elsewhere and scaled × 0.5 (still inside the image) used to be peeled silently.
    It lies in the shell's empty lumen: the warning names the scale, and the layer, 0 everywhere,
    is warned about (its directors will be skipped)."""
    from nemo.peel import mesh_object_extent_ratio

    vol, centre = shell_volume(R + 2)
    img = tmp_path / "shell.tif"
    write_hyperstack(img, (vol * 200).astype(np.uint8), SPACING, axes="ZYX")
    good = sphere_mesh(centre)
    half = make_mesh(centre + 0.5 * (np.asarray(good.vertices) - centre), good.faces)
    assert mesh_object_extent_ratio(good, vol, SPACING) == pytest.approx(R / (R + 2), rel=0.1)
    assert mesh_object_extent_ratio(half, vol, SPACING) == pytest.approx(0.5 * R / (R + 2), rel=0.1)
    for mesh, name, warned in ((good, "good.ply", False), (half, "half.ply", True)):
        save_mesh(mesh, tmp_path / name)  # no spacing in the header: a mesh made elsewhere
        code, _, err = run_cli("peel", img, tmp_path / name, "-o", tmp_path / f"{name}.parquet", "--range", "0", "4")
        assert code == 0 and ("a mesh off the object" in err) == warned, err
        assert ("× the extent of the image's bright object" in err) == warned, err


# ------------------------------------------------------------------ on the meshed shell (conftest)
def test_peel_counts_nan_voxels_apart_from_outside(meshed_shell, shell_image):
    mesh = load_mesh(meshed_shell / "m.inner.ply")
    vol = shell_image.astype(np.float32)
    half = len(vol) // 2
    vol[:half] = np.nan  # the lower half of the volume holds no data
    with pytest.warns(NemoWarning) as record:
        out = peel(vol, (1.0, 1.0, 1.0), mesh.vertices, vertex_normals(mesh), 0, 2, 5)
    message = " ".join(str(w.message) for w in record)
    low = mesh.vertices[:, 2] < half - 3
    assert np.isnan(out[low]).all() and np.isfinite(out[mesh.vertices[:, 2] > half + 1]).all()
    assert "sample NaN voxels" in message and "outside the image" not in message


def test_number_of_samples_is_bounded(meshed_shell, shell_image):
    mesh = load_mesh(meshed_shell / "m.inner.ply")
    with pytest.raises(NemoError, match="at most"):
        peel(shell_image, (1.0, 1.0, 1.0), mesh.vertices, vertex_normals(mesh), 0, 2, n_samples=10_000)


def test_cli_peel_refuses_a_mesh_made_at_another_spacing(meshed_shell, tmp_path, run_cli, cli_error):
    img = meshed_shell / "shell.tif"
    code, _, err = run_cli("mesh", img, "-o", tmp_path / "half.ply", "--spacing", "0.5", "0.5", "0.5", "--step", "1")
    assert code == 0, err
    assert load_mesh(tmp_path / "half.ply").metadata["spacing"] == (0.5, 0.5, 0.5)
    code, _, err = run_cli("peel", img, tmp_path / "half.ply", "-o", tmp_path / "l.parquet", "--range", "0", "2")
    line = cli_error(code, err, "spacing", "0.5", "--spacing")
    assert "(1, 1, 1)" in line
    # with the spacing it was made with, it is accepted
    code, _, err = run_cli("peel", img, tmp_path / "half.ply", "-o", tmp_path / "l.parquet", "--range", "0", "1",
                           "--spacing", "0.5", "0.5", "0.5")
    assert code == 0, err


def test_cli_peel_refuses_a_pixel_unit_mesh_on_a_calibrated_image(shell_image, tmp_path, run_cli, cli_error):
    raw = tmp_path / "raw.tif"
    tifffile.imwrite(raw, shell_image)  # no calibration: unit "pixel"
    code, _, err = run_cli("mesh", raw, "-o", tmp_path / "px.ply", "--step", "1")
    assert code == 0, err
    assert load_mesh(tmp_path / "px.ply").units == "pixel"
    code, _, err = run_cli("peel", raw, tmp_path / "px.ply", "-o", tmp_path / "l.parquet", "--range", "0", "2",
                           "--spacing", "0.5", "0.5", "0.5")
    cli_error(code, err, "unit", "pixel", "um")


def test_cli_peel_refuses_a_mesh_outside_the_image(meshed_shell, tmp_path, run_cli, cli_error):
    mesh = load_mesh(meshed_shell / "m.inner.ply")
    moved = make_mesh(np.asarray(mesh.vertices) * 2.5, mesh.faces)  # an external mesh: no spacing recorded
    save_mesh(moved, tmp_path / "big.ply")
    code, _, err = run_cli("peel", meshed_shell / "shell.tif", tmp_path / "big.ply", "-o", tmp_path / "l.parquet",
                           "--range", "0", "1")
    cli_error(code, err, "outside the image", "% of the mesh")


def test_cli_peel_refuses_a_shift_table_from_another_mesh(meshed_shell, tmp_path, run_cli, cli_error):
    shell = meshed_shell
    code, _, err = run_cli("thickness", shell / "m.inner.ply", shell / "m.outer.ply", "-o", tmp_path / "th.parquet")
    assert code == 0, err
    # a thickness table of the inner half used to shift the range on the whole mesh
    code, _, err = run_cli("peel", shell / "shell.tif", shell / "m.ply", "-o", tmp_path / "l.parquet",
                           "--range", "0", "1", "--shift", f"{tmp_path / 'th.parquet'}:thickness",
                           "--shift-fraction", "0.2")
    cli_error(code, err, "th.parquet", "vertices")


def _textured_wall(depth: float, R: float = 20.0):
    """A ball of radius R (1 µm voxels) under a smooth 9 µm wall whose fibres (meridional stripes,
    2 µm wide) lie ``depth`` µm outside it; the wall's inner surface as an icosphere."""
    n = 80
    z, y, x = (np.indices((n, n, n)) - n / 2 + 0.5).astype(np.float64)
    r = np.sqrt(x**2 + y**2 + z**2)
    wall = ((r >= R) & (r <= R + 9)).astype(np.float32) * 100
    stripes = np.cos(12 * np.arctan2(y, x)) > 0.5
    volume = ndimage.gaussian_filter(wall + 300 * (np.abs(r - R - depth) < 1.0) * stripes, 1.0)  # a PSF
    sphere = trimesh.creation.icosphere(5, radius=R)
    sphere.apply_translation([n / 2 - 0.5] * 3)
    return volume, sphere


@pytest.mark.parametrize("depth", [3.0, 7.0])
def test_texture_profile_finds_the_depth_of_the_fibres(depth):
    """The texture along the surface peaks at the fibres' depth; a layer [0, 5] µm holds the
    fibres at 3 µm and misses those at 7 µm (then ``outside``); the smooth wall has no texture."""
    from nemo.peel import texture_profile

    volume, sphere = _textured_wall(depth)
    prof = texture_profile(volume, (1.0, 1.0, 1.0), sphere.vertices, vertex_normals(sphere), 0.0, 5.0)
    assert prof["peak_depth"] == pytest.approx(depth, abs=0.6)
    assert prof["outside"] == (depth > 5)
    wall = ndimage.gaussian_filter(np.where(volume > 105, 100.0, volume), 1.0)  # no fibres
    smooth = texture_profile(wall, (1.0, 1.0, 1.0), sphere.vertices, vertex_normals(sphere), 0.0, 5.0)
    assert not smooth["outside"] and smooth["peak"] < 0.2 * prof["peak"]


def test_a_layer_that_misses_the_texture_is_warned_about_and_flagged():
    from nemo import stages
    from nemo.summary import quality_flags

    volume, sphere = _textured_wall(7.0)
    with pytest.warns(NemoWarning, match="texture peaks at depth 7"):
        _, p = stages.peel(volume, (1.0, 1.0, 1.0), sphere, {"range": [0, 5]})
    assert p["texture"]["outside"] and p["texture"]["peak_depth"] == pytest.approx(7.0, abs=0.6)
    _, p = stages.peel(volume, (1.0, 1.0, 1.0), sphere, {"range": [4, 9]})
    assert not p["texture"]["outside"]
    row = {"euler_characteristic": 2, "charge_sum": 2.0, "n_defects": 4, "n_directors": 100, "S_mean": 0.8}
    assert quality_flags(row, {}) == []
    row["texture"] = {"outside": True, "peak_depth": 7.0}
    assert [f for f in quality_flags(row, {}) if "texture peaks at depth 7" in f]


def test_leaves_image_is_where_peel_samples_outside_the_image():
    """:func:`leaves_image` names exactly the vertices whose segments peel finds partly outside the
    image (random points and directions in and near an anisotropic box; a shift; no normal)."""
    rng = np.random.default_rng(3)
    shape, spacing = (12, 20, 30), (2.0, 1.0, 1.0)
    box = (np.array(shape) - 1.0)[::-1] * np.array(spacing)[::-1]  # x, y, z
    vertices = rng.uniform(0.05, 0.95, (4000, 3)) * box
    normals = rng.normal(size=(4000, 3))
    normals[:5] = 0.0  # no normal: NaN intensity, but no segment to leave the image
    shift = rng.uniform(-2.0, 2.0, 4000)
    volume = rng.uniform(1.0, 2.0, shape)
    for d_min, d_max, sh, n in ((0.0, 6.0, None, 5), (-4.0, 3.0, shift, 5), (2.0, 2.0, shift, 1)):
        out = leaves_image(shape, spacing, vertices, normals, sample_depths(d_min, d_max, n), sh)
        with pytest.warns(NemoWarning):
            nan = np.isnan(peel(volume, spacing, vertices, normals, d_min, d_max, n_samples=n, shift=sh))
        assert 200 < out.sum() < 3900
        np.testing.assert_array_equal(out, nan & np.isfinite(normals).all(axis=1) & (np.abs(normals).sum(axis=1) > 0))
    # a vertex on the box's high face, sampled inwards: (n − 1) d / d can exceed n − 1 in floating point
    shape, spacing = (7, 7, 7), (0.1, 0.1, 0.1)
    on_face = np.array([[(7 - 1) * 0.1, 0.3, 0.3], [0.3, 0.3, 0.3]])  # and one inside
    inwards = np.array([[-1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NemoWarning)
        nan = np.isnan(peel(np.ones(shape), spacing, on_face, inwards, 0.0, 0.2, n_samples=3))
    np.testing.assert_array_equal(leaves_image(shape, spacing, on_face, inwards, sample_depths(0.0, 0.2, 3)), nan)

