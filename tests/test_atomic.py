"""nemo.atomic: a write that fails or is interrupted leaves the previous file as it was."""

from __future__ import annotations

import json

import pandas as pd
import pytest

from nemo import atomic
from nemo.tables import read_table, write_table


def test_failed_write_keeps_the_previous_file_and_leaves_no_temporary(tmp_path):
    target = tmp_path / "result.json"
    atomic.write_json(target, {"run": 1})
    with pytest.raises(RuntimeError):
        with atomic.atomic_path(target) as tmp:
            tmp.write_text('{"run": 2, "half')  # interrupted half-way
            raise RuntimeError("killed")
    assert json.loads(target.read_text()) == {"run": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["result.json"]


def test_interrupt_keeps_the_previous_table(tmp_path, monkeypatch):
    path = tmp_path / "t.parquet"
    write_table(pd.DataFrame({"vertex": [0, 1], "intensity": [1.0, 2.0]}), path)
    import nemo.tables

    def interrupted(table, where, **kwargs):
        where.write_bytes(b"PAR1 partial")
        raise KeyboardInterrupt

    monkeypatch.setattr(nemo.tables.pq, "write_table", interrupted)
    with pytest.raises(KeyboardInterrupt):
        write_table(pd.DataFrame({"vertex": [0], "intensity": [9.0]}), path)
    assert read_table(path, "layer")["intensity"].tolist() == [1.0, 2.0]
    assert [p.name for p in tmp_path.iterdir()] == ["t.parquet"]


def test_success_replaces_and_keeps_the_suffix_when_asked(tmp_path):
    target = tmp_path / "figure.png"
    target.write_bytes(b"old")
    with atomic.atomic_path(target, keep_suffix=True) as tmp:
        assert tmp.suffix == ".png" and tmp.parent == tmp_path and tmp.name.startswith(".")
        tmp.write_bytes(b"new")
    assert target.read_bytes() == b"new" and [p.name for p in tmp_path.iterdir()] == ["figure.png"]
