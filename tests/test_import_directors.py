"""Directors from other tools (`nemo directors import`, nemo.import_directors): a director field
given at scattered points near a sphere, as vectors or as angles in a stated tangent basis, is
mapped onto the mesh and equals the analytic field; several points on one vertex are averaged
as a nematic; far points are refused with a count, a wrong unit is an error; the imported table
runs through `nemo order` and `nemo defects` and gives the analytic field's defects."""

from __future__ import annotations

import warnings

import numpy as np
import pandas as pd
import pytest
import trimesh

from nemo import config
from nemo.errors import NemoError, NemoWarning
from nemo.geometry import axis_frames
from nemo.import_directors import import_directors, nematic_mean, read_points
from nemo.mesh import make_mesh, mean_edge_length, save_mesh, vertex_normals
from nemo.tables import SCHEMAS, read_provenance, read_table

R = 50.0
#: Where the comparisons are made: away from the poles, where the azimuthal field turns fast.
EQUATOR = 0.6


@pytest.fixture(scope="module")
def sphere():
    s = trimesh.creation.icosphere(4, radius=R)  # 2562 vertices, mean edge 3.8
    return make_mesh(s.vertices, s.faces)


def azimuthal(p: np.ndarray) -> np.ndarray:
    """The analytic tangent field ẑ × p̂ (normalised): two +1 defects at the poles."""
    e = np.cross([0.0, 0.0, 1.0], p)
    return e / np.linalg.norm(e, axis=1, keepdims=True)


def scattered(n: int, seed: int = 0, off: float = 0.5) -> np.ndarray:
    """Random points (not at vertices) within ``off`` µm of the sphere."""
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return u * (R + rng.uniform(-off, off, n))[:, None]


def vector_points(n: int = 6000, seed: int = 0) -> pd.DataFrame:
    """Vectors of random length and sign with a normal component added."""
    rng = np.random.default_rng([seed, 1])  # another stream than the positions
    p = scattered(n, seed)
    normal = p / np.linalg.norm(p, axis=1, keepdims=True)
    v = (azimuthal(p) + rng.uniform(-0.8, 0.8, (n, 1)) * normal) * rng.choice([-3.0, 0.5, 2.0], (n, 1))
    return pd.DataFrame({"x": p[:, 0], "y": p[:, 1], "z": p[:, 2], "nx": v[:, 0], "ny": v[:, 1], "nz": v[:, 2]})


def angle_points(basis: str, unit: str, axis=(1.0, 0.5, 0.2), n: int = 6000, seed: int = 1) -> pd.DataFrame:
    """The azimuthal field as angles from e1 towards N × e1 at each point (its own normal)."""
    rng = np.random.default_rng([seed, 1])  # another stream than the positions
    p = scattered(n, seed)
    normal = p / np.linalg.norm(p, axis=1, keepdims=True)
    df = pd.DataFrame({"x": p[:, 0], "y": p[:, 1], "z": p[:, 2]})
    if basis == "axis":
        ref = np.broadcast_to(np.asarray(axis, float), p.shape)
    elif basis == "local":  # any tangent reference, with a normal component the import removes
        ref = rng.normal(size=(n, 3))
        ref -= np.einsum("ij,ij->i", ref, normal)[:, None] * normal
        ref = ref / np.linalg.norm(ref, axis=1, keepdims=True) + 0.5 * normal
        df[["e1x", "e1y", "e1z"]] = ref
    else:
        ref = axis_frames(normal)[0]
    e1 = ref - np.einsum("ij,ij->i", ref, normal)[:, None] * normal
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(normal, e1)
    d = azimuthal(p)
    theta = np.arctan2(np.einsum("ij,ij->i", d, e2), np.einsum("ij,ij->i", d, e1))
    theta += np.pi * rng.integers(-2, 3, n)  # θ + k·180°: the same director
    df["angle"] = np.degrees(theta) if unit == "degrees" else theta
    return df


def assert_analytic(sphere, df: pd.DataFrame, min_cos: float = 0.999, frames_switch: bool = False) -> None:
    """The imported directors equal the azimuthal field at their vertices (away from the poles;
    with ``frames_switch``, also away from the line where NEMO's frames switch from N × x̂ to
    N × ŷ: there a point and its vertex may lie on either side, and the frames are discontinuous)."""
    assert list(df.columns) == list(SCHEMAS["directors"])
    v = df["vertex"].to_numpy()
    pos = np.asarray(sphere.vertices)[v]
    np.testing.assert_allclose(df[["x", "y", "z"]].to_numpy(), pos)
    n = df[["nx", "ny", "nz"]].to_numpy()
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-9)
    assert np.abs(np.einsum("ij,ij->i", n, vertex_normals(sphere)[v])).max() < 1e-9  # tangent
    band = np.abs(pos[:, 2]) < EQUATOR * R
    if frames_switch:
        band &= np.abs(np.hypot(pos[:, 1], pos[:, 2]) / R - 0.3) > 0.03
    assert band.sum() > 1000
    cos = np.abs(np.einsum("ij,ij->i", n[band], azimuthal(pos[band])))
    assert cos.min() > min_cos, cos.min()


# ----------------------------------------------------------------------------- the field
def test_vectors_with_a_normal_component_give_the_analytic_field(sphere):
    points = vector_points()
    before = points.copy()
    df, counts = import_directors(sphere, points)
    pd.testing.assert_frame_equal(points, before)  # the input is not modified
    assert_analytic(sphere, df)
    assert counts["n_points"] == 6000 and counts["n_far"] == 0 and counts["n_shared"] > 100
    assert counts["n_nearly_normal"] == 0 and counts["n_directors"] == len(df)
    assert counts["max_distance"] == pytest.approx(2 * mean_edge_length(sphere))
    assert df["vertex"].is_unique and df["vertex"].is_monotonic_increasing
    # coherency = the agreement of the points on a vertex: 1 for one point, near 1 where the
    # field turns slowly, lower near the poles where neighbouring points differ
    coh = df["coherency"].to_numpy()
    assert ((coh >= 0) & (coh <= 1 + 1e-12)).all()
    band = np.abs(df["z"].to_numpy()) < EQUATOR * R
    assert coh[band].min() > 0.99 and coh.min() < 0.9


@pytest.mark.parametrize("basis, unit", [("axis", "degrees"), ("axis", "radians"), ("local", "degrees"),
                                         ("frames", "radians")])
def test_angles_in_a_tangent_basis_give_the_analytic_field(sphere, basis, unit):
    points = angle_points(basis, unit)
    axis = (1.0, 0.5, 0.2) if basis == "axis" else None
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        df, counts = import_directors(sphere, points, basis=basis, axis=axis, angle_unit=unit)
    assert_analytic(sphere, df, frames_switch=basis == "frames")
    if basis == "axis":  # dropped: the points whose normal is within 17.5° of ±axis
        u = points[["x", "y", "z"]].to_numpy()
        near = np.abs(u @ np.array(axis) / np.linalg.norm(u, axis=1) / np.linalg.norm(axis)) > np.cos(np.radians(16))
        assert near.sum() <= counts["n_nearly_normal"] <= 1.2 * near.sum()
        expected = (f"{counts['n_nearly_normal']} of 6000 points of the points have a reference direction e1 "
                    "nearly normal to the surface (tangential part < 0.3 of it): dropped")
        assert [str(w.message) for w in caught] == [expected]
    else:
        assert counts["n_nearly_normal"] == 0 and not caught  # no unit warning either


@pytest.mark.filterwarnings("ignore:.*nearly normal to the surface:nemo.errors.NemoWarning")
def test_the_wrong_basis_or_sense_does_not_pass(sphere):
    """The comparison can fail: another axis, or angles measured clockwise, give another field."""
    points = angle_points("axis", "degrees")
    wrong_axis, _ = import_directors(sphere, points, basis="axis", axis=(0, 1, 0), angle_unit="degrees")
    with pytest.raises(AssertionError):
        assert_analytic(sphere, wrong_axis)
    clockwise, _ = import_directors(sphere, points.assign(angle=-points["angle"]), basis="axis",
                                    axis=(1.0, 0.5, 0.2), angle_unit="degrees")
    with pytest.raises(AssertionError):
        assert_analytic(sphere, clockwise)


def test_an_axis_along_the_normal_is_dropped_with_a_count(sphere):
    points = angle_points("axis", "degrees", axis=(0, 0, 1))
    with pytest.warns(NemoWarning, match=r"\d+ of 6000 points .* nearly normal to the surface"):
        df, counts = import_directors(sphere, points, basis="axis", axis=(0, 0, 1), angle_unit="degrees")
    polar = np.abs(points["z"].to_numpy()) / np.linalg.norm(points[["x", "y", "z"]].to_numpy(), axis=1)
    assert 0 < counts["n_nearly_normal"] <= (polar > 0.9).sum()  # ẑ is within 17.5° of the normal
    assert_analytic(sphere, df)


def test_angles_in_degrees_given_as_radians_warn(sphere):
    points = angle_points("frames", "degrees")
    with pytest.warns(NemoWarning, match="if they are degrees"):
        import_directors(sphere, points, basis="frames", angle_unit="radians")


# ----------------------------------------------------------------------------- several points per vertex
def _on_vertex(sphere, vertex: int, angles_deg, weights=None, coherency=None) -> pd.DataFrame:
    """Points a little off one vertex with the given angles in NEMO's frame there."""
    t1, t2 = axis_frames(vertex_normals(sphere)[[vertex]])
    th = np.radians(np.asarray(angles_deg, float))
    d = np.cos(th)[:, None] * t1 + np.sin(th)[:, None] * t2
    p = np.asarray(sphere.vertices)[vertex] + 0.05 * mean_edge_length(sphere) * t2 + 0.1 * t1
    df = pd.DataFrame({"x": p[0, 0], "y": p[0, 1], "z": p[0, 2], "nx": d[:, 0], "ny": d[:, 1], "nz": d[:, 2]})
    if weights is not None:
        df["weight"] = weights
    if coherency is not None:
        df["coherency"] = coherency
    return df


def _angle_at(sphere, df: pd.DataFrame) -> float:
    t1, t2 = axis_frames(vertex_normals(sphere)[df["vertex"].to_numpy()])
    n = df[["nx", "ny", "nz"]].to_numpy()
    return float(np.degrees(np.arctan2(n @ t2[0], n @ t1[0])).item() % 180)


@pytest.mark.parametrize("theta", [0.0, 30.0, 75.0, 140.0])
def test_opposite_vectors_on_one_vertex_average_as_a_nematic(sphere, theta):
    df, counts = import_directors(sphere, _on_vertex(sphere, 100, [theta, theta + 180.0]))
    assert len(df) == 1 and df["vertex"].item() == 100 and counts["n_shared"] == 1
    off = (_angle_at(sphere, df) - theta + 90.0) % 180.0 - 90.0  # nematic: 180° − ε is θ = 0
    assert off == pytest.approx(0.0, abs=1e-6)  # θ, not θ + 90° nor undefined
    assert df["coherency"].item() == pytest.approx(1.0)


def test_weights_and_coherency_on_one_vertex(sphere):
    df, _ = import_directors(sphere, _on_vertex(sphere, 7, [10.0, 100.0], weights=[3.0, 1.0]))
    assert _angle_at(sphere, df) == pytest.approx(10.0, abs=1e-6)
    assert df["coherency"].item() == pytest.approx(0.5)  # agreement S = (3 − 1) / 4
    df, _ = import_directors(sphere, _on_vertex(sphere, 7, [10.0, 100.0], coherency=[0.2, 0.6]))
    assert _angle_at(sphere, df) == pytest.approx(100.0, abs=1e-6)  # weight = coherency by default
    assert df["coherency"].item() == pytest.approx((0.2**2 + 0.6**2) / 0.8 * (0.4 / 0.8))


def test_nematic_mean_of_many_vertices_at_once():
    normals = np.tile([0.0, 0.0, 1.0], (4, 1))
    t1, t2 = axis_frames(normals[:1])
    th = np.radians([20.0, 200.0, 20.0, 110.0, 60.0])
    d = np.cos(th)[:, None] * t1 + np.sin(th)[:, None] * t2
    vertices, mean, agreement, count = nematic_mean(np.array([3, 3, 1, 1, 0]), d, np.array([1, 1, 1, 1, 0.0]),
                                                    normals)
    assert vertices.tolist() == [1, 3]  # vertex 0 has weight 0
    assert count.tolist() == [2, 2]
    np.testing.assert_allclose(agreement, [0.0, 1.0], atol=1e-12)  # 20° and 110°: no order
    assert abs(mean[1] @ d[0]) == pytest.approx(1.0)


# ----------------------------------------------------------------------------- distances and units
def test_far_points_are_refused_with_a_count(sphere):
    points = vector_points()
    far = points.iloc[:300].copy()
    far[["x", "y", "z"]] *= 1.3  # 15 µm outside
    mixed = pd.concat([points.iloc[300:], far], ignore_index=True)
    with pytest.warns(NemoWarning, match=r"300 of 6000 points .* farther than `max_distance` 7\.\d+ "):
        df, counts = import_directors(sphere, mixed)
    assert counts["n_far"] == 300
    assert_analytic(sphere, df)
    _, kept = import_directors(sphere, mixed, max_distance=20.0)  # a larger distance keeps them
    assert kept["n_far"] == 0


def test_points_just_off_the_surface_are_kept(sphere):
    """The distance is to the surface, not to the nearest vertex: a point mid-face 1.5 edges
    off the surface is more than 2 edges from every vertex but within 2 edges of the surface."""
    edge = mean_edge_length(sphere)
    face = np.asarray(sphere.triangles_center)[:500]
    p = face * (1 + 1.7 * edge / R)
    points = pd.DataFrame({"x": p[:, 0], "y": p[:, 1], "z": p[:, 2], "nx": 1.0, "ny": 0.5, "nz": 0.0})
    _, counts = import_directors(sphere, points, max_distance=2 * edge)
    assert counts["n_far"] == 0
    with pytest.raises(NemoError, match="500 of 500 points"):  # 1.7 edges off the faces
        import_directors(sphere, points, max_distance=1.5 * edge)


def test_points_in_another_unit_are_an_error(sphere):
    points = vector_points()
    points[["x", "y", "z"]] *= 1000  # mm read as µm, say
    with pytest.raises(NemoError, match=r"6000 of 6000 points .* another unit\?.* x = column, y = row"):
        import_directors(sphere, points)


# ----------------------------------------------------------------------------- clear errors
BAD = {
    "no position": (lambda d: d.drop(columns="z"), {}, r"lacks the position column\(s\) z"),
    "no director": (lambda d: d.drop(columns=["nx", "ny", "nz"]), {}, r"no director column .* nx, ny, nz"),
    "half a vector": (lambda d: d.drop(columns="nz"), {}, r"lacks nz"),
    "vector and angle": (lambda d: d.assign(angle=0.0), {}, r"both a vector .* and an angle"),
    "basis with vectors": (lambda d: d, {"basis": "axis"}, r"`basis`, `axis` and `angle_unit` apply to an angle"),
    "angle without basis": (lambda d: _angles(d), {"angle_unit": "degrees"}, r"state their tangent basis with `basis`"),
    "bad basis": (lambda d: _angles(d), {"basis": "polar", "angle_unit": "degrees"}, r"unknown `basis` 'polar'"),
    "angle without unit": (lambda d: _angles(d), {"basis": "frames"}, r"state their unit with `angle_unit`"),
    "axis missing": (lambda d: _angles(d), {"basis": "axis", "angle_unit": "degrees"}, r"give `axis`"),
    "zero axis": (lambda d: _angles(d), {"basis": "axis", "axis": (0, 0, 0), "angle_unit": "degrees"},
                  r"not all 0"),
    "axis without basis axis": (lambda d: _angles(d), {"basis": "frames", "axis": (1, 0, 0), "angle_unit": "degrees"},
                                r"`axis` is only used with `basis` axis"),
    "local without e1": (lambda d: _angles(d), {"basis": "local", "angle_unit": "degrees"}, r"lacks e1x, e1y, e1z"),
    "NaN rows": (lambda d: d.assign(x=np.where(d.index.isin([4, 9]), np.nan, d["x"])), {},
                 r"2 of 6000 rows have missing \(NaN\) or infinite values in x, y, z \(rows 4, 9"),
    "NaN angle": (lambda d: _angles(d).assign(angle=np.nan), {"basis": "frames", "angle_unit": "degrees"},
                  r"6000 of 6000 rows .* in angle"),
    "text column": (lambda d: d.assign(ny="a"), {}, r"column\(s\) ny are not numbers"),
    "zero vector": (lambda d: d.assign(nx=0.0, ny=0.0, nz=0.0), {}, r"6000 row\(s\) have the zero vector"),
    "negative weight": (lambda d: d.assign(weight=-1.0), {}, r"6000 negative weight"),
    "coherency > 1": (lambda d: d.assign(coherency=2.0), {}, r"coherency must lie in \[0, 1\]"),
    "all weight 0": (lambda d: d.assign(weight=0.0), {}, r"no director .* is left .* 6000 of weight 0"),
}


def _angles(d: pd.DataFrame) -> pd.DataFrame:
    return d.drop(columns=["nx", "ny", "nz"]).assign(angle=30.0)


@pytest.mark.parametrize("name", list(BAD))
def test_bad_points_and_options_are_clear_errors(sphere, name):
    edit, options, message = BAD[name]
    with pytest.raises(NemoError, match=message):
        import_directors(sphere, edit(vector_points()), source="p.csv", **options)


# ----------------------------------------------------------------------------- files
def test_csv_parquet_npy_npz_read_the_same(tmp_path, sphere):
    points = vector_points(500)
    points.rename(columns={"x": "X", "nz": " NZ"}).to_csv(tmp_path / "p.csv", index=False)
    points.to_parquet(tmp_path / "p.parquet")
    np.save(tmp_path / "p.npy", points.to_records(index=False))
    np.savez(tmp_path / "p.npz", **{c: points[c].to_numpy() for c in points.columns})
    for name in ("p.csv", "p.parquet", "p.npy", "p.npz"):
        read = read_points(tmp_path / name)
        pd.testing.assert_frame_equal(read, points, check_exact=False, rtol=1e-12, obj=name)


@pytest.mark.parametrize("name, write, message", [
    ("p.npy", lambda p: np.save(p, np.zeros((5, 6))), r"plain array of shape \(5, 6\)"),
    ("p.npz", lambda p: np.savez(p, x=np.zeros(3), y=np.zeros(4)), r"one 1-D array per column"),
    ("p.txt", lambda p: p.write_text("x,y"), r"use a \.csv, \.tsv, \.parquet, \.npy, \.npz file"),
    ("p.parquet", lambda p: p.write_text("not parquet"), r"cannot read .* as a parquet table"),
    ("p.csv", lambda p: p.write_text("x,y,z,nx,ny,nz\n"), r"has no rows"),
    ("p.csv", lambda p: p.write_text("x,X,y\n1,2,3\n"), r"the column\(s\) x twice"),
    ("missing.csv", lambda p: None, r"director file not found"),
    ("p.csv", lambda p: p.write_text("x;y;z;nx;ny;nz\n1;2;3;4;5;6\n"), r"separate the columns with commas"),
])
def test_unreadable_files_are_clear_errors(tmp_path, name, write, message):
    write(tmp_path / name)
    with pytest.raises(NemoError, match=message):
        read_points(tmp_path / name)


# ----------------------------------------------------------------------------- the command line
@pytest.fixture(scope="module")
def sphere_ply(tmp_path_factory, sphere):
    path = tmp_path_factory.mktemp("mesh") / "sphere.ply"
    save_mesh(sphere, path)
    return path


def _defects_after_import(run_cli, tmp_path, sphere_ply, points_file, *options):
    code, out, err = run_cli("directors", "import", sphere_ply, points_file, "-o", tmp_path / "d.parquet", *options)
    assert code == 0, err
    code, _, err = run_cli("order", sphere_ply, tmp_path / "d.parquet", "-o", tmp_path / "o.parquet")
    assert code == 0, err
    code, _, err = run_cli("defects", sphere_ply, tmp_path / "o.parquet", tmp_path / "d.parquet",
                           "-o", tmp_path / "f.parquet")
    assert code == 0, err
    return out, read_table(tmp_path / "f.parquet", kind="defects")


def test_cli_import_then_order_and_defects_find_the_two_poles(run_cli, tmp_path, sphere_ply, sphere):
    vector_points().to_csv(tmp_path / "p.csv", index=False)
    before = (tmp_path / "p.csv").read_bytes()
    out, defects = _defects_after_import(run_cli, tmp_path, sphere_ply, tmp_path / "p.csv")
    assert "6000 points ->" in out and "vertices averaged several points" in out
    assert (tmp_path / "p.csv").read_bytes() == before
    prov = read_provenance(tmp_path / "d.parquet")
    assert prov["command"] == "directors import" and prov["mesh"] == str(sphere_ply)
    assert prov["n_vertices"] == len(sphere.vertices) and prov["unit"] == "um"
    params = prov["parameters"]
    assert params["n_points"] == 6000 and params["max_distance"] == pytest.approx(2 * mean_edge_length(sphere))
    # nemo order's default radius follows the imported density: the disc of about 10 directors
    nominal = np.sqrt(10 / np.pi) * np.sqrt(sphere.area / params["n_directors"]) / 2.5
    assert params["nominal_radius"] == pytest.approx(nominal)
    assert read_provenance(tmp_path / "o.parquet")["radius"] == pytest.approx(2.5 * nominal)
    assert len(defects) == 2, defects
    assert sorted(np.sign(defects["z"])) == [-1, 1] and (np.abs(defects["z"]) > 0.97 * R).all()
    np.testing.assert_allclose(defects["charge"], 1.0, atol=0.05)


def test_cli_four_half_defects_from_angles(run_cli, tmp_path, sphere_ply):
    from nemo.synthetic import director_field, preset_defects

    dirs, charges = preset_defects("tetrahedron")
    p = scattered(8000, seed=3)
    normal = p / np.linalg.norm(p, axis=1, keepdims=True)
    n = director_field(p, dirs, charges)
    t1, t2 = axis_frames(normal)  # NEMO's frames at each point: --basis frames
    theta = np.degrees(np.arctan2(np.einsum("ij,ij->i", n, t2), np.einsum("ij,ij->i", n, t1)))
    pd.DataFrame({"x": p[:, 0], "y": p[:, 1], "z": p[:, 2], "angle": theta}).to_parquet(tmp_path / "p.parquet")
    _, defects = _defects_after_import(run_cli, tmp_path, sphere_ply, tmp_path / "p.parquet",
                                       "--basis", "frames", "--angle-unit", "degrees")
    assert len(defects) == 4, defects
    np.testing.assert_allclose(defects["charge"], 0.5, atol=0.05)
    found = defects[["x", "y", "z"]].to_numpy() / R
    assert (np.degrees(np.arccos(np.clip(found @ dirs.T, -1, 1))).min(axis=0) < 8).all()  # each truth found


def test_cli_errors_name_the_flags(run_cli, capsys, tmp_path, sphere_ply):
    _angles(vector_points(200)).to_csv(tmp_path / "a.csv", index=False)
    code, _, err = run_cli("directors", "import", sphere_ply, tmp_path / "a.csv", "-o", tmp_path / "d.parquet")
    assert code == 2 and "nemo directors import: error:" in err and "with --basis" in err, err
    code, _, err = run_cli("directors", "import", sphere_ply, tmp_path / "a.csv", "-o", tmp_path / "d.parquet",
                           "--basis", "axis", "--angle-unit", "degrees")
    assert code == 2 and "give --axis as three numbers" in err, err
    points = vector_points(200)
    points[["x", "y", "z"]] *= 1000
    points.to_csv(tmp_path / "far.csv", index=False)
    code, _, err = run_cli("directors", "import", sphere_ply, tmp_path / "far.csv", "-o", tmp_path / "d.parquet")
    assert code == 2 and "farther than --max-distance" in err and "another unit" in err, err
    assert not (tmp_path / "d.parquet").exists()
    code, _, err = run_cli("directors", "import", sphere_ply, tmp_path / "far.csv", "-o", tmp_path / "far.csv")
    assert code == 2 and "would destroy the input" in err
    with pytest.raises(SystemExit):  # argparse: usage and the message
        run_cli("directors", "import", sphere_ply, tmp_path / "a.csv", "-o", tmp_path / "d.parquet",
                "--min-tangential", "2")
    err = capsys.readouterr().err
    assert "usage: nemo directors import" in err and "--min-tangential: must be in (0, 1], got 2" in err


def test_help_documents_both_forms_and_the_measure_form_still_runs(run_cli, capsys, tmp_path, sphere_ply, sphere):
    with pytest.raises(SystemExit):
        run_cli("directors", "--help")
    text = capsys.readouterr().out
    assert "nemo directors MESH LAYER" in text and "nemo directors import MESH POINTS" in text
    assert "--patch-radius" in text and "--basis {" not in text
    with pytest.raises(SystemExit):
        run_cli("directors", "import", "--help")
    text = capsys.readouterr().out
    assert text.startswith("usage: nemo directors import") and "--basis {" in text and "--patch-radius" not in text
    assert "counter-clockwise seen from outside" in text
    layer = pd.DataFrame({"vertex": np.arange(len(sphere.vertices)),
                          "intensity": np.sin(np.asarray(sphere.vertices)[:, 0] / 3.0)})
    layer.to_parquet(tmp_path / "layer.parquet")
    code, _, err = run_cli("directors", sphere_ply, tmp_path / "layer.parquet", "-o", tmp_path / "m.parquet",
                             "--n-patches", "50")
    assert code == 0, err
    assert read_provenance(tmp_path / "m.parquet")["command"] == "directors"


def test_every_import_option_is_a_flag_and_a_config_key():
    """The workflow passes layers.NAME.import as --key value: every key is a flag of the command."""
    from nemo.cli import build_parser

    sub = build_parser("directors")._subparsers._group_actions[0].choices["directors"]
    args = sub.parse_known_args(["import", "m.ply", "p.csv", "-o", "d.parquet"])[0]
    keys = set(config.section_defaults("directors_import"))
    assert keys == {"basis", "axis", "angle_unit", "max_distance", "min_tangential"}
    assert keys <= set(vars(args)) and args._command == "directors import"


# ----------------------------------------------------------------------------- the config
@pytest.mark.parametrize("layer, key, message", [
    ({"directors_from": "d/t{t}.csv", "range": [0, 5]}, "layers.f.range", "remove range"),
    ({"directors_from": "d/t{t}.csv", "shift": 0.5}, "layers.f.shift", "remove shift"),
    ({"directors_from": "d/t{time}.csv"}, "layers.f.directors_from", "unknown placeholder"),
    ({"directors_from": "d/t{t}.csv", "import": {"basis": "axis", "angle_unit": "degrees"}},
     "layers.f.import.axis", "give axis"),
    ({"directors_from": "d/t{t}.csv", "import": {"basis": "local"}}, "layers.f.import.angle_unit", "unit"),
    ({"directors_from": "d/t{t}.csv", "import": {"basis": "polar"}}, "layers.f.import.basis", "is not one of"),
    ({"surface": "inner"}, "layers.f", "'range' is a required property"),
])
def test_config_directors_from_is_checked(layer, key, message):
    with pytest.raises(NemoError, match=message) as exc:
        config.analysis(config.validate({"layers": {"f": layer}}))
    assert f"'{key}" in str(exc.value)


def test_config_directors_from_needs_no_range():
    a = config.analysis(config.validate({"layers": {"f": {"directors_from": "d/{dataset}_t{t:03d}_c{c}.csv"},
                                                    "g": {"range": [0, 5]}}}))
    assert set(config.imported_layers(a)) == {"f"} and a["layers"]["f"]["surface"] == "inner"
    assert config.directors_from_path(a["layers"]["f"]["directors_from"], dataset="demo", t=7, c=1,
                                      layer="f") == "d/demo_t007_c1.csv"


def test_summary_of_an_imported_layer_has_no_intensity(tmp_path):
    """frames.parquet: a layer without a peeled intensity table still gets its director columns."""
    import json

    from nemo.summary import frame_summary
    from nemo.tables import write_table

    (tmp_path / "m.json").write_text(json.dumps({"area": 1.0}))
    write_table(vector_points(10).assign(vertex=np.arange(10), coherency=0.5), tmp_path / "d.parquet")
    write_table(pd.DataFrame({"vertex": [0], "S": [0.8], "nx": [1.0], "ny": [0.0], "nz": [0.0]}), tmp_path / "o.parquet")
    write_table(pd.DataFrame({c: [] for c in SCHEMAS["defects"]}), tmp_path / "f.parquet")
    f = frame_summary([{"t": 0, "c": 0, "layer": "ext", "surface": "inner", "measure": tmp_path / "m.json",
                        "directors": tmp_path / "d.parquet", "order": tmp_path / "o.parquet",
                        "defects": tmp_path / "f.parquet"}])
    assert np.isnan(f["intensity_mean"].item()) and f["n_directors"].item() == 10
    assert f["S_mean"].item() == pytest.approx(0.8) and f["n_defects"].item() == 0


def test_peeling_a_layer_with_directors_from_is_refused():
    """Peeling goes through section('layer'): an imported layer is refused there."""
    with pytest.raises(NemoError, match="is not peeled: its directors are imported"):
        config.section("layer", {"directors_from": "d/t{t}.csv"})
    assert config.section("layer", {"range": [0, 5]})["range"] == [0, 5]


@pytest.mark.parametrize("spacing", [6.0, 10.0])
def test_a_sparse_import_finds_its_defects_with_every_default(spacing):
    """One director per 6 or 10 µm vertex (the five +1/2, one -1/2 set), imported and analysed
    with no length given: the default averaging disc holds about 10 directors."""
    import sparse_fields as sf

    from nemo import stages
    from nemo.synthetic import director_field, preset_defects, projection_pole

    dirs, charges = preset_defects("five-one")
    mesh = sf.fibonacci_sphere(50.0, spacing)
    n = director_field(np.asarray(mesh.vertices), dirs, charges, pole=projection_pole(dirs))
    v = np.asarray(mesh.vertices)
    points = pd.DataFrame({"x": v[:, 0], "y": v[:, 1], "z": v[:, 2], "nx": n[:, 0], "ny": n[:, 1], "nz": n[:, 2]})
    ddf, dp = stages.import_directors(mesh, points)
    odf, op = stages.order(mesh, ddf, None, patch_radius=dp["nominal_radius"])
    assert op["radius"] == pytest.approx(np.sqrt(10 / np.pi) * sf.mean_spacing(mesh), rel=0.1)
    found, _, _ = stages.defects(mesh, odf, ddf, None, avg_radius=op["radius"])
    sc = sf.score(found, 50.0 * dirs, charges)
    assert sc["found"] == 6 and sc["extras"] == 0 and sc["charge_ok"], (sc, found)
