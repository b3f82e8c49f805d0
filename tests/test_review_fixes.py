"""Regression tests for the first review's bugs: each fails on the code before the fix.

1. a table computed on another mesh is refused (directors, peel --shift, order, measure);
2. peel refuses a mesh that does not belong to the image (spacing, unit, outside the box);
4. marching cubes at a level equal to voxel values gives no zero-area faces, zero normals,
   fake S = 0 or NaN layers;
6. NaN voxels give a clear error (mesh) or are counted apart (peel);
7. one tangent-frame construction (nemo.geometry.axis_frames) everywhere;
and the quality items with a testable behaviour (9, 10, 12, 15).
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import tifffile
import trimesh

from nemo.cli import main as nemo_main
from nemo.errors import NemoError, NemoWarning
from nemo.geometry import axis_frames
from nemo.io import write_hyperstack
from nemo.mesh import load_mesh, make_mesh, save_mesh, vertex_normals
from nemo.tables import read_provenance, read_table, write_table

R_IN, R_OUT = 10.0, 14.0
N = 40


def _radius_grid(shape=(N, N, N), spacing=(1.0, 1.0, 1.0), centre=(19.3, 19.6, 19.8)):
    z, y, x = (np.arange(n) * s for n, s in zip(shape, spacing))
    zz, yy, xx = np.meshgrid(z, y, x, indexing="ij")
    return np.sqrt((xx - centre[0]) ** 2 + (yy - centre[1]) ** 2 + (zz - centre[2]) ** 2)


def shell_image(spacing=(1.0, 1.0, 1.0)):
    """A smooth hollow shell R_IN < r < R_OUT (uint8, 0 outside, 200 inside the wall)."""
    r = _radius_grid(spacing=spacing)
    wall = 0.5 * (np.tanh((r - R_IN) / 0.8) - np.tanh((r - R_OUT) / 0.8))
    return (200 * wall).astype(np.uint8)


def _error_line(code, err, *words):
    assert code == 2, err
    lines = [ln for ln in err.splitlines() if ln.strip() and not ln.startswith("nemo: ")]
    assert len(lines) == 1 and "error:" in lines[0] and "Traceback" not in err, err
    for w in words:
        assert w.lower() in lines[0].lower(), (w, lines[0])
    return lines[0]


@pytest.fixture(scope="module")
def shell(tmp_path_factory):
    """shell.tif (1 µm voxels) with m.ply / m.inner.ply / m.outer.ply from 'nemo mesh --split'."""
    d = tmp_path_factory.mktemp("shell")
    write_hyperstack(d / "shell.tif", shell_image(), (1.0, 1.0, 1.0), axes="ZYX")
    assert nemo_main(["mesh", str(d / "shell.tif"), "-o", str(d / "m.ply"), "--split", "centre", "--step", "1"]) == 0
    return d


# ---------------------------------------------------------------------------------- item 1
def test_layer_from_another_mesh_is_refused(shell, run_cli):
    code, _, err = run_cli("peel", shell / "shell.tif", shell / "m.inner.ply", "-o", shell / "layer_inner.parquet",
                           "--range", "0", "2")
    assert code == 0, err
    prov = read_provenance(shell / "layer_inner.parquet")
    assert prov["n_vertices"] == len(load_mesh(shell / "m.inner.ply").vertices)
    # the reviewer's case: the layer peeled on the inner half given with the whole mesh
    code, _, err = run_cli("directors", shell / "m.ply", shell / "layer_inner.parquet", "-o", shell / "d.parquet",
                           "--patch-radius", "3")
    _error_line(code, err, "vertices", "mesh")
    # the same table without provenance (made by another tool): refused for its row count
    layer = read_table(shell / "layer_inner.parquet")
    write_table(layer, shell / "bare.parquet")
    code, _, err = run_cli("directors", shell / "m.ply", shell / "bare.parquet", "-o", shell / "d.parquet",
                           "--patch-radius", "3")
    _error_line(code, err, "rows", "another mesh")
    # and the right pair works
    code, _, err = run_cli("directors", shell / "m.inner.ply", shell / "layer_inner.parquet", "-o",
                           shell / "d_inner.parquet", "--patch-radius", "3", "--n-patches", "100")
    assert code == 0, err
    assert read_provenance(shell / "d_inner.parquet")["n_vertices"] == len(layer)


def test_shift_order_and_curvature_tables_from_another_mesh(shell, tmp_path, run_cli):
    code, _, err = run_cli("thickness", shell / "m.inner.ply", shell / "m.outer.ply", "-o", shell / "th.parquet")
    assert code == 0, err
    n_inner = len(load_mesh(shell / "m.inner.ply").vertices)
    prov = read_provenance(shell / "th.parquet")
    assert prov["mesh"] == str(shell / "m.inner.ply") and prov["n_vertices"] == n_inner  # item 12
    code, _, err = run_cli("peel", shell / "shell.tif", shell / "m.ply", "-o", shell / "l.parquet", "--range", "0", "1",
                           "--shift", f"{shell / 'th.parquet'}:thickness", "--shift-fraction", "0.2")
    _error_line(code, err, "th.parquet", "vertices")
    code, _, err = run_cli("curvature", shell / "m.inner.ply", "-o", shell / "k.parquet", "--radius", "3")
    assert code == 0, err
    assert read_provenance(shell / "k.parquet")["n_vertices"] == n_inner  # item 12
    code, _, err = run_cli("measure", shell / "m.outer.ply", "--curvature", shell / "k.parquet")
    _error_line(code, err, "k.parquet", "vertices")
    # directors of the inner half averaged on the whole mesh: made here, in this test's own folder
    # (no dependence on which test ran before on this worker)
    code, _, err = run_cli("peel", shell / "shell.tif", shell / "m.inner.ply", "-o", tmp_path / "layer.parquet",
                           "--range", "0", "2")
    assert code == 0, err
    code, _, err = run_cli("directors", shell / "m.inner.ply", tmp_path / "layer.parquet", "-o",
                           tmp_path / "d_inner.parquet", "--patch-radius", "3", "--n-patches", "100")
    assert code == 0, err
    assert read_provenance(tmp_path / "d_inner.parquet")["n_vertices"] == n_inner
    code, _, err = run_cli("order", shell / "m.ply", tmp_path / "d_inner.parquet", "-o", tmp_path / "o.parquet",
                           "--radius", "5")
    _error_line(code, err, "vertices")
    assert not (tmp_path / "o.parquet").exists()
    # and on its own mesh the same table is accepted
    code, _, err = run_cli("order", shell / "m.inner.ply", tmp_path / "d_inner.parquet", "-o",
                           tmp_path / "o.parquet", "--radius", "5")
    assert code == 0, err


# ---------------------------------------------------------------------------------- item 2
def test_peel_refuses_a_mesh_made_at_another_spacing(shell, tmp_path, run_cli):
    img = shell / "shell.tif"
    code, _, err = run_cli("mesh", img, "-o", tmp_path / "half.ply", "--spacing", "0.5", "0.5", "0.5", "--step", "1")
    assert code == 0, err
    assert load_mesh(tmp_path / "half.ply").metadata["spacing"] == (0.5, 0.5, 0.5)
    code, _, err = run_cli("peel", img, tmp_path / "half.ply", "-o", tmp_path / "l.parquet", "--range", "0", "2")
    line = _error_line(code, err, "spacing", "0.5", "--spacing")
    assert "(1, 1, 1)" in line
    # with the spacing it was made with, it is accepted
    code, _, err = run_cli("peel", img, tmp_path / "half.ply", "-o", tmp_path / "l.parquet", "--range", "0", "1",
                           "--spacing", "0.5", "0.5", "0.5")
    assert code == 0, err


def test_peel_refuses_a_pixel_unit_mesh_on_a_calibrated_image(tmp_path, run_cli):
    raw = tmp_path / "raw.tif"
    tifffile.imwrite(raw, shell_image())  # no calibration: unit "pixel"
    code, _, err = run_cli("mesh", raw, "-o", tmp_path / "px.ply", "--step", "1")
    assert code == 0, err
    assert load_mesh(tmp_path / "px.ply").units == "pixel"
    code, _, err = run_cli("peel", raw, tmp_path / "px.ply", "-o", tmp_path / "l.parquet", "--range", "0", "2",
                           "--spacing", "0.5", "0.5", "0.5")
    _error_line(code, err, "unit", "pixel", "um")


def test_peel_refuses_a_mesh_outside_the_image(shell, tmp_path, run_cli):
    mesh = load_mesh(shell / "m.inner.ply")
    moved = make_mesh(np.asarray(mesh.vertices) * 2.5, mesh.faces)  # an external mesh: no spacing recorded
    save_mesh(moved, tmp_path / "big.ply")
    code, _, err = run_cli("peel", shell / "shell.tif", tmp_path / "big.ply", "-o", tmp_path / "l.parquet",
                           "--range", "0", "1")
    _error_line(code, err, "outside the image", "% of the mesh")


# ---------------------------------------------------------------------------------- item 4
@pytest.fixture(scope="module")
def quantised():
    """The reviewer's case, small: a uint8 synthetic vesicle meshed at the integer level 64
    without blur, where many voxels equal the level (old code: zero-area faces, zero normals)."""
    from nemo.surface import reconstruct, split_mesh
    from nemo.synthetic import vesicle

    data, truth = vesicle(radius=20.0, seed=1, fibre_spacing=3.0)
    vol = data[0, :, 0]
    whole = reconstruct(vol, (1.0, 1.0, 1.0), sigma=0.0, threshold=64, step=1, keep="all")
    inner, outer = split_mesh(whole, by="centre")
    return vol, np.asarray(truth["centre"]), float(truth["radius"]), (whole, inner, outer)


def test_level_on_voxel_values_gives_no_degenerate_faces(quantised):
    _, centre, radius, meshes = quantised
    for mesh in meshes:
        assert mesh.area_faces.min() > 0
        normals = vertex_normals(mesh)
        assert np.isfinite(normals).all()
        np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-9)
        assert np.unique(mesh.faces).size == len(mesh.vertices)  # no unreferenced vertex
    _, inner, outer = meshes
    # no face of one wall in the other half (old code: zero-area faces of the outer wall, sign 0,
    # went to the inner half)
    r_in = np.linalg.norm(inner.vertices - centre, axis=1)
    r_out = np.linalg.norm(outer.vertices - centre, axis=1)
    assert r_in.max() < r_out.min()
    assert abs(np.median(r_in) - radius) < 1.5


def test_level_on_voxel_values_gives_no_fake_defects_or_nan_layer(quantised):
    from nemo.order import order
    from nemo.peel import peel

    vol, centre, radius, (_, inner, _) = quantised
    p = inner.vertices - centre
    e_phi = np.c_[-p[:, 1], p[:, 0], np.zeros(len(p))]
    v = np.flatnonzero(np.linalg.norm(e_phi, axis=1) > 0.3 * radius)  # away from the poles
    nrm = vertex_normals(inner)[v]
    d = e_phi[v] - np.einsum("ij,ij->i", e_phi[v], nrm)[:, None] * nrm  # tangent to the mesh
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    df = pd.DataFrame({"vertex": v, "x": inner.vertices[v, 0], "y": inner.vertices[v, 1],
                       "z": inner.vertices[v, 2], "nx": d[:, 0], "ny": d[:, 1], "nz": d[:, 2], "coherency": 1.0})
    s = order(inner, df, radius=2.0, targets=v)["S"].to_numpy()
    # latitude circles on an unsmoothed staircase: S near 1 (lowered by the normals' scatter),
    # never the fake S = 0 of a vertex without a normal
    assert np.isfinite(s).all() and np.median(s) > 0.9 and s.min() > 0.5
    layer = peel(vol, (1.0, 1.0, 1.0), inner.vertices, vertex_normals(inner), 0.0, 2.0, 5)
    assert np.isfinite(layer).all()


def test_tangential_eig_is_nan_without_a_tangent_plane():
    from nemo.order import lift_q, tangential_eig

    n = np.array([[1.0, 0, 0], [1.0, 0, 0]])
    normals = np.array([[0, 0, 1.0], [0, 0, 0.0]])
    s, director = tangential_eig(lift_q(n, np.array([[0, 0, 1.0], [0, 0, 1.0]])), normals)
    assert s[0] == pytest.approx(1.0) and np.isnan(s[1]) and np.isnan(director[1]).all()


# ---------------------------------------------------------------------------------- item 6
def test_nan_voxels_are_a_clear_error_for_mesh(tmp_path, run_cli):
    from nemo.surface import reconstruct

    vol = shell_image().astype(np.float32)
    vol[0, :5, :5] = np.nan
    with pytest.raises(NemoError, match="25 NaN or infinite voxels"):
        reconstruct(vol, (1.0, 1.0, 1.0))
    write_hyperstack(tmp_path / "nan.tif", vol, (1.0, 1.0, 1.0), axes="ZYX")
    code, _, err = run_cli("mesh", tmp_path / "nan.tif", "-o", tmp_path / "m.ply")
    _error_line(code, err, "NaN", "voxels")


def test_peel_counts_nan_voxels_apart_from_outside(shell):
    from nemo.peel import peel

    mesh = load_mesh(shell / "m.inner.ply")
    vol = shell_image().astype(np.float32)
    vol[: N // 2] = np.nan  # the lower half of the volume holds no data
    with pytest.warns(NemoWarning) as record:
        out = peel(vol, (1.0, 1.0, 1.0), mesh.vertices, vertex_normals(mesh), 0, 2, 5)
    message = " ".join(str(w.message) for w in record)
    low = mesh.vertices[:, 2] < N // 2 - 3
    assert np.isnan(out[low]).all() and np.isfinite(out[mesh.vertices[:, 2] > N // 2 + 1]).all()
    assert "sample NaN voxels" in message and "outside the image" not in message


# ---------------------------------------------------------------------------------- item 7
def test_one_axis_frame_construction():
    from nemo.geometry import axis_frames as tangent_basis
    from nemo.synthetic import nematic_angle, preset_defects

    normals = np.array([[0.93, 0.3, 0.21], [1.0, 0, 0], [0, 0, 1.0], [-0.2, 0.97, 0.1]])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    t1, t2 = axis_frames(normals)
    for a, b in zip(tangent_basis(normals), (t1, t2)):
        np.testing.assert_array_equal(a, b)
    d, m = preset_defects("tetrahedron")
    th = nematic_angle(normals, d, m)
    np.testing.assert_allclose(th, nematic_angle(normals, d, m, t1, t2))


# ---------------------------------------------------------------------------------- items 9, 10, 15
def test_option_sizes_are_bounded(shell):
    from nemo.directors import directors
    from nemo.peel import peel

    mesh = load_mesh(shell / "m.inner.ply")
    intensity = np.ones(len(mesh.vertices))
    with pytest.raises(NemoError, match="`pixel`"):
        directors(mesh, intensity, patch_radius=6.0, pixel=0.01)
    # inner wall: object radius 9.94, mean edge 0.92 (pixel ≥ 0.092): 9.5 / 0.095 = 100 px + margin
    with pytest.raises(NemoError, match="micro-images of"):
        directors(mesh, intensity, patch_radius=9.5, pixel=0.095)
    with pytest.raises(NemoError, match="larger than the object"):
        directors(mesh, intensity, patch_radius=20.0, pixel=0.1)
    with pytest.raises(NemoError, match="at most"):
        peel(shell_image(), (1.0, 1.0, 1.0), mesh.vertices, vertex_normals(mesh), 0, 2, n_samples=10_000)


def test_curvature_radius_too_large_warns():
    from nemo.morphology import curvature

    ico = trimesh.creation.icosphere(subdivisions=3, radius=30.0)
    mesh = make_mesh(ico.vertices, ico.faces)
    with pytest.warns(NemoWarning, match="large for this surface"):
        curvature(mesh, 1000.0, rng=0)


def test_alignment_checks_normals_and_max_distance():
    from nemo.order import alignment

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
