"""nemo.layout: the results folder layout shared by the workflow, `nemo run` and the viewers,
and the discovery of frames and their files in it."""

from __future__ import annotations

from pathlib import Path

import pytest

from nemo import layout
from nemo.errors import NemoError


def _touch(*paths: Path) -> None:
    for p in paths:
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(b"")


def test_names_of_the_per_frame_files():
    assert layout.frame_dir("results", "demo", 3, 1) == "results/demo/t3/c1"
    assert layout.layer_file("directors", "basal") == "directors_basal.parquet"
    assert layout.measure_file("inner") == "measure_inner.json"
    assert layout.curvature_file("outer") == "curvature_outer.parquet"
    assert layout.align_file("a", "b") == "align_a_b.parquet"
    assert layout.surface_mesh_path("surf/t{t}.ply", 7) == "surf/t7.ply"
    with pytest.raises(NemoError, match="only placeholder"):
        layout.surface_mesh_path("surf/{c}.ply", 0)


def test_discover_frame_classifies_a_workflow_frame_folder(tmp_path):
    frame = tmp_path / "demo" / "t2" / "c1"
    _touch(*(frame / name for name in ("mesh.ply", "mesh.inner.ply", "mesh.outer.ply", "layer_basal.parquet",
                                       "directors_basal.parquet", "order_basal.parquet", "defects_basal.parquet",
                                       "order_apical.parquet", "curvature_inner.parquet", "thickness.parquet",
                                       "align_basal_apical.parquet")))
    ff = layout.discover_frame(frame)
    assert (ff.t, ff.c) == (2, 1)
    assert set(ff.meshes) == {"mesh", "inner", "outer"}
    assert ff.layer_names() == ["apical", "basal"]
    assert ff.curvature == {"inner": frame / "curvature_inner.parquet"}
    assert list(ff.align) == ["basal_apical"]
    assert len(ff.tables()) == 8


def test_find_frames_from_the_root_a_dataset_or_a_frame(tmp_path):
    for t in (0, 1):
        _touch(tmp_path / "demo" / f"t{t}" / "c0" / "mesh.ply")
    _touch(tmp_path / "other" / "t5" / "c2" / "mesh.ply", tmp_path / "demo" / "t1" / "c0" / "notes.txt")
    (tmp_path / "demo" / "summary").mkdir()
    tree = layout.find_frames(tmp_path, dataset="demo")
    assert tree.dataset == "demo" and sorted(tree.frames) == [(0, 0), (1, 0)] and tree.summary is not None
    assert layout.find_frames(tmp_path / "other").frames == {(5, 2): tmp_path / "other" / "t5" / "c2"}
    single = layout.find_frames(tmp_path / "demo" / "t1" / "c0")
    assert list(single.frames) == [(1, 0)] and single.summary == tmp_path / "demo" / "summary"
    run = tmp_path / "run"  # a nemo run folder: its frame from summary.json (it titled c=0 for --c 1)
    _touch(run / "mesh.ply")
    assert list(layout.find_frames(run).frames) == [(0, 0)]  # no summary: (0, 0)
    (run / "summary.json").write_text('{"t": 3, "c": 1}')
    assert list(layout.find_frames(run).frames) == [(3, 1)]
    with pytest.raises(NemoError, match="dataset 'nope' not found"):
        layout.find_frames(tmp_path, dataset="nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(NemoError, match="no NEMO results"):
        layout.find_frames(tmp_path / "empty")
    with pytest.raises(NemoError, match="is not a folder"):
        layout.find_frames(tmp_path / "missing")
