"""The checks every ``nemo`` command shares (nemo/cli/common.py, nemo/cli/__init__.py):
outputs never replace inputs, unwritable outputs and bad seeds are messages, not tracebacks."""

from __future__ import annotations

import hashlib

import numpy as np
import pandas as pd
import pytest
import trimesh

from nemo.mesh import save_mesh
from nemo.tables import write_table


def digest(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture
def sphere_tables(tmp_path):
    """A sphere mesh with a layer table and a directors table made by the commands."""
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=20.0)
    mesh.units = "um"
    mesh_path = tmp_path / "mesh.ply"
    save_mesh(mesh, mesh_path)
    n = len(mesh.vertices)
    x = mesh.vertices[:, 0]
    layer = pd.DataFrame({"vertex": np.arange(n), "intensity": 100 + 50 * np.cos(x / 2.0)})
    layer_path = tmp_path / "layer.parquet"
    write_table(layer, layer_path, command="peel", mesh=str(mesh_path), n_vertices=n, unit="um")
    return mesh_path, layer_path


def test_output_equal_to_an_input_is_refused_and_the_input_kept(sphere_tables, run_cli, tmp_path):
    mesh_path, layer_path = sphere_tables
    before = digest(layer_path)
    code, _, err = run_cli("directors", mesh_path, layer_path, "--patch-radius", "6", "-o", layer_path)
    assert code == 2 and "is the input" in err and "Traceback" not in err
    assert digest(layer_path) == before
    dirs = tmp_path / "dirs.parquet"
    assert run_cli("directors", mesh_path, layer_path, "--patch-radius", "6", "-o", dirs)[0] == 0
    before = digest(dirs)
    code, _, err = run_cli("order", mesh_path, dirs, "--radius", "10", "-o", dirs)
    assert code == 2 and "nemo order: error: the output" in err
    assert digest(dirs) == before
    # the same file by another name (a relative path, ./) is the same input
    code, _, err = run_cli("order", mesh_path, dirs, "--radius", "10", "-o", tmp_path / "." / "dirs.parquet")
    assert code == 2 and digest(dirs) == before


@pytest.mark.parametrize("where", ["under_a_file", "is_a_folder"])
def test_unusable_output_path_is_a_message(sphere_tables, run_cli, tmp_path, where):
    mesh_path, _ = sphere_tables
    blocker = tmp_path / "plain.txt"
    blocker.write_text("x")
    out = blocker / "c.parquet" if where == "under_a_file" else tmp_path / "folder.parquet"
    if where == "is_a_folder":
        out.mkdir()
    code, _, err = run_cli("curvature", mesh_path, "--radius", "8", "-o", out)
    assert code == 2 and err.startswith("nemo curvature: error:") and "Traceback" not in err
    assert ("is a file" in err) if where == "under_a_file" else ("is a folder" in err)


def test_run_output_under_a_file_is_a_message(run_cli, tmp_path):
    blocker = tmp_path / "plain.txt"
    blocker.write_text("x")
    image = tmp_path / "missing.tif"
    code, _, err = run_cli("run", image, "-o", blocker)
    assert code == 2 and "Traceback" not in err


@pytest.mark.parametrize("command", [
    ["synth", "{tmp}/v.tif", "--seed", "-1"],
    ["curvature", "{mesh}", "--seed", "-1", "-o", "{tmp}/c.parquet"],
    ["directors", "{mesh}", "{layer}", "--seed", "-1", "-o", "{tmp}/d.parquet"],
    ["synth", "{tmp}/v.tif", "--seed", "4294967296"],
])
def test_seeds_outside_numpys_range_are_refused_by_the_parser(sphere_tables, tmp_path, command, capsys):
    from nemo.cli import main

    mesh_path, layer_path = sphere_tables
    argv = [a.format(tmp=tmp_path, mesh=mesh_path, layer=layer_path) for a in command]
    with pytest.raises(SystemExit) as exc:
        main(argv)
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "--seed" in err and "between 0 and" in err


def test_an_os_error_is_a_message(sphere_tables, run_cli, tmp_path, monkeypatch):
    """A refused read or write (permissions, full disk) names the file instead of a traceback."""
    import nemo.tables

    mesh_path, _ = sphere_tables

    def full_disk(*args, **kwargs):
        raise OSError(28, "No space left on device", str(tmp_path / "c.parquet"))

    monkeypatch.setattr(nemo.tables.pq, "write_table", full_disk)
    code, _, err = run_cli("curvature", mesh_path, "--radius", "8", "-o", tmp_path / "c.parquet")
    assert code == 2 and "No space left on device" in err and "c.parquet" in err
    assert not list(tmp_path.glob(".c.parquet.tmp*")), "the temporary file was left behind"


def test_library_argument_names_become_flags_or_config_keys():
    from nemo.cli import as_flags

    message = "use a larger `patch_radius` or `n_samples`"
    assert as_flags(message, "directors") == "use a larger --patch-radius or --samples"
    assert as_flags(message, "run") == "use a larger patch_radius or n_samples"  # nemo run: config keys
