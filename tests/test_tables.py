"""Parquet tables (nemo.tables): round trip with provenance, schemas, refusals, atomic writes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest

import nemo
import nemo.tables
from nemo.errors import NemoError
from nemo.tables import (
    SCHEMAS,
    check_table_mesh,
    field_on_vertices,
    read_provenance,
    read_table,
    write_table,
)


def _layer(vertex, intensity):
    return pd.DataFrame({"vertex": np.asarray(vertex, dtype=np.int64), "intensity": np.asarray(intensity, float)})


# ----------------------------------------------------------------------------- round trip
def test_round_trip_keeps_the_data_and_the_provenance(tmp_path):
    df = pd.DataFrame({"vertex": np.array([4, 0, 2], dtype=np.int64), "intensity": [1.5, np.nan, -2.0],
                       "label": ["a", "b", "c"]}, index=[10, 11, 12])
    path = tmp_path / "new" / "sub" / "t.parquet"  # the folder does not exist yet
    write_table(df, path, unit="um", command="peel", parameters={"range": [0, 2], "reduce": "mean"},
                mesh=Path("m.ply"), n_vertices=np.int64(5), scale=np.float32(0.5), shape=np.array([3, 4]))
    back = read_table(path, "layer")
    # the rows and columns as written; the pandas index is not stored (a fresh 0, 1, 2)
    pd.testing.assert_frame_equal(back, df.reset_index(drop=True))
    # numpy scalars, arrays and paths stored as plain JSON values, the nemo version added
    assert read_provenance(path) == {
        "version": nemo.__version__, "unit": "um", "command": "peel",
        "parameters": {"range": [0, 2], "reduce": "mean"}, "mesh": "m.ply", "n_vertices": 5, "scale": 0.5,
        "shape": [3, 4],
    }
    assert isinstance(read_provenance(path)["n_vertices"], int)
    # pandas' own metadata is kept beside nemo's
    assert set(pq.read_schema(path).metadata) == {b"pandas", b"nemo"}


def test_overwrite_replaces_the_table_and_its_provenance(tmp_path):
    path = tmp_path / "t.parquet"
    write_table(_layer([0, 1], [1.0, 2.0]), path, command="first", n_vertices=2)
    write_table(_layer([0], [9.0]), path, command="second")
    assert read_table(path, "layer")["intensity"].tolist() == [9.0]
    assert read_provenance(path) == {"version": nemo.__version__, "command": "second"}


def test_provenance_that_is_not_json_is_refused_before_writing(tmp_path):
    path = tmp_path / "t.parquet"
    with pytest.raises(TypeError, match="not JSON serialisable"):
        write_table(_layer([0], [1.0]), path, parameters={"rng": object()})
    assert list(tmp_path.iterdir()) == []


def test_a_table_from_another_tool_has_empty_provenance(tmp_path):
    path = tmp_path / "plain.parquet"
    _layer([0, 1], [1.0, 2.0]).to_parquet(path)
    assert read_provenance(path) == {}
    assert read_table(path, "layer", n_vertices=2)["intensity"].tolist() == [1.0, 2.0]


# ----------------------------------------------------------------------------- schemas
def test_every_per_vertex_table_kind_has_a_vertex_column():
    assert set(SCHEMAS) == {"layer", "curvature", "thickness", "directors", "order", "align", "defects"}
    for kind, columns in SCHEMAS.items():
        assert "vertex" in columns, kind
        assert len(set(columns)) == len(columns), kind


@pytest.mark.parametrize("kind", sorted(SCHEMAS))
def test_each_kind_needs_each_of_its_columns(tmp_path, kind):
    full = pd.DataFrame({c: np.arange(3) for c in SCHEMAS[kind]})
    write_table(full.assign(extra=1.0), tmp_path / "full.parquet")
    assert list(read_table(tmp_path / "full.parquet", kind).columns) == [*SCHEMAS[kind], "extra"]
    for column in SCHEMAS[kind]:
        write_table(full.drop(columns=column), tmp_path / "lacking.parquet")
        with pytest.raises(NemoError, match=rf"lacks column\(s\) {column} needed for a {kind} table"):
            read_table(tmp_path / "lacking.parquet", kind)


def test_missing_columns_are_all_named_with_what_the_file_has(tmp_path):
    path = tmp_path / "t.parquet"
    write_table(pd.DataFrame({"vertex": [0], "depth": [1.0]}), path)
    with pytest.raises(NemoError) as exc:
        read_table(path, "layer", columns=("profile",))
    assert str(exc.value) == (
        f"{path} lacks column(s) intensity, profile needed for a layer table and this step (it has: vertex, "
        "depth); "
        "was it made by the right nemo command?"
    )
    with pytest.raises(NemoError, match=r"lacks column\(s\) S needed for this step"):
        read_table(path, columns=("vertex", "S"))
    assert list(read_table(path, columns=("depth",)).columns) == ["vertex", "depth"]
    assert list(read_table(path).columns) == ["vertex", "depth"]  # no kind: any columns


# ----------------------------------------------------------------------------- unreadable files
def test_missing_file_and_non_parquet_files_are_clear_errors(tmp_path):
    with pytest.raises(NemoError, match="table not found: .*nope.parquet"):
        read_table(tmp_path / "nope.parquet", "layer")
    (tmp_path / "t.csv").write_text("vertex,intensity\n0,1\n")
    with pytest.raises(NemoError, match="t.csv is not a Parquet table"):
        read_table(tmp_path / "t.csv", "layer")
    write_table(_layer(range(50), np.ones(50)), tmp_path / "t.parquet")
    raw = (tmp_path / "t.parquet").read_bytes()
    (tmp_path / "cut.parquet").write_bytes(raw[: len(raw) // 2])  # a copy cut short
    with pytest.raises(NemoError, match="cut.parquet is not a Parquet table"):
        read_table(tmp_path / "cut.parquet", "layer")


# ----------------------------------------------------------------------------- tables and meshes
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


def test_check_table_mesh_uses_provenance_then_vertex_indices(tmp_path):
    path = tmp_path / "t.parquet"
    # a subset of a 10-vertex mesh's vertices (like directors at patch centres)
    write_table(_layer([2, 9], [1.0, 1.0]), path, mesh="m.ply", n_vertices=10)
    check_table_mesh(read_table(path), path, 10)
    with pytest.raises(NemoError) as exc:
        check_table_mesh(read_table(path), path, 11)
    assert str(exc.value) == (
        f"{path} was computed on another mesh (m.ply, 10 vertices) than the one given (11 vertices): "
        "pass the mesh the table was made on"
    )
    # no provenance: only the vertex indices tell; vertex 9 needs at least 10 vertices
    write_table(_layer([2, 9], [1.0, 1.0]), path)
    check_table_mesh(read_table(path), path, 10)
    check_table_mesh(read_table(path), path, 500)
    with pytest.raises(NemoError, match="refers to vertex 9 but the mesh has vertices 0 to 8"):
        check_table_mesh(read_table(path), path, 9)
    write_table(_layer([-1, 3], [1.0, 1.0]), path)
    with pytest.raises(NemoError, match="another mesh"):
        check_table_mesh(read_table(path), path, 10)
    # an empty table and a table without a vertex column fit any mesh
    write_table(_layer([], []), path)
    check_table_mesh(read_table(path), path, 3)
    write_table(pd.DataFrame({"S": [0.5]}), path)
    check_table_mesh(read_table(path), path, 3)


def test_read_table_checks_the_mesh_only_when_asked(tmp_path):
    path = tmp_path / "t.parquet"
    write_table(_layer([0, 1, 2], [1.0, 2.0, 3.0]), path, n_vertices=3)
    assert len(read_table(path, "layer")) == 3  # no n_vertices: no check
    assert len(read_table(path, "layer", n_vertices=3)) == 3
    with pytest.raises(NemoError, match=r"another mesh \(\?, 3 vertices\)"):
        read_table(path, "layer", n_vertices=4)


def test_field_on_vertices_scatters_by_vertex(tmp_path):
    df = pd.DataFrame({"vertex": [3, 0], "H": [2, 7]})  # integer values, rows out of order
    out = field_on_vertices(df, "H", 5)
    assert out.dtype == np.float64
    np.testing.assert_array_equal(out, [7.0, np.nan, np.nan, 2.0, np.nan])
    with pytest.raises(NemoError, match="t.parquet has 2 rows but the mesh has 5 vertices"):
        field_on_vertices(df, "H", 5, "t.parquet", exact=True)
    every = pd.DataFrame({"vertex": [2, 0, 1], "H": [0.2, 0.0, 0.1]})
    np.testing.assert_array_equal(field_on_vertices(every, "H", 3, exact=True), [0.0, 0.1, 0.2])
    twice = pd.DataFrame({"vertex": [0, 0, 1], "H": [1.0, 1.0, 1.0]})  # 3 rows, vertex 2 missing
    with pytest.raises(NemoError, match="3 rows but the mesh has 3 vertices"):
        field_on_vertices(twice, "H", 3, exact=True)
    with pytest.raises(NemoError, match="refers to vertex 3 but the mesh has 3 vertices"):
        field_on_vertices(df, "H", 3)
    with pytest.raises(NemoError, match="t.parquet has no column 'K' \\(columns: vertex, H\\)"):
        field_on_vertices(df, "K", 5, "t.parquet")
    assert np.isnan(field_on_vertices(df.iloc[:0], "H", 2)).all()


# ----------------------------------------------------------------------------- atomic writes
def test_interrupt_keeps_the_previous_table(tmp_path, monkeypatch):
    path = tmp_path / "t.parquet"
    write_table(pd.DataFrame({"vertex": [0, 1], "intensity": [1.0, 2.0]}), path)

    def interrupted(table, where, **kwargs):
        where.write_bytes(b"PAR1 partial")
        raise KeyboardInterrupt

    monkeypatch.setattr(nemo.tables.pq, "write_table", interrupted)
    with pytest.raises(KeyboardInterrupt):
        write_table(pd.DataFrame({"vertex": [0], "intensity": [9.0]}), path)
    assert read_table(path, "layer")["intensity"].tolist() == [1.0, 2.0]
    assert [p.name for p in tmp_path.iterdir()] == ["t.parquet"]


def test_failed_first_write_leaves_no_file(tmp_path, monkeypatch):
    def disk_full(table, where, **kwargs):
        where.write_bytes(b"PAR1 partial")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(nemo.tables.pq, "write_table", disk_full)
    with pytest.raises(OSError, match="No space left"):
        write_table(_layer([0], [1.0]), tmp_path / "out" / "t.parquet")
    assert list((tmp_path / "out").iterdir()) == []  # the folder was made, no table nor temporary in it


def test_misuse_and_damaged_provenance_are_clear(tmp_path):
    """An unknown kind is a programming error; numpy bools are JSON; a negative vertex is named;
    provenance of a non-Parquet file is a NemoError, not pyarrow's."""
    from nemo.tables import check_table_mesh, read_provenance

    path = tmp_path / "t.parquet"
    write_table(pd.DataFrame({"vertex": [-3, 1], "intensity": [1.0, 2.0]}), path, ok=np.bool_(True))
    assert read_provenance(path)["ok"] is True
    with pytest.raises(ValueError, match="unknown table kind 'layr'"):
        read_table(path, "layr")
    with pytest.raises(NemoError, match="refers to vertex -3 but the mesh has vertices 0 to 9"):
        check_table_mesh(read_table(path), path, 10)
    (tmp_path / "bad.parquet").write_bytes(b"not parquet at all")
    with pytest.raises(NemoError, match="is not a Parquet table"):
        read_provenance(tmp_path / "bad.parquet")
    with pytest.raises(NemoError, match="table not found"):
        read_provenance(tmp_path / "missing.parquet")


def test_a_tables_in_memory_attrs_are_not_written(tmp_path):
    """pandas stores ``DataFrame.attrs`` in the Parquet file and deep-copies them at every slice of the
    table read back: a defects table's candidates (96 KB for 254 objects) cost 6 s of a summary. Only
    the provenance is written; the caller's table keeps its attrs."""
    df = pd.DataFrame({"vertex": np.arange(3, dtype=np.int64), "intensity": np.ones(3)})
    df.attrs["candidates"] = [{"vertex": k} for k in range(1000)]
    write_table(df, tmp_path / "t.parquet", command="test")
    assert pd.read_parquet(tmp_path / "t.parquet").attrs == {}
    assert len(df.attrs["candidates"]) == 1000 and read_provenance(tmp_path / "t.parquet")["command"] == "test"
