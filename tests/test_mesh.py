"""The mesh container: PLY/OBJ round trips, foreign, inward-wound and corrupt files, vertex normals
and areas, coincident vertices (nemo.mesh)."""

from __future__ import annotations

import re

import numpy as np
import pytest
import trimesh

from nemo.errors import NemoError, NemoWarning
from nemo.mesh import (
    check_mesh,
    load_mesh,
    make_mesh,
    mean_edge_length,
    merge_coincident_vertices,
    nonmanifold_problem,
    save_mesh,
    signed_volume,
    split_nonmanifold_vertices,
    vertex_areas,
    vertex_normals,
)


def _sphere(radius=50.0, centre=(120.0, 80.0, 60.0), subdivisions=3):
    ico = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(ico.vertices) + np.asarray(centre), np.asarray(ico.faces)


def _sphere_mesh(radius=10.0, subdivisions=3):
    """An icosphere about the origin, as a NEMO mesh."""
    return make_mesh(*_sphere(radius, (0.0, 0.0, 0.0), subdivisions))


def test_make_mesh_orients_inverted_sphere_outward():
    v, f = _sphere()
    mesh = make_mesh(v, f[:, ::-1])  # inward winding given
    assert signed_volume(mesh.vertices, mesh.faces) > 0
    outward = np.einsum("ij,ij->i", mesh.vertex_normals, mesh.vertices - v.mean(axis=0))
    assert (outward > 0).all()
    assert mesh.units == "um"


def test_inward_wound_ply_is_flipped_with_a_warning(tmp_path):
    mesh = _sphere_mesh()
    inward = trimesh.Trimesh(mesh.vertices, mesh.faces[:, ::-1], process=False)
    path = tmp_path / "inward.ply"
    save_mesh(inward, path)
    with pytest.warns(NemoWarning, match="wound inward"):
        back = load_mesh(path)
    assert signed_volume(back.vertices, back.faces) > 0
    centred = back.vertices - back.vertices.mean(axis=0)
    assert np.all(np.einsum("ij,ij->i", vertex_normals(back), centred) > 0)


def test_mixed_winding_is_made_consistent_and_outward_with_a_warning(tmp_path):
    mesh = _sphere_mesh()
    faces = mesh.faces.copy()
    faces[::2] = faces[::2, ::-1]  # half the faces wound inward
    path = tmp_path / "mixed.ply"
    save_mesh(trimesh.Trimesh(mesh.vertices, faces, process=False), path)
    with pytest.warns(NemoWarning, match="wound both ways"):
        back = load_mesh(path)
    centred = back.vertices - back.vertices.mean(axis=0)
    assert back.is_winding_consistent and np.all(np.einsum("ij,ij->i", vertex_normals(back), centred) > 0)


def test_an_open_cap_wound_inward_is_warned_about(tmp_path, recwarn):
    mesh = _sphere_mesh()
    centred = mesh.vertices - mesh.vertices.mean(axis=0)
    cap = mesh.faces[(centred[mesh.faces][:, :, 2] > 0.2 * np.abs(centred[:, 2]).max()).all(axis=1)]
    for name, faces, warned in (("out", cap, False), ("in", cap[:, ::-1], True)):
        save_mesh(trimesh.Trimesh(mesh.vertices, faces, process=False), tmp_path / f"{name}.ply")
        recwarn.clear()
        load_mesh(tmp_path / f"{name}.ply")
        assert any("towards its centre" in str(w.message) for w in recwarn) == warned, name


def test_ply_round_trip_keeps_vertices_faces_units_fields(tmp_path, rng):
    v, f = _sphere()
    h = rng.normal(size=len(v))
    mesh = make_mesh(v, f, unit="nm", fields={"H": h, "thickness": np.full(len(v), np.nan)})
    save_mesh(mesh, tmp_path / "m.ply")
    back = load_mesh(tmp_path / "m.ply")
    np.testing.assert_allclose(back.vertices, v, rtol=1e-6)  # float32 storage
    np.testing.assert_array_equal(back.faces, mesh.faces)
    assert back.units == "nm"
    np.testing.assert_allclose(back.vertex_attributes["H"], h, rtol=1e-6)
    assert np.isnan(back.vertex_attributes["thickness"]).all()
    # orientation survives: same face normals
    np.testing.assert_allclose(back.face_normals, mesh.face_normals, atol=1e-5)
    assert not list(tmp_path.glob(".*tmp*"))  # atomic write left no temporary file


def test_spacing_comment_round_trip(tmp_path):
    mesh = _sphere_mesh()
    mesh.metadata["spacing"] = (2.0, 0.5, 0.25)
    save_mesh(mesh, tmp_path / "m.ply")
    assert load_mesh(tmp_path / "m.ply").metadata["spacing"] == (2.0, 0.5, 0.25)


def test_obj_round_trip(tmp_path):
    v, f = _sphere()
    save_mesh(make_mesh(v, f), tmp_path / "m.obj")
    back = load_mesh(tmp_path / "m.obj")
    np.testing.assert_allclose(back.vertices, v, rtol=1e-6)
    np.testing.assert_array_equal(back.faces, f)
    assert back.units == "um"
    assert load_mesh(tmp_path / "m.obj", unit="mm").units == "mm"


@pytest.mark.parametrize("encoding", ["ascii", "binary"])
def test_foreign_ply_without_nemo_comment(tmp_path, encoding):
    """A PLY written by another program (trimesh itself, as MeshLab would) reads back, unit µm."""
    v, f = _sphere(radius=20.0)
    (tmp_path / "ext.ply").write_bytes(trimesh.Trimesh(v, f, process=False).export(file_type="ply", encoding=encoding))
    back = load_mesh(tmp_path / "ext.ply")
    np.testing.assert_allclose(back.vertices, v, rtol=1e-6)
    np.testing.assert_array_equal(back.faces, f)
    assert back.units == "um"
    assert dict(back.vertex_attributes) == {}


def _meshlab_ply(tmp_path):
    """MeshLab-style ASCII PLY with per-vertex normals, colours and a 'quality' field."""
    v, f = _sphere(radius=10.0, subdivisions=1)
    n = v - v.mean(axis=0)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    lines = ["ply", "format ascii 1.0", "comment VCGLIB generated", f"element vertex {len(v)}",
             "property float x", "property float y", "property float z",
             "property float nx", "property float ny", "property float nz",
             "property uchar red", "property uchar green", "property uchar blue", "property float quality",
             f"element face {len(f)}", "property list uchar int vertex_indices", "end_header"]
    lines += [" ".join(f"{x:.6f}" for x in (*p, *q)) + f" 10 20 30 {i:.1f}" for i, (p, q) in enumerate(zip(v, n))]
    lines += [f"3 {a} {b} {c}" for a, b, c in f]
    (tmp_path / "meshlab.ply").write_text("\n".join(lines) + "\n")
    return tmp_path / "meshlab.ply", v, f


def test_foreign_ply_with_normals_and_colours(tmp_path):
    """Normals and colours are not mistaken for fields."""
    path, v, f = _meshlab_ply(tmp_path)
    back = load_mesh(path)
    np.testing.assert_allclose(back.vertices, v, atol=1e-6)
    np.testing.assert_array_equal(back.faces, f)
    assert not {"nx", "ny", "nz", "red", "green", "blue"} & set(back.vertex_attributes)


def test_foreign_ascii_ply_keeps_extra_vertex_fields(tmp_path):
    path, v, _ = _meshlab_ply(tmp_path)
    back = load_mesh(path)
    assert set(back.vertex_attributes) == {"quality"}
    np.testing.assert_allclose(back.vertex_attributes["quality"], np.arange(len(v)))


def test_foreign_obj(tmp_path):
    text = "# cube corner\nv 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"
    (tmp_path / "tet.obj").write_text(text)
    back = load_mesh(tmp_path / "tet.obj")
    assert back.vertices.shape == (4, 3) and back.faces.shape == (4, 3)
    assert abs(signed_volume(back.vertices, back.faces)) == pytest.approx(1 / 6)


def test_corrupt_and_wrong_files(tmp_path):
    v, f = _sphere()
    save_mesh(make_mesh(v, f), tmp_path / "good.ply")
    raw = (tmp_path / "good.ply").read_bytes()
    (tmp_path / "truncated.ply").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(NemoError, match="corrupt|truncated"):
        load_mesh(tmp_path / "truncated.ply")
    (tmp_path / "noheader.ply").write_bytes(b"hello world\n" + raw[100:])
    with pytest.raises(NemoError, match="not a PLY"):
        load_mesh(tmp_path / "noheader.ply")
    (tmp_path / "garbage.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 99999999\n"
                                           b"property float x\nend_header\n\x00\x01")
    with pytest.raises(NemoError):
        load_mesh(tmp_path / "garbage.ply")
    points = ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
              "end_header\n0 0 0\n1 0 0\n0 1 0\n")
    (tmp_path / "cloud.ply").write_text(points)
    with pytest.raises(NemoError, match="no triangles"):
        load_mesh(tmp_path / "cloud.ply")
    with pytest.raises(NemoError, match="not found"):
        load_mesh(tmp_path / "missing.ply")
    (tmp_path / "m.stl").write_text("solid x\nendsolid x\n")
    with pytest.raises(NemoError, match="no triangles"):
        load_mesh(tmp_path / "m.stl")
    (tmp_path / "m.off").write_text("OFF\n")
    with pytest.raises(NemoError, match=r"\.ply, \.obj and \.stl"):
        load_mesh(tmp_path / "m.off")
    with pytest.raises(NemoError, match=r"\.ply or \.obj"):
        save_mesh(make_mesh(v, f), tmp_path / "m.stl")


def test_check_mesh_rejects_nan_and_bad_indices():
    v, f = _sphere(subdivisions=1)
    bad = trimesh.Trimesh(np.where(np.arange(len(v))[:, None] == 3, np.nan, v), f, process=False)
    with pytest.raises(NemoError, match="NaN"):
        check_mesh(bad)
    with pytest.raises(NemoError, match="only"):
        check_mesh(trimesh.Trimesh(v[:3], f[:1], process=False))


def test_mean_edge_length_of_a_regular_mesh():
    # a flat grid of unit squares split into triangles: edges 1 (x2 per cell) and sqrt(2) (x1)
    n = 30
    x, y = np.meshgrid(np.arange(n + 1.0), np.arange(n + 1.0))
    verts = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = np.concatenate([np.column_stack([a, b, d]), np.column_stack([a, d, c])])
    mesh = make_mesh(verts, faces, orient_outward=False)
    n_unit = 2 * n * (n + 1)
    expected = (n_unit + n * n * np.sqrt(2)) / (n_unit + n * n)
    assert mean_edge_length(mesh) == pytest.approx(expected)


def test_vertex_areas_sum_to_area_and_sphere_is_close_to_analytic():
    mesh = _sphere_mesh(radius=7.0, subdivisions=5)
    areas = vertex_areas(mesh)
    assert areas.shape == (len(mesh.vertices),)
    assert np.isclose(areas.sum(), mesh.area)
    assert abs(areas.sum() / (4 * np.pi * 49) - 1) < 2e-3


def test_coincident_vertices_merged_and_degenerate_normals_taken_from_twin():
    mesh = _sphere_mesh()
    v = np.vstack([mesh.vertices, mesh.vertices[:1]])  # a duplicate of vertex 0
    f = np.vstack([mesh.faces, [[0, len(v) - 1, 1]]])  # a zero-area face on it
    dup = trimesh.Trimesh(v, f, process=False)
    n = vertex_normals(dup)
    assert np.allclose(n[-1], n[0])
    mv, mf, index = merge_coincident_vertices(v, f)
    assert len(mv) == len(mesh.vertices) and len(mf) == len(mesh.faces)
    assert index[-1] == index[0]


def test_split_inner_surface_survives_a_ply_round_trip(tmp_path):
    """The inner wall from a shell keeps outward (away from centre) normals on disk."""
    from nemo.surface import reconstruct, split_mesh

    z, y, x = np.ogrid[:40, :40, :40]
    r = np.sqrt((x - 20.0) ** 2 + (y - 19.5) ** 2 + (z - 20.5) ** 2)
    vol = ((r > 10) & (r < 15)).astype(np.float32) * 100
    inner, _ = split_mesh(reconstruct(vol, (1, 1, 1), sigma=1.0, step=2, keep="all"), keep="largest")
    save_mesh(inner, tmp_path / "inner.ply")
    back = load_mesh(tmp_path / "inner.ply")
    outward = np.einsum("ij,ij->i", back.vertex_normals, back.vertices - [20.0, 19.5, 20.5])
    assert (outward > 0).all()
    assert signed_volume(back.vertices, back.faces) > 0


# --------------------------------------------------------------------------- non-manifold meshes
def _bowtie():
    """Two unit icospheres touching at one point that is a single shared vertex."""
    v, f = _sphere(radius=1.0, centre=(0.0, 0.0, 0.0), subdivisions=2)
    j = int(np.argmin(np.linalg.norm(v + v[0], axis=1)))  # the antipode of vertex 0
    assert np.allclose(v[j], -v[0])
    v2 = v + 2 * v[0]  # second sphere: its vertex j lands on vertex 0 of the first
    keep = np.arange(len(v)) != j
    remap = np.full(len(v), -1)
    remap[keep] = len(v) + np.arange(keep.sum())
    remap[j] = 0
    return np.vstack([v, v2[keep]]), np.vstack([f, remap[f]])


def _duplicated_face():
    v, f = _sphere(subdivisions=2)
    return v, np.vstack([f, f[7:8]])


def _book():
    """Three triangles on one edge (0, 1): the spine of a three-page book."""
    v = np.array([[0, 0, 0], [10, 0, 0], [5, 8, 0], [5, -4, 7], [5, -4, -7]], dtype=float)
    return v, np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])


_NONMANIFOLD = {
    "bowtie": (_bowtie, r"not a manifold surface: 1 vertex is shared by separate fans of faces .*vertex 0 joins 2 fans"),
    "duplicate": (_duplicated_face, r"not a manifold surface: 1 face duplicates another face .*faces 7 and 320"),
    "book": (_book, r"not a manifold surface: 1 edge is shared by more than two faces .*vertices 0 and 1 is in 3 faces"),
}


def _write_ply(path, v, f):
    path.write_bytes(trimesh.Trimesh(v, f, process=False).export(file_type="ply", encoding="binary"))
    return path


@pytest.mark.parametrize("kind", sorted(_NONMANIFOLD))
def test_load_mesh_rejects_nonmanifold_meshes(tmp_path, kind):
    build, wording = _NONMANIFOLD[kind]
    ply = _write_ply(tmp_path / f"{kind}.ply", *build())
    with pytest.raises(NemoError, match=wording) as err:
        load_mesh(ply)
    message = str(err.value)
    assert str(ply) in message and "\n" not in message  # names the file, one paragraph
    assert "MeshLab" in message and "Repair non Manifold Edges" in message  # and the fix
    assert "silently wrong" in message


@pytest.mark.parametrize("kind", sorted(_NONMANIFOLD))
def test_cli_curvature_rejects_nonmanifold_mesh(tmp_path, capsys, kind):
    from nemo.cli import main

    build, wording = _NONMANIFOLD[kind]
    ply = _write_ply(tmp_path / f"{kind}.ply", *build())
    before = ply.read_bytes()
    code = main(["curvature", str(ply), "-o", str(tmp_path / "c.parquet")])
    err = capsys.readouterr().err
    assert code == 2
    assert "nemo curvature: error:" in err and re.search(wording, err)
    assert "Traceback" not in err
    assert ply.read_bytes() == before
    assert not (tmp_path / "c.parquet").exists()


def test_check_mesh_rejects_faces_with_a_repeated_vertex():
    v, f = _sphere(subdivisions=1)
    f = np.vstack([f, [[3, 5, 3]]])
    with pytest.raises(NemoError, match=r"1 face repeats a vertex index \(e\.g\. face 80: vertices 3, 5, 3\)"):
        check_mesh(trimesh.Trimesh(v, f, process=False), "m.ply")


def test_manifold_meshes_still_load(tmp_path):
    """Closed spheres, an open hemisphere (a boundary), an annulus and separate closed
    components are all manifold."""
    v, f = _sphere(subdivisions=3)
    hemi = f[(v[f].mean(axis=1)[:, 2] > 60.0)]
    used = np.unique(hemi)
    remap = np.full(len(v), -1)
    remap[used] = np.arange(len(used))
    ann = trimesh.creation.annulus(r_min=5.0, r_max=8.0, height=2.0)
    cases = {
        "sphere": (v, f),
        "hemisphere": (v[used], remap[hemi]),
        "two_spheres": (np.vstack([v, v + 200.0]), np.vstack([f, f + len(v)])),
        "annulus": (np.asarray(ann.vertices), np.asarray(ann.faces)),
    }
    for name, (vv, ff) in cases.items():
        assert nonmanifold_problem(ff, len(vv)) is None, name
        back = load_mesh(_write_ply(tmp_path / f"{name}.ply", vv, ff))
        assert len(back.faces) == len(ff), name
    assert not load_mesh(tmp_path / "hemisphere.ply").is_watertight


def test_nonmanifold_check_accepts_inconsistent_winding_and_flags_open_bowtie():
    v, f = _sphere(subdivisions=2)
    f = f.copy()
    f[::5] = f[::5, ::-1]  # winding is a separate matter: still a manifold
    assert nonmanifold_problem(f, len(v)) is None
    # two open fans (triangles) meeting at vertex 0
    assert "vertex 0 joins 2 fans" in nonmanifold_problem(np.array([[0, 1, 2], [0, 3, 4]]), 5)


def test_split_nonmanifold_vertices_repairs_bowtie_and_touching_sheets():
    v, f = _bowtie()
    v2, f2, index = split_nonmanifold_vertices(v, f, return_index=True)
    assert len(v2) == len(v) + 1 and f2.shape == f.shape
    np.testing.assert_array_equal(v2[: len(v)], v)  # input vertices keep their indices
    np.testing.assert_array_equal(v2, v[index])
    np.testing.assert_array_equal(index[f2], f)  # every face keeps its positions
    assert nonmanifold_problem(f2, len(v2)) is None
    mesh = trimesh.Trimesh(v2, f2, process=False)
    assert mesh.is_watertight and len(mesh.split(only_watertight=False)) == 2
    # two closed tetrahedra sharing an edge (four faces on it), as marching cubes gives where
    # two sheets touch: split into two closed tetrahedra
    tet = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 1], [0, -1, 1], [0, 1, -1], [0, -1, -1]], dtype=float)
    f = np.vstack([tet, np.where(tet == 2, 4, np.where(tet == 3, 5, tet))[:, ::-1]])
    assert "edge between vertices 0 and 1 is in 4 faces" in nonmanifold_problem(f, len(v))
    v2, f2 = split_nonmanifold_vertices(v, f)
    assert len(v2) == 8 and nonmanifold_problem(f2, len(v2)) is None
    assert trimesh.Trimesh(v2, f2, process=False).is_watertight
    # a manifold mesh comes back unchanged
    v, f = _sphere(subdivisions=2)
    v2, f2 = split_nonmanifold_vertices(v, f)
    np.testing.assert_array_equal(v2, v)
    np.testing.assert_array_equal(f2, f)


def test_split_nonmanifold_vertices_repairs_a_split_half_of_a_noisy_surface():
    """Selecting the faces on one side of a rough surface leaves pinched vertices along the
    cut; the repaired half passes check_mesh with the same faces and positions."""
    rng = np.random.default_rng(3)
    v, f = _sphere(radius=20.0, centre=(0.0, 0.0, 0.0), subdivisions=4)
    v = v + rng.normal(scale=0.6, size=v.shape)
    keep = (v[f].mean(axis=1)[:, 2] + rng.normal(scale=0.8, size=len(f))) > 0  # ragged cut
    half = f[keep]
    assert "fans" in nonmanifold_problem(half, len(v))
    v2, f2, index = split_nonmanifold_vertices(v, half, return_index=True)
    np.testing.assert_array_equal(index[f2], half)
    check_mesh(trimesh.Trimesh(v2, f2, process=False))


def test_measure_reports_a_non_manifold_mesh_instead_of_refusing_it(tmp_path, run_cli):
    """nemo measure is a diagnostic: it loads a non-manifold surface and says so in its notes."""
    a = trimesh.creation.icosphere(subdivisions=2, radius=5.0)
    b = trimesh.creation.icosphere(subdivisions=2, radius=5.0)
    top = int(np.argmax(a.vertices[:, 2]))
    shift = a.vertices[top] - b.vertices[int(np.argmin(b.vertices[:, 2]))]
    vertices = np.vstack([a.vertices, b.vertices + shift])
    faces = np.vstack([a.faces, b.faces + len(a.vertices)])
    faces[faces == len(a.vertices) + int(np.argmin(b.vertices[:, 2]))] = top  # share one vertex
    path = tmp_path / "bowtie.ply"
    save_mesh(make_mesh(vertices, faces, orient_outward=False), path)
    code, out, err = run_cli("measure", path)
    assert code == 0 and "not a manifold orientable surface" in out, err
    code, _, err = run_cli("curvature", path, "-o", tmp_path / "c.parquet")
    assert code == 2 and "not a manifold surface" in err
