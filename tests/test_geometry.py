"""Unit vectors, tangent frames and the mesh-edge graph (nemo.geometry)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import scipy.sparse as sp
import trimesh

from nemo.errors import NemoError, NemoWarning
from nemo.geometry import (
    axis_frames,
    boundary_loop,
    edge_graph,
    frames_from_vectors,
    geodesic_ball,
    project_tangent,
    smooth_conserving,
    tangent_basis,
    tangent_frames,
    unit_vectors,
)
from nemo.mesh import make_mesh


def sphere_mesh(radius=30.0, subdivisions=4):
    ico = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return make_mesh(ico.vertices, ico.faces)


# ------------------------------------------------------------------------------------------------
# unit vectors


def test_unit_vectors_zero_length_nan_or_zero():
    v = np.array([[3.0, 4.0, 0.0], [0.0, 0.0, 0.0], [np.nan, 1.0, 0.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # 0/0 stays silent
        nan_rows = unit_vectors(v)
        zero_rows = unit_vectors(v, zero_stays_zero=True)
    np.testing.assert_array_equal(nan_rows[0], [0.6, 0.8, 0.0])
    assert np.isnan(nan_rows[1]).all() and np.isnan(nan_rows[2]).all()
    np.testing.assert_array_equal(zero_rows[0], [0.6, 0.8, 0.0])
    np.testing.assert_array_equal(zero_rows[1], [0.0, 0.0, 0.0])
    np.testing.assert_array_equal(zero_rows[2], v[2])  # a NaN length: returned undivided
    # bit-identical to the plain division (the former private copies in order, morphology, frames)
    rng = np.random.default_rng(0)
    w = rng.standard_normal((100, 3))
    norm = np.linalg.norm(w, axis=-1, keepdims=True)
    np.testing.assert_array_equal(unit_vectors(w), w / norm)
    np.testing.assert_array_equal(unit_vectors(w, zero_stays_zero=True), w / norm)
    # any trailing dimension
    assert unit_vectors(np.array([0.0, 2.0])).tolist() == [0.0, 1.0]


def test_project_tangent():
    normals = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    vec = np.array([[2.0, 0.0, 5.0], [0.0, 0.0, 3.0]])
    out = project_tangent(vec, normals)
    np.testing.assert_array_equal(out[0], [1.0, 0.0, 0.0])
    assert np.isnan(out[1]).all()  # normal vectors have no tangent direction


# ------------------------------------------------------------------------------------------------
# tangent frames


def test_frames_axis_and_smooth():
    mesh = sphere_mesh(30.0, subdivisions=4)
    normals = np.asarray(mesh.vertex_normals)
    for method in ("axis", "smooth"):
        t1, t2 = tangent_frames(mesh, method)
        np.testing.assert_allclose(np.linalg.norm(t1, axis=1), 1, atol=1e-9)
        np.testing.assert_allclose(np.einsum("ij,ij->i", t1, t2), 0, atol=1e-9)
        np.testing.assert_allclose(np.cross(t1, t2), normals, atol=1e-6)
    # the smooth frame varies slowly between neighbouring vertices (away from its singularity)
    t1s, _ = tangent_frames(mesh, "smooth")
    e = mesh.edges_unique
    far = (mesh.vertices[e[:, 0], 2] > -20) & (mesh.vertices[e[:, 0], 2] < 20)
    turn = np.rad2deg(np.arccos(np.clip(np.einsum("ij,ij->i", t1s[e[:, 0]], t1s[e[:, 1]]), -1, 1)))
    assert np.percentile(turn[far], 99) < 15
    # big meshes fall back to axis frames with a warning, never minutes of potpourri3d
    with pytest.warns(NemoWarning, match="smooth tangent frames skipped"):
        t1f, _ = tangent_frames(mesh, "smooth", max_vertices=100)
    np.testing.assert_allclose(t1f, axis_frames(normals)[0])
    # a subset of vertices
    sub = np.array([3, 7, 11])
    t1v, _ = tangent_frames(mesh, "axis", vertices=sub)
    np.testing.assert_array_equal(t1v, axis_frames(normals[sub])[0])
    with pytest.raises(NemoError, match="unknown tangent-frame method"):
        tangent_frames(mesh, "polar")


def test_axis_frames_switch_zero_and_nan_normals():
    # axis frames where N ∥ x̂ use ŷ
    t1x, t2x = axis_frames(np.array([[1.0, 0, 0], [0, 0, 1.0]]))
    np.testing.assert_allclose(np.cross(t1x, t2x), [[1, 0, 0], [0, 0, 1]], atol=1e-12)
    t1, t2 = axis_frames(np.array([[0.0, 0.0, 0.0], [np.nan, np.nan, np.nan]]))
    np.testing.assert_array_equal(t1[0], [0.0, 0.0, 0.0])  # a zero normal gives a zero frame
    assert not np.isfinite(t1[1]).all() and np.isnan(t2[1]).all()  # NaN rows for NaN normals


def test_tangent_basis_is_one_row_of_axis_frames():
    n = np.array([0.3, -0.5, 0.8])
    t1, t2 = tangent_basis(n)
    a1, a2 = axis_frames(n[None])
    assert t1.shape == (3,)
    np.testing.assert_array_equal(t1, a1[0])
    np.testing.assert_array_equal(t2, a2[0])


def test_one_frame_construction_for_measured_and_analytic_angles():
    """tangent_basis and the synthetic data's analytic angles use the same axis frames as the
    measurements, so angles compare directly."""
    from nemo.synthetic import nematic_angle, preset_defects

    normals = np.array([[0.93, 0.3, 0.21], [1.0, 0, 0], [0, 0, 1.0], [-0.2, 0.97, 0.1]])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    t1, t2 = axis_frames(normals)
    for i, normal in enumerate(normals):
        for a, b in zip(tangent_basis(normal), (t1[i], t2[i])):
            np.testing.assert_array_equal(a, b)
    d, m = preset_defects("tetrahedron")
    th = nematic_angle(normals, d, m)
    np.testing.assert_allclose(th, nematic_angle(normals, d, m, t1, t2))


def test_frames_from_vectors_falls_back_to_axis_frames():
    normals = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    t1, t2 = frames_from_vectors(normals, np.array([[0.0, 2.0, 1.0], [0.0, 0.0, 1.0]]))
    np.testing.assert_allclose(t1[0], [0.0, 1.0, 0.0])
    np.testing.assert_array_equal(t1[1], axis_frames(normals[1:])[0][0])
    np.testing.assert_allclose(np.cross(t1, t2), normals, atol=1e-12)


# ------------------------------------------------------------------------------------------------
# mesh-edge graph


def test_boundary_loop_is_ccw_ring_of_edges():
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=50.0)
    graph = edge_graph(mesh)
    v = 17
    idx, dist = geodesic_ball(graph, v, 30.0)
    inside = np.zeros(len(mesh.vertices), bool)
    inside[idx[dist < 20.0]] = True
    loop, _ = boundary_loop(np.asarray(mesh.faces), inside)
    assert loop is not None and len(loop) > 20
    edges = {tuple(sorted(e)) for e in mesh.edges_unique.tolist()}
    assert all(tuple(sorted((a, b))) in edges for a, b in zip(loop, np.roll(loop, -1)))
    t1, t2 = tangent_basis(mesh.vertex_normals[v])
    rel = mesh.vertices[loop] - mesh.vertices[v]
    ang = np.unwrap(np.arctan2(rel @ t2, rel @ t1))
    assert ang[-1] - ang[0] > 1.8 * np.pi  # counter-clockwise seen from the outward normal
    # geodesic distances along edges: the contour lies just inside the radius
    d = dict(zip(idx.tolist(), dist.tolist()))
    assert all(15.0 < d[i] < 20.0 for i in loop)


def test_boundary_loop_empty_and_closed():
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=10.0)
    faces = np.asarray(mesh.faces)
    loop, region = boundary_loop(faces, np.zeros(len(mesh.vertices), bool))
    assert loop is None and len(region) == 0
    loop, region = boundary_loop(faces, np.ones(len(mesh.vertices), bool))
    assert loop is None and len(region) == len(mesh.vertices)  # the ball covers a closed surface


def test_edge_graph_and_smooth_conserving():
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=10.0)
    graph = edge_graph(mesh)
    assert sp.issparse(graph) and (graph != graph.T).nnz == 0
    e = mesh.edges_unique[0]
    assert graph[e[0], e[1]] == pytest.approx(np.linalg.norm(mesh.vertices[e[0]] - mesh.vertices[e[1]]))
    values = np.random.default_rng(1).standard_normal(len(mesh.vertices))
    out = smooth_conserving(values, graph, 3)
    assert out.sum() == pytest.approx(values.sum(), rel=1e-12)
    assert out.std() < values.std()
