"""nemo.objects: per-vertex object labels and per-object runs of a step."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import trimesh

from nemo import objects
from nemo.errors import NemoError
from nemo.mesh import load_mesh, save_mesh


def _two_spheres(r0: float = 10.0, r1: float = 6.0) -> trimesh.Trimesh:
    a = trimesh.creation.icosphere(subdivisions=3, radius=r0)
    b = trimesh.creation.icosphere(subdivisions=2, radius=r1)
    b.apply_translation([40.0, 0.0, 0.0])
    a.units = b.units = "um"
    return objects.concatenate([a, b], [0, 1])


def test_concatenate_labels_vertices_and_parts_give_them_back(tmp_path):
    mesh = _two_spheres()
    labels = objects.vertex_labels(mesh)
    assert np.bincount(labels).tolist() == [642, 162]
    save_mesh(mesh, tmp_path / "two.ply")  # the labels survive the PLY
    mesh = load_mesh(tmp_path / "two.ply")
    split = objects.parts(mesh)
    assert [p.label for p in split] == [0, 1]
    for part, radius in zip(split, (10.0, 6.0)):
        assert part.mesh.is_watertight and part.mesh.euler_number == 2
        np.testing.assert_allclose(np.asarray(part.mesh.vertices), np.asarray(mesh.vertices)[part.vertices])
        r = np.linalg.norm(part.mesh.vertices - part.mesh.vertices.mean(axis=0), axis=1)
        np.testing.assert_allclose(r, radius, rtol=1e-3)
        assert part.mesh.units == "um"
    assert objects.parts(split[0].mesh) is None  # one object: run as before
    assert objects.parts(trimesh.creation.icosphere()) is None  # no labels: one object


def test_tables_go_to_the_parts_and_back():
    mesh = _two_spheres()
    split = objects.parts(mesh)
    n = len(mesh.vertices)
    df = pd.DataFrame({"vertex": np.arange(n)[::-1], "value": np.arange(n)[::-1] * 2.0})
    local = [objects.local_table(df, p) for p in split]
    for part, table in zip(split, local):
        assert sorted(table["vertex"]) == list(range(len(part.vertices)))
        np.testing.assert_array_equal(table["value"], 2.0 * part.vertices[table["vertex"]])
    back = objects.combine_tables(local, split)
    np.testing.assert_array_equal(back["vertex"], np.arange(n))
    np.testing.assert_array_equal(back["value"], 2.0 * np.arange(n))
    np.testing.assert_array_equal(back["object"], objects.vertex_labels(mesh))
    assert list(back.columns) == ["vertex", "object", "value"]


def test_parameters_per_object():
    split = objects.parts(_two_spheres())
    p = objects.combine_params([{"radius": 2.0}, {"radius": 3.0}], split)
    assert p["radius"] == 2.0 and objects.values(p, "radius") == [2.0, 3.0]
    assert objects.pick(p, 1) == {"radius": 3.0, "object": 1}
    assert objects.values({"radius": 5.0}, "radius") == 5.0 and objects.pick({"a": 1}, 3) == {"a": 1}
    assert objects.value_for([1, 2], 1) == 2 and objects.value_for(7.0, 1) == 7.0


def test_bad_labels_are_clear_errors():
    mesh = _two_spheres()
    bad = objects.vertex_labels(mesh).astype(float)
    bad[0] = 1.0  # a face now joins two objects
    objects.set_labels(mesh, bad)
    with pytest.raises(NemoError, match="joins two objects"):
        objects.parts(mesh)
    bad[0] = np.nan
    objects.set_labels(mesh, bad)
    with pytest.raises(NemoError, match="not one non-negative label per vertex"):
        objects.parts(mesh)
