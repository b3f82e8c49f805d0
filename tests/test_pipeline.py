"""``nemo run`` / :func:`nemo.pipeline.run_frame` and ``nemo defects`` on synthetic vesicles.

Ground truth: the defect positions and charges written by nemo.synthetic beside each image.
The default (fast) tests use small vesicles with parameters scaled to their size; the paper-scale
runs (R = 200 µm, the paper's parameters) are marked slow.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from nemo import layout
from nemo.defects import FIT_PER_AVERAGING
from nemo.errors import NemoError, NemoWarning
from nemo.pipeline import run_frame
from nemo.synthetic import write_vesicle
from nemo.tables import read_provenance, read_table


def truth_defects(truth: dict, t: int = 0, layer: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rec = [d for d in truth["defects"] if d["t"] == t and d["layer"] == layer]
    return np.array([[d["x"], d["y"], d["z"]] for d in rec]), np.array([d["charge"] for d in rec])


def assert_matches_truth(df, truth, max_error: float, charge_tol: float = 0.05) -> np.ndarray:
    """Every true defect found once, within max_error µm, right charge, nothing else."""
    pos, charges = truth_defects(truth)
    assert len(df) == len(pos), df
    d = np.linalg.norm(df[["x", "y", "z"]].to_numpy()[:, None] - pos[None], axis=2)
    k = d.argmin(axis=1)
    assert sorted(k) == list(range(len(pos)))
    err = d.min(axis=1)
    assert err.max() < max_error, err
    np.testing.assert_allclose(df["charge"], charges[k], atol=charge_tol)
    np.testing.assert_array_equal(df["charge_rounded"], charges[k])
    return err


#: Parameters for a small vesicle (R = 40 µm): the paper's ratios scaled to the size.
SMALL = {
    "mesh": {"step": 1},
    "directors": {"patch_radius": 6.0, "n_patches": 4000},
    "order": {"radius": 12.0},
}


@pytest.fixture(scope="module")
def small_vesicle(tmp_path_factory):
    path = tmp_path_factory.mktemp("ves") / "small.tif"
    truth = write_vesicle(path, radius=40.0, rotate=3, fibre_spacing=3.0, seed=1)
    return path, truth


@pytest.fixture(scope="module")
def small_run(small_vesicle, tmp_path_factory):
    from nemo import _log

    _log.configure(0)  # log to the current stderr (an earlier in-process CLI call may have swapped it)
    path, truth = small_vesicle
    out = tmp_path_factory.mktemp("run")
    summary = run_frame(path, out, SMALL)
    return out, summary, truth


def test_cli_run_config_errors(run_cli, tmp_path, small_vesicle):
    path, _ = small_vesicle
    cfg = tmp_path / "c.yaml"
    cfg.write_text("layers:\n  a:\n    range: [5, 0]\n")
    code, _, err = run_cli("run", path, "-o", tmp_path / "o", "--config", cfg)
    assert code == 2 and "layers.a.range" in err and "Traceback" not in err
    cfg.write_text("mesh:\n  stepum: 2\n")
    code, _, err = run_cli("run", path, "-o", tmp_path / "o", "--config", cfg)
    assert code == 2 and "'stepum' was unexpected" in err and "mesh" in err
    code, _, err = run_cli("run", tmp_path / "nothere.tif", "-o", tmp_path / "o")
    assert code == 2
    code, _, err = run_cli("run", path, "--config", cfg, "--dataset", "nope", "-o", tmp_path / "o")
    assert code == 2


def test_print_config_resolves_every_length_on_the_frame(run_cli, small_vesicle, small_run, tmp_path):
    """--print-config: the data-derived defaults as numbers, the given ones unchanged."""
    import yaml

    from nemo.mesh import load_mesh, mean_edge_length

    path, truth = small_vesicle
    h = mean_edge_length(load_mesh(small_run[0] / "mesh.inner.ply"))  # same mesh step (1 voxel)
    code, out, err = run_cli("run", path, "--print-config")
    assert code == 0, err
    cfg = yaml.safe_load(out)
    edge = cfg["resolved_per_layer"]["fibres"]["directors"]
    r_obj = truth["radius"]  # the inner wall of the shell: R = 40 µm
    assert edge["patch_radius"] == pytest.approx(max(0.1 * r_obj, 8 * h), rel=0.03)
    assert cfg["resolved_per_layer"]["fibres"]["order"]["radius"] == pytest.approx(2.5 * edge["patch_radius"])
    assert cfg["mesh"]["step"] == 1 and cfg["mesh"]["sigma"] > 0
    for surface in ("inner", "outer"):
        assert 0 < cfg["curvature"][surface]["radius"] <= 0.5 * (r_obj + 8)
    given = tmp_path / "g.yaml"
    given.write_text("directors:\n  patch_radius: 7.5\ncurvature: null\n")
    code, out, _ = run_cli("run", path, "--print-config", "--config", given)
    cfg = yaml.safe_load(out)
    assert cfg["resolved_per_layer"]["fibres"]["directors"]["patch_radius"] == 7.5
    assert cfg["resolved_per_layer"]["fibres"]["order"]["radius"] == 18.75 and cfg["curvature"] is None


# ------------------------------------------------------------------------------------------------
# end to end on a small vesicle


def test_run_frame_writes_every_file_and_finds_the_defects(small_run):
    out, summary, truth = small_run
    names = ["mesh.ply", "mesh.inner.ply", "mesh.outer.ply", "measure_inner.json", "measure_outer.json",
             "curvature_inner.parquet", "curvature_outer.parquet", "thickness.parquet", "summary.json"]
    names += [layout.layer_file(kind, "fibres") for kind in layout.LAYER_KINDS] + [layout.refined_file("fibres")]
    for name in names:
        assert (out / name).exists(), name
    saved = json.loads((out / layout.SUMMARY_JSON).read_text())
    check = saved["layers"]["fibres"]["euler_check"]
    assert check["closed"] and check["euler_characteristic"] == 2 and check["matches"]
    assert set(saved["timings_s"]) >= {"mesh", "peel", "directors", "order", "curvature", "defects"}
    df = read_table(out / layout.layer_file("defects", "fibres"), kind="defects")
    err = assert_matches_truth(df, truth, max_error=3.0)
    assert np.median(err) < 2.0  # measured 0.7-2.1 µm (fibre spacing 3 µm, mesh edge ≈ 0.9 µm)
    prov = read_provenance(out / layout.layer_file("defects", "fibres"))
    assert prov["euler_check"]["matches"] and prov["parameters"]["avg_radius"] == 12.0
    assert read_provenance(out / layout.layer_file("order", "fibres"))["parameters"]["radius"] == 12.0
    dprov = read_provenance(out / layout.layer_file("directors", "fibres"))["parameters"]
    assert dprov["patch_radius"] == 6.0 and dprov["n_patches"] == 4000 and dprov["pixel"] > 0
    # refinement directors: near the defects only (within the fit radius FIT_PER_AVERAGING x 12 µm)
    assert prov["parameters"]["fit_radius"] == pytest.approx(FIT_PER_AVERAGING * 12.0)
    extra = read_table(out / layout.refined_file("fibres"), kind="directors")
    assert prov["parameters"]["n_refine_directors"] == len(extra) > 0
    d = np.linalg.norm(extra[["x", "y", "z"]].to_numpy()[:, None] - df[["x", "y", "z"]].to_numpy()[None], axis=2)
    reach = d.min(axis=1)
    assert reach.max() <= FIT_PER_AVERAGING * 12.0 + 3.0  # refined positions moved at most a few µm
    assert np.quantile(reach, 0.95) > 0.75 * 12.0 + 1.0  # the fit's directors, beyond the former 0.75 x


def test_run_keeps_unrelated_files_and_removes_its_stale_ones(small_vesicle, tmp_path):
    """A second run with fewer stages leaves no stale result of the first, and nothing else goes."""
    path, _ = small_vesicle
    out = tmp_path / "o"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    (out / "curvature_outer.parquet").write_text("stale")
    run_frame(path, out, {**SMALL, "curvature": None, "thickness": None, "mesh": {"step": 2, "split": "centre"}})
    assert (out / "notes.txt").read_text() == "mine"
    assert not (out / "curvature_outer.parquet").exists() and not (out / "thickness.parquet").exists()


def test_cli_defects_on_run_outputs(run_cli, small_run, tmp_path):
    out, _, truth = small_run
    mesh, order = out / "mesh.inner.ply", out / layout.layer_file("order", "fibres")
    dirs = out / layout.layer_file("directors", "fibres")
    code, stdout, _ = run_cli("defects", mesh, order, dirs, "-o", tmp_path / "d.parquet")
    assert code == 0
    assert "Euler check: sum of charges" in stdout and "chi = 2: ok" in stdout
    df = read_table(tmp_path / "d.parquet", kind="defects")
    assert_matches_truth(df, truth, max_error=3.0)
    # the K term from the curvature table instead of angle defects
    code, stdout, _ = run_cli("defects", mesh, order, dirs, "--curvature", out / "curvature_inner.parquet",
                              "-o", tmp_path / "k.parquet")
    assert code == 0
    dk = read_table(tmp_path / "k.parquet", kind="defects")
    assert read_provenance(tmp_path / "k.parquet")["parameters"]["curvature_source"] == "table"
    assert_matches_truth(dk, truth, max_error=3.0)
    # without the K term the winding alone falls short by the enclosed curvature
    code, stdout, _ = run_cli("defects", mesh, order, dirs, "--no-curvature-correction",
                              "--contour-radius", "20", "-o", tmp_path / "n.parquet")
    assert code == 0
    dn = read_table(tmp_path / "n.parquet", kind="defects")
    assert len(dn) == 4
    r_over_R = 20.0 / truth["radius"]
    np.testing.assert_allclose(dn["charge"], dn["charge_winding"], atol=1e-12)
    np.testing.assert_allclose(dn["charge"] + dn["charge_curvature"], 0.5, atol=0.05)
    assert np.all(np.abs(dn["charge"] - (0.5 - (1 - math.cos(r_over_R)))) < 0.05)
    # a table computed on another mesh is refused with a clear message
    code, _, err = run_cli("defects", out / "mesh.ply", order, dirs, "-o", tmp_path / "x.parquet")
    assert code == 2 and "another mesh" in err
    code, _, err = run_cli("defects", mesh, dirs, order, "-o", tmp_path / "x.parquet")
    assert code == 2 and "lacks column" in err


def test_step_commands_reproduce_run_frame(run_cli, small_vesicle, small_run, tmp_path):
    """The step commands with the same options give run_frame's tables to the last bit."""
    import pandas as pd

    path, _ = small_vesicle
    out = small_run[0]
    mesh = tmp_path / "m.ply"
    assert run_cli("mesh", path, "-o", mesh, "--step", "1")[0] == 0
    assert run_cli("peel", path, tmp_path / "m.inner.ply", "-o", tmp_path / "l.parquet")[0] == 0
    assert run_cli("directors", tmp_path / "m.inner.ply", tmp_path / "l.parquet", "-o", tmp_path / "d.parquet",
                   "--patch-radius", "6", "--n-patches", "4000")[0] == 0
    assert run_cli("order", tmp_path / "m.inner.ply", tmp_path / "d.parquet", "-o", tmp_path / "o.parquet",
                   "--radius", "12")[0] == 0
    assert run_cli("defects", tmp_path / "m.inner.ply", tmp_path / "o.parquet", tmp_path / "d.parquet",
                   "--layer", tmp_path / "l.parquet", "-o", tmp_path / "f.parquet")[0] == 0
    for mine, theirs in (("l", "layer"), ("d", "directors"), ("o", "order"), ("f", "defects")):
        a = pd.read_parquet(tmp_path / f"{mine}.parquet")
        b = pd.read_parquet(out / layout.layer_file(theirs, "fibres"))
        pd.testing.assert_frame_equal(a, b)


# ------------------------------------------------------------------------------------------------
# the paper's vesicle (slow: ≈ 30 s each on 2 cores)


PAPER_CASES = {
    "default": {},
    "rotated": {"rotate": 11},
    "rotated-2": {"rotate": 12},
    "noise": {"rotate": 13, "noise": 20.0},
    "anisotropic": {"rotate": 14, "spacing": (2.0, 1.0, 1.0)},
    "five-one": {"defects": "five-one", "rotate": 15},
    "two-plus-one": {"defects": "two-plus-one", "rotate": 16},
}


#: Issue 5's headline bar: each +1/2 defect within 2 µm of the truth on the paper's vesicle, also
#: rotated, with noise and with dz = 2 dx; other configurations: better than the paper's 3.58 µm.
HEADLINE = {"default", "rotated", "rotated-2", "noise", "anisotropic"}


@pytest.mark.slow
@pytest.mark.parametrize("case", list(PAPER_CASES))
def test_paper_vesicle(case, tmp_path):
    """All defects found once, right charges (|raw − truth| ≤ 0.05), nothing else; every
    position within 2 µm (headline cases) or the paper's 3.58 µm. Measured (2 cores, loaded):
    headline cases 0.46–1.50 µm (systematic ≈ 1.2 µm towards the comet tail, see
    nemo.pipeline), five-one 0.65–1.95 µm, two-plus-one 0.6 µm; charges within 0.015."""
    path = tmp_path / "vesicle.tif"
    truth = write_vesicle(path, **PAPER_CASES[case])
    summary = run_frame(path, tmp_path / "out")  # every parameter derived from the data
    df = read_table(tmp_path / "out" / layout.layer_file("defects", "fibres"), kind="defects")
    err = assert_matches_truth(df, truth, max_error=2.0 if case in HEADLINE else 3.58)
    print(f"{case}: errors {np.round(err, 2)} µm, charges {np.round(df['charge'].to_numpy(), 3)}, "
          f"{summary['total_s']:.1f} s")
    assert summary["layers"]["fibres"]["euler_check"]["matches"]


def test_a_failed_run_leaves_the_previous_results_intact(small_vesicle, small_run, tmp_path, monkeypatch):
    """nemo run replaces its folder's files only on success: a failure mid-way changes nothing."""
    import shutil

    from nemo import stages
    from nemo.errors import NemoError

    out = tmp_path / "o"
    shutil.copytree(small_run[0], out)
    before = {p.name: p.read_bytes() for p in out.iterdir()}

    def broken(*args, **kwargs):
        raise NemoError("directors failed")

    monkeypatch.setattr(stages, "directors", broken)  # after mesh, curvature, thickness and peel
    with pytest.raises(NemoError, match="directors failed"):
        run_frame(small_vesicle[0], out, SMALL)
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert not [p for p in tmp_path.iterdir() if p.name != "o"], "a staging folder was left behind"


def test_run_frame_deconvolves_each_channel_by_its_own_psf(tmp_path):
    """One PSF per channel: the mesh (segmented channel 0) records channel 0's PSF and its channel,
    the layer of channel 1 channel 1's; a list without channel 1 is refused with the fix."""
    path = tmp_path / "two.tif"
    write_vesicle(path, radius=30.0, spacing=(2.0, 1.0, 1.0), channels=2, second_layer_depth=6.0,
                  second_layer_channel=1, seed=3)
    cfg = {"curvature": None, "thickness": None, "alignment": [],
           "layers": {"deep": {"surface": "inner", "range": [0, 4], "channels": [1]}}}
    run_frame(path, tmp_path / "out", cfg, c=1, psf=[[2.0, 1.0, 1.0], [3.0, 1.5, 1.5]])
    from nemo.mesh import load_mesh

    mesh = load_mesh(tmp_path / "out" / layout.MESH["inner"]).metadata["nemo_params"]
    assert mesh["deconvolution"]["psf"] == [2.0, 1.0, 1.0] and mesh["c"] == 0 and mesh["t"] == 0
    layer = read_provenance(tmp_path / "out" / layout.layer_file("layer", "deep"))["parameters"]
    assert layer["deconvolution"]["psf"] == [3.0, 1.5, 1.5] and layer["deconvolution"]["iterations"] > 0
    with pytest.raises(NemoError, match="not for channel 1"):
        run_frame(path, tmp_path / "bad", cfg, c=1, psf=[[2.0, 1.0, 1.0]])


def test_provenance_names_the_final_folder(small_run):
    """Tables record the mesh path where it ends up, not the staging folder."""
    out, _, _ = small_run
    prov = read_provenance(out / layout.layer_file("order", "fibres"))
    assert prov["mesh"] == str(out / layout.MESH["inner"])


def test_run_into_dot_and_a_symlinked_folder_leaves_no_staging_folder(small_run, small_vesicle, tmp_path,
                                                                      monkeypatch):
    """`-o .` stages beside the real folder; a symlink is followed; nothing is left behind."""
    import errno
    import os

    real = tmp_path / "real"
    real.mkdir()
    (tmp_path / "link").symlink_to(real)
    calls = []
    replace = os.replace

    def cross_device(src, dst):  # publishing the first file meets another file system (HPC scratch)
        if not calls and ".partial" in Path(src).parent.name and not Path(src).name.startswith("."):
            calls.append(src)
            raise OSError(errno.EXDEV, "Invalid cross-device link")
        return replace(src, dst)

    monkeypatch.setattr(os, "replace", cross_device)
    cfg = {**SMALL, "curvature": None, "thickness": None}
    run_frame(small_vesicle[0], tmp_path / "link", cfg)
    assert calls and (real / "summary.json").exists() and (real / "mesh.ply").exists()
    monkeypatch.chdir(real)
    run_frame(small_vesicle[0], ".", cfg)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link", "real"]
    assert not [p for p in real.iterdir() if p.name.startswith(".")]


def test_stale_removal_keeps_files_that_are_not_results(small_vesicle, tmp_path):
    out = tmp_path / "o"
    out.mkdir()
    (out / "directors_cells.csv").write_text("x,y,z,angle\n")  # a user's input, named like a table
    run_frame(small_vesicle[0], out, {**SMALL, "curvature": None, "thickness": None})
    assert (out / "directors_cells.csv").exists()


# ------------------------------------------------------- segmentations and user surfaces
@pytest.fixture
def ball_and_labels(tmp_path):
    """A blurred ball (R = 10 µm at (16, 16, 16)) and a label image: the ball is label 2, a
    second, larger ball elsewhere label 5 (so the mask picks the object, not the threshold)."""
    from scipy.ndimage import gaussian_filter

    from nemo.io import write_hyperstack

    z, y, x = np.indices((32, 32, 64))
    ball = np.sqrt((x - 16) ** 2 + (y - 16) ** 2 + (z - 16) ** 2) <= 10
    other = np.sqrt((x - 46) ** 2 + (y - 16) ** 2 + (z - 16) ** 2) <= 13
    image = gaussian_filter(200.0 * (ball | other), 1.0).astype(np.float32)
    labels = np.where(ball, 2, np.where(other, 5, 0)).astype(np.uint16)
    write_hyperstack(tmp_path / "img.tif", image, (1, 1, 1), axes="ZYX")
    write_hyperstack(tmp_path / "labels.tif", labels, (1, 1, 1), axes="ZYX")
    return tmp_path


def _morphology_config(path, **dataset):
    return {"datasets": {"d": {"path": str(path), **dataset}}, "layers": {}, "curvature": None,
            "thickness": None, "mesh": {"split": "none"}}


def test_a_killed_runs_staging_folder_is_removed_by_the_next_run(tmp_path):
    from nemo.pipeline import _staging_folder

    final = tmp_path / "out"
    dead = tmp_path / ".out.partial999999999"  # no such process
    mine = tmp_path / f".other.partial{os.getpid()}"  # another output's folder: not this run's business
    for folder in (dead, mine):
        folder.mkdir()
    stage = _staging_folder(final)
    assert stage.is_dir() and not dead.exists() and mine.exists()


def test_run_frame_refuses_a_dataset_selection_the_image_lacks(ball_and_labels):
    """As the workflow does: `c: [3]` on a one-channel image is a config error, not channel 0."""
    d = ball_and_labels
    with pytest.raises(NemoError, match=r"datasets\.d\.c.*\[3\] out of range"):
        run_frame(None, d / "out", _morphology_config(d / "img.tif", c=[3]), dataset="d")
    assert not (d / "out").exists()


def test_run_frame_with_a_label_mask_analyses_the_chosen_object(ball_and_labels):
    d = ball_and_labels
    cfg = _morphology_config(d / "img.tif", mask=str(d / "labels.tif"), mask_labels=[2])
    run_frame(None, d / "out", cfg, dataset="d")
    m = json.loads((d / "out" / "measure_whole.json").read_text())
    assert m["area"] == pytest.approx(4 * np.pi * 10.5**2, rel=0.08)  # the labelled voxels' hull
    np.testing.assert_allclose(read_mesh_centre(d / "out" / "mesh.ply"), (16, 16, 16), atol=0.2)


def test_touching_labels_meshed_as_one_fail_the_quality_control(tmp_path):
    """Two touching droplets labelled 1 and 2 with every label as object (keep: largest) are one
    surface, their area and volume together: the frame is flagged (it passed, only a log warning
    said so: an independent review); with mesh.keep: all they are two objects and pass."""
    from scipy.ndimage import gaussian_filter

    from nemo.io import write_hyperstack

    z, y, x = np.indices((32, 32, 56))
    first = np.sqrt((x - 16) ** 2 + (y - 16) ** 2 + (z - 16) ** 2) <= 10
    second = np.sqrt((x - 37) ** 2 + (y - 16) ** 2 + (z - 16) ** 2) <= 11
    labels = np.where(first, 1, np.where(second, 2, 0)).astype(np.uint16)  # touching at x = 26
    write_hyperstack(tmp_path / "img.tif", gaussian_filter(200.0 * (labels > 0), 1.0).astype(np.float32), (1, 1, 1),
                     axes="ZYX")
    write_hyperstack(tmp_path / "labels.tif", labels, (1, 1, 1), axes="ZYX")
    cfg = _morphology_config(tmp_path / "img.tif", mask=str(tmp_path / "labels.tif"))
    with pytest.warns(NemoWarning, match="labels touch"):
        summary = run_frame(None, tmp_path / "out", cfg, dataset="d")
    assert summary["mesh"]["regions"] == [2] and summary["mesh"]["n_objects"] == 1
    [row] = summary["qc"]
    assert not row["qc_pass"] and "2 large labels of the mask that touch" in row["qc_flags"]
    summary = run_frame(None, tmp_path / "all", {**cfg, "mesh": {"split": "none", "keep": "all"}}, dataset="d")
    assert summary["mesh"]["n_objects"] == 2 and all(q["qc_pass"] for q in summary["qc"]), summary["qc"]


def test_run_frame_of_a_droplet_at_the_defaults(ball_and_labels, monkeypatch):
    """A filled ball (one wall) with the default split (auto): the run goes through; the inner and
    outer surfaces are the ball's, its curvature is 1/R (computed once for both), its thickness
    NaN (not flagged)."""
    from nemo import stages
    from nemo.mesh import load_mesh

    d = ball_and_labels
    cfg = {"datasets": {"d": {"path": str(d / "img.tif"), "mask": str(d / "labels.tif"), "mask_labels": [2]}},
           "layers": {}}
    calls = []
    curvature = stages.curvature
    monkeypatch.setattr(stages, "curvature", lambda *a, **k: calls.append(1) or curvature(*a, **k))
    summary = run_frame(None, d / "out", cfg, dataset="d")
    assert len(calls) == 1  # inner and outer are one surface
    pd.testing.assert_frame_equal(read_table(d / "out" / "curvature_inner.parquet"),
                                  read_table(d / "out" / "curvature_outer.parquet"))
    assert summary["mesh"]["split"] == "auto" and summary["mesh"]["walls"] == 1
    inner, outer = (load_mesh(d / "out" / f"mesh.{name}.ply") for name in ("inner", "outer"))
    np.testing.assert_array_equal(inner.vertices, outer.vertices)
    m = json.loads((d / "out" / "measure_inner.json").read_text())
    assert m["walls"] == 1 and m["euler_characteristic"] == 2
    assert read_table(d / "out" / "thickness.parquet")["thickness"].isna().all()
    H = read_table(d / "out" / "curvature_outer.parquet")["H"].to_numpy()
    assert np.nanmedian(H) * (3 * m["volume"] / (4 * math.pi)) ** (1 / 3) == pytest.approx(1.0, abs=0.03)


def test_a_layer_outward_from_a_droplet_fails_the_quality_control(ball_and_labels):
    """The default layer (0–5 µm outward from the inner wall) on an object of one wall samples the
    background: besides the warning, the frame's QC names it."""
    d = ball_and_labels
    cfg = {"datasets": {"d": {"path": str(d / "img.tif"), "mask": str(d / "labels.tif"), "mask_labels": [2]}}}
    with pytest.warns(NemoWarning):
        summary = run_frame(None, d / "out", cfg, dataset="d")
    row = next(q for q in summary["qc"] if q["layer"] == "fibres")
    assert not row["qc_pass"] and "the layer's range from its outline reaches outside it" in row["qc_flags"]


def test_a_hollow_torus_is_split_into_its_two_walls(tmp_path):
    """A hollow torus (ring 24 µm, tube wall 5–10 µm): seen from its centre both walls turn both
    ways, and split: auto read one wall, dropping the inner (an independent review); its walls are
    now the two tori, the thickness the wall's 5 µm."""
    from scipy.special import erf

    from nemo.io import write_hyperstack

    z, y, x = np.meshgrid(np.arange(-15, 16.0), np.arange(-39, 40.0), np.arange(-39, 40.0), indexing="ij")
    tube = np.hypot(np.hypot(x, y) - 24.0, z)
    image = 20.0 + 50.0 * (1 + erf(tube - 5.0)) * (1 + erf(10.0 - tube))
    write_hyperstack(tmp_path / "torus.tif", image.astype(np.float32), (1, 1, 1), axes="ZYX")
    cfg = {"datasets": {"d": {"path": str(tmp_path / "torus.tif")}}, "layers": {}, "curvature": None}
    summary = run_frame(None, tmp_path / "out", cfg, dataset="d")
    assert summary["mesh"]["walls"] == 2
    for wall, r in (("inner", 5.0), ("outer", 10.0)):
        m = json.loads((tmp_path / "out" / f"measure_{wall}.json").read_text())
        assert m["euler_characteristic"] == 0 and m["area"] == pytest.approx(4 * np.pi**2 * 24.0 * r, rel=0.04)
    thickness = read_table(tmp_path / "out" / "thickness.parquet")["thickness"]
    assert thickness.notna().mean() > 0.95 and thickness.median() == pytest.approx(5.0, abs=0.3)


def test_a_shell_cut_by_the_field_of_view_passes_where_its_rays_and_samples_leave_the_image(tmp_path):
    """A shell (R 16 / 22 µm) whose lower part the image's bottom plane cuts (its centre 6 µm above
    it): near the rim the thickness rays and the layer's samples leave the image (no thickness, no
    intensity there: ``beyond_view``) and the frame's quality control does not count them; the
    thickness in view is the wall's 6 µm."""
    from scipy.ndimage import gaussian_filter

    from nemo.io import write_hyperstack

    z, y, x = np.indices((36, 56, 56), dtype=float)
    r = np.sqrt((x - 27.5) ** 2 + (y - 27.5) ** 2 + (z - 6.0) ** 2)
    shell = (r >= 16.0) & (r <= 22.0)
    image = 20.0 + gaussian_filter(200.0 * shell, 1.0)
    write_hyperstack(tmp_path / "cap.tif", image.astype(np.float32), (1, 1, 1), axes="ZYX")
    cfg = {"datasets": {"d": {"path": str(tmp_path / "cap.tif")}}, "curvature": None,
           "layers": {"wall": {"surface": "inner", "range": [0.0, 5.0]},  # and one shifted by half the thickness:
                      "mid": {"surface": "inner", "range": [0.0, 1.0], "shift": 0.5}}}  # NaN where it is NaN
    summary = run_frame(None, tmp_path / "out", cfg, dataset="d")
    th = read_table(tmp_path / "out" / "thickness.parquet")
    assert th["beyond_view"].mean() > 0.05 and th["thickness"][~th["beyond_view"]].notna().all()
    assert th["thickness"].median() == pytest.approx(6.0, abs=0.3)
    for name in ("wall", "mid"):
        layer = read_table(tmp_path / "out" / f"layer_{name}.parquet")
        assert layer["beyond_view"].mean() > 0.05 and layer["intensity"][~layer["beyond_view"]].notna().all(), name
    assert len(summary["qc"]) == 2
    for qc in summary["qc"]:
        assert "thickness found" not in qc["qc_flags"] and "no layer intensity" not in qc["qc_flags"], qc["qc_flags"]


def test_run_frame_with_user_surfaces_per_time_point(ball_and_labels):
    import trimesh

    d = ball_and_labels
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=10_000.0)
    sphere.apply_translation((16_000, 16_000, 16_000))
    sphere.export(d / "surface_t0.stl")
    cfg = _morphology_config(d / "img.tif", surface_mesh=str(d / "surface_t{t}.stl"), mesh_unit="nm")
    summary = run_frame(None, d / "out", cfg, dataset="d")
    assert summary["mesh"]["source"].endswith("surface_t0.stl") and summary["mesh"]["mesh_unit"] == "nm"
    m = json.loads((d / "out" / "measure_whole.json").read_text())
    assert m["area"] == pytest.approx(sphere.area * 1e-6, rel=1e-4)
    from nemo.pipeline import resolved_config

    printed = resolved_config(None, cfg, dataset="d")  # --print-config meshes the frame the same way
    assert printed["mesh"]["source"].endswith("surface_t0.stl") and printed["mesh"]["mesh_unit"] == "nm"
    cfg["datasets"]["d"]["mesh_unit"] = None
    with pytest.raises(NemoError, match="does not say in which unit"):
        run_frame(None, d / "out2", cfg, dataset="d")


def read_mesh_centre(path):
    from nemo.mesh import load_mesh

    return load_mesh(path).vertices.mean(axis=0)


# ----------------------------------------------------------------------------- several objects
@pytest.fixture(scope="module")
def two_vesicles(tmp_path_factory, write_two_vesicles):
    """Two synthetic vesicles side by side (R = 30 and 22 µm, 1.5 µm voxels, the second turned at
    random), analysed with ``mesh.keep: all``; truth: each one's defects in the joint image."""
    d = tmp_path_factory.mktemp("two_vesicles")
    truth = write_two_vesicles(d / "two.tif")
    config = {"mesh": {"keep": "all", "split": "centre"},
              "layers": {"film": {"surface": "inner", "range": [0, 4]}}}
    summary = run_frame(d / "two.tif", d / "out", config=config)
    return {"dir": d, "out": d / "out", "truth": truth, "config": config, "summary": summary}


def test_run_frame_analyses_each_object_on_its_own(two_vesicles):
    from nemo.summary import collect_defects, frame_summary

    out, truth = two_vesicles["out"], two_vesicles["truth"]
    defects = read_table(out / "defects_film.parquet", "defects")
    for label, true in enumerate(truth):  # object 0 is the larger vesicle
        found = defects[defects["object"] == label]
        d = np.linalg.norm(found[["x", "y", "z"]].to_numpy()[:, None] - true["defects"][None], axis=2)
        assert len(found) == 4 and sorted(d.argmin(axis=1)) == [0, 1, 2, 3], d
        assert d.min(axis=1).max() < 3.0, d.min(axis=1)  # 1.5 µm voxels
        np.testing.assert_allclose(found["charge"], 0.5, atol=0.05)
    order = read_table(out / "order_film.parquet", "order")
    directors = read_table(out / "directors_film.parquet", "directors")
    assert set(order["object"]) == set(directors["object"]) == {0, 1}
    params = read_provenance(out / "directors_film.parquet")["parameters"]
    radii = [p["patch_radius"] for p in params["objects"]]
    assert radii[1] < radii[0]  # each object's patches follow its own size
    rec = {"t": 0, "c": 0, "layer": "film", "surface": "inner", "measure": out / "measure_inner.json",
           "curvature": out / "curvature_inner.parquet", "thickness": out / "thickness.parquet",
           "layer_table": out / "layer_film.parquet", "directors": out / "directors_film.parquet",
           "order": out / "order_film.parquet", "defects": out / "defects_film.parquet"}
    frames = frame_summary([rec])
    assert frames["object"].tolist() == [0, 1] and (frames["n_objects"] == 2).all()
    assert frames["qc_pass"].all(), frames["qc_flags"].tolist()
    qc = json.loads((out / "summary.json").read_text())["qc"]  # nemo run's own verdict: the same rows
    assert [(q["layer"], q["object"], q["qc_pass"]) for q in qc] == [("film", 0, True), ("film", 1, True)]
    np.testing.assert_allclose(frames["charge_sum"], 2.0, atol=0.05)  # χ = 2 for each vesicle
    np.testing.assert_allclose(frames["euler_characteristic"], 2)
    for (_, row), true, radius in zip(frames.iterrows(), truth, (30, 22)):
        np.testing.assert_allclose(row[["centre_x", "centre_y", "centre_z"]].to_numpy(float), true["centre"], atol=1.0)
        assert row["H_fit_mean"] == pytest.approx(1 / radius, rel=0.05)
        assert row["thickness_median"] == pytest.approx(10.0, abs=1.5)
    assert collect_defects([rec])["object"].tolist() == defects["object"].tolist()


def test_step_commands_reproduce_the_per_object_run(run_cli, two_vesicles, tmp_path):
    """nemo order and nemo defects on the run's labelled mesh give the run's numbers."""
    out = two_vesicles["out"]
    code, _, err = run_cli("order", str(out / "mesh.inner.ply"), str(out / "directors_film.parquet"),
                           "-o", str(tmp_path / "order.parquet"))
    assert code == 0, err
    np.testing.assert_allclose(read_table(tmp_path / "order.parquet", "order")["S"],
                               read_table(out / "order_film.parquet", "order")["S"])
    code, _, err = run_cli("defects", str(out / "mesh.inner.ply"), str(tmp_path / "order.parquet"),
                           str(out / "directors_film.parquet"), "--layer", str(out / "layer_film.parquet"),
                           "-o", str(tmp_path / "defects.parquet"))
    assert code == 0, err
    mine, run = read_table(tmp_path / "defects.parquet", "defects"), read_table(out / "defects_film.parquet", "defects")
    np.testing.assert_allclose(mine[["x", "y", "z", "charge"]], run[["x", "y", "z", "charge"]])
    assert mine["object"].tolist() == run["object"].tolist()


def test_print_config_lists_each_objects_lengths(two_vesicles):
    """--print-config with keep: all: every object's data-derived lengths, as the run used them."""
    from nemo.pipeline import resolved_config

    out = two_vesicles["out"]
    cfg = resolved_config(two_vesicles["dir"] / "two.tif", two_vesicles["config"])
    per_object = cfg["resolved_per_layer"]["film"]["objects"]
    assert [o["object"] for o in per_object] == [0, 1]
    used = read_provenance(out / "order_film.parquet")["parameters"]["objects"]
    np.testing.assert_allclose([o["order"]["radius"] for o in per_object], [o["radius"] for o in used])
    assert per_object[1]["order"]["radius"] < per_object[0]["order"]["radius"]
