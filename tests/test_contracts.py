"""Contracts between steps: tables and meshes that do not belong together are refused,
inward meshes are repaired with a warning, calibration overrides set the unit."""

from __future__ import annotations

import warnings

import numpy as np
import pandas as pd
import pytest
import tifffile
import trimesh

from nemo.errors import NemoError, NemoWarning
from nemo.io import read_stack, write_hyperstack
from nemo.mesh import (
    load_mesh, make_mesh, merge_coincident_vertices, save_mesh, signed_volume, vertex_areas,
    vertex_normals,
)
from nemo.tables import field_on_vertices, read_table, write_table


def _sphere(radius=10.0, subdivisions=3):
    s = trimesh.creation.icosphere(subdivisions, radius=radius)
    return make_mesh(s.vertices, s.faces)


def test_inward_wound_ply_is_flipped_with_a_warning(tmp_path):
    mesh = _sphere()
    inward = trimesh.Trimesh(mesh.vertices, mesh.faces[:, ::-1], process=False)
    path = tmp_path / "inward.ply"
    save_mesh(inward, path)
    with pytest.warns(NemoWarning, match="wound inward"):
        back = load_mesh(path)
    assert signed_volume(back.vertices, back.faces) > 0
    centred = back.vertices - back.vertices.mean(axis=0)
    assert np.all(np.einsum("ij,ij->i", vertex_normals(back), centred) > 0)


def test_spacing_comment_round_trip(tmp_path):
    mesh = _sphere()
    mesh.metadata["spacing"] = (2.0, 0.5, 0.25)
    save_mesh(mesh, tmp_path / "m.ply")
    assert load_mesh(tmp_path / "m.ply").metadata["spacing"] == (2.0, 0.5, 0.25)


def test_vertex_areas_sum_to_area_and_sphere_is_close_to_analytic():
    mesh = _sphere(radius=7.0, subdivisions=5)
    areas = vertex_areas(mesh)
    assert areas.shape == (len(mesh.vertices),)
    assert np.isclose(areas.sum(), mesh.area)
    assert abs(areas.sum() / (4 * np.pi * 49) - 1) < 2e-3


def test_coincident_vertices_merged_and_degenerate_normals_taken_from_twin():
    mesh = _sphere()
    v = np.vstack([mesh.vertices, mesh.vertices[:1]])  # a duplicate of vertex 0
    f = np.vstack([mesh.faces, [[0, len(v) - 1, 1]]])  # a zero-area face on it
    dup = trimesh.Trimesh(v, f, process=False)
    n = vertex_normals(dup)
    assert np.allclose(n[-1], n[0])
    mv, mf, index = merge_coincident_vertices(v, f)
    assert len(mv) == len(mesh.vertices) and len(mf) == len(mesh.faces)
    assert index[-1] == index[0]


def test_table_from_another_mesh_is_refused(tmp_path):
    path = tmp_path / "layer.parquet"
    write_table(pd.DataFrame({"vertex": np.arange(100), "intensity": np.ones(100)}), path,
                mesh="small.ply", n_vertices=100)
    with pytest.raises(NemoError, match="100 vertices"):
        read_table(path, "layer", n_vertices=642)
    df = read_table(path, "layer", n_vertices=100)
    with pytest.raises(NemoError, match="another mesh"):
        field_on_vertices(df, "intensity", 642, str(path), exact=True)
    assert np.all(field_on_vertices(df, "intensity", 100, str(path), exact=True) == 1)


def test_spacing_override_sets_um_and_pixel_unit_is_uncalibrated(tmp_path):
    data = np.zeros((4, 5, 6), np.uint8)
    tifffile.imwrite(tmp_path / "px.tif", data, imagej=True, metadata={"axes": "ZYX", "unit": "pixel"})
    with pytest.warns(NemoWarning, match="no spatial calibration"):
        _, info = read_stack(tmp_path / "px.tif")
    assert info.unit == "pixel" and not info.calibrated
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _, info = read_stack(tmp_path / "px.tif", spacing=(2, 0.5, 0.5))
    assert info.unit == "um" and info.spacing == (2.0, 0.5, 0.5)


def test_missing_z_spacing_warns(tmp_path):
    data = np.zeros((4, 5, 6), np.uint8)
    tifffile.imwrite(tmp_path / "noz.tif", data, imagej=True, resolution=(2.0, 2.0),
                     metadata={"axes": "ZYX", "unit": "micron"})
    with pytest.warns(NemoWarning, match="no z spacing"):
        _, info = read_stack(tmp_path / "noz.tif")
    assert info.spacing == (0.5, 0.5, 0.5)
    write_hyperstack(tmp_path / "ok.tif", data, (1.0, 0.5, 0.5), axes="ZYX")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read_stack(tmp_path / "ok.tif")
