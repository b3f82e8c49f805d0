"""nemo.atomic: a write that fails or is interrupted leaves the previous file as it was."""

from __future__ import annotations

import json
import os

import pytest

from nemo import atomic


def test_failed_write_keeps_the_previous_file_and_leaves_no_temporary(tmp_path):
    target = tmp_path / "result.json"
    atomic.write_json(target, {"run": 1})
    with pytest.raises(RuntimeError):
        with atomic.atomic_path(target) as tmp:
            tmp.write_text('{"run": 2, "half')  # interrupted half-way
            raise RuntimeError("killed")
    assert json.loads(target.read_text()) == {"run": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["result.json"]


def test_success_replaces_and_keeps_the_suffix_when_asked(tmp_path):
    target = tmp_path / "figure.png"
    target.write_bytes(b"old")
    with atomic.atomic_path(target, keep_suffix=True) as tmp:
        assert tmp.suffix == ".png" and tmp.parent == tmp_path and tmp.name.startswith(".")
        tmp.write_bytes(b"new")
    assert target.read_bytes() == b"new" and [p.name for p in tmp_path.iterdir()] == ["figure.png"]


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs Linux's /proc")
def test_a_folder_that_takes_no_file_is_refused_before_any_work():
    """/proc passes ``os.access(W_OK)`` for root yet takes no file: ``nemo mesh -o /proc/x.ply``
    computed the mesh and failed only when writing it (a user other than root is refused by the
    access check)."""
    from nemo.errors import NemoError

    with pytest.raises(NemoError, match=r"(cannot write in|is not writable).*choose a writable output path"):
        atomic.make_folder("/proc")


def test_make_folder_creates_parents_and_leaves_nothing_behind(tmp_path):
    folder = atomic.make_folder(tmp_path / "a" / "b")
    assert folder.is_dir() and not any(folder.iterdir())
