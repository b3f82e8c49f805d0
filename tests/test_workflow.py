"""The Snakemake workflow: dry runs, parse-time config errors, the real default run, reruns,
tracking through the workflow, a multi-frame two-channel hyperstack, --keep-going, SLURM.

Every run happens in a temporary working directory (``snakemake -s Snakefile -d TMP``) so the
repository's own results/ is never touched.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from conftest import snakemake_env

ROOT = Path(__file__).resolve().parents[1]
SNAKEFILE = ROOT / "Snakefile"
DEFAULT_CONFIG = ROOT / "config" / "config.yaml"
SNAKEMAKE = [sys.executable, "-m", "snakemake"]

FRAMES_COLUMNS = {"t", "c", "layer", "area", "volume", "S_mean", "thickness_mean", "H_mean",
                  "K_mean", "n_defects", "charge_sum"}
DEFECTS_COLUMNS = {"t", "c", "layer", "x", "y", "z", "charge", "charge_rounded", "S", "track_id"}
TRACKS_COLUMNS = {"track_id", "layer", "charge", "first_t", "last_t", "length", "mean_speed"}


# ----------------------------------------------------------------------------- helpers
def smk(workdir: Path, *args, check: bool = True, timeout: float = 1200, slurm: bool = False) -> subprocess.CompletedProcess:
    """Run Snakemake on the NEMO Snakefile in ``workdir`` (``slurm``: with SLURM's own ``scontrol``,
    :func:`conftest.snakemake_env`)."""
    cmd = [*SNAKEMAKE, "-s", str(SNAKEFILE), "-d", str(workdir), *map(str, args)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=snakemake_env(slurm))
    if check and proc.returncode != 0:
        raise AssertionError(f"snakemake {' '.join(map(str, args))} failed ({proc.returncode}):\n"
                             f"{proc.stdout[-4000:]}\n{proc.stderr[-6000:]}")
    return proc


def job_counts(proc: subprocess.CompletedProcess) -> dict[str, int]:
    """Jobs per rule from a (dry) run's 'Job stats' table; {} when nothing is to be done."""
    text = proc.stdout + proc.stderr
    if "Job stats:" not in text:
        assert "Nothing to be done" in text, text[-3000:]
        return {}
    table = text.split("Job stats:", 1)[1].split("total", 1)[0]
    counts = {}
    for line in table.splitlines():
        m = re.match(r"^(\S+)\s+(\d+)\s*$", line.strip())
        if m:
            counts[m.group(1)] = int(m.group(2))
    return counts


def write_config(path: Path, cfg: dict) -> Path:
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return path


def default_config() -> dict:
    return yaml.safe_load(DEFAULT_CONFIG.read_text())


def read_truth(path: Path) -> dict:
    return json.loads(Path(path).read_text())


def truth_defects(truth: dict) -> pd.DataFrame:
    return pd.DataFrame(truth["defects"])


# ----------------------------------------------------------------------------- dry runs and config errors
def test_dry_run_default_config(tmp_path):
    proc = smk(tmp_path, "-n", "--cores", "2")
    counts = job_counts(proc)
    cfg = default_config()
    frames = cfg["datasets"]["demo"]["synthetic"]["frames"]
    n_layers = len(cfg["layers"])
    assert counts["synth_demo"] == 1
    assert counts["mesh"] == frames
    for rule in ("peel", "directors", "order", "defects"):
        assert counts[rule] == frames * n_layers, rule
    assert counts["align"] == frames * len(cfg["alignment"])
    assert counts["track"] == counts["aggregate_frames"] == counts["aggregate_defects"] == 1
    assert not (tmp_path / "results").exists(), "a dry run must not write results"


def test_default_profile_paths_exist():
    # both documented locations of the profiles work (profiles/ points to workflow/profiles/)
    for name in ("local", "slurm"):
        top = ROOT / "profiles" / name / "config.yaml"
        assert top.exists() and top.resolve() == (ROOT / "workflow/profiles" / name / "config.yaml").resolve()
        prof = yaml.safe_load(top.read_text())
        assert isinstance(prof, dict)
    assert yaml.safe_load((ROOT / "profiles/slurm/config.yaml").read_text())["executor"] == "slurm"


@pytest.fixture(scope="module")
def tiny_stack(tmp_path_factory):
    """A real (tiny) 2-frame, 1-channel hyperstack for header checks at parse time."""
    from nemo.io import write_hyperstack

    d = tmp_path_factory.mktemp("stack")
    data = np.zeros((2, 8, 1, 16, 16), dtype=np.uint8)
    write_hyperstack(d / "stack.tif", data, spacing=(1, 1, 1), axes="TZCYX")
    write_hyperstack(d / "mask_7_planes.tif", np.ones((7, 16, 16), np.uint8), spacing=(1, 1, 1), axes="ZYX")
    write_hyperstack(d / "stack_3t.tif", np.zeros((3, 8, 1, 16, 16), np.uint8), spacing=(1, 1, 1), axes="TZCYX")
    write_hyperstack(d / "mask_2t.tif", np.ones((2, 8, 16, 16), np.uint8), spacing=(1, 1, 1), axes="TZYX")
    write_hyperstack(d / "mask_2c.tif", np.ones((8, 2, 16, 16), np.uint8), spacing=(1, 1, 1), axes="ZCYX")
    return d / "stack.tif"


def _bad(cfg_edit, tiny_stack=None):
    cfg = default_config()
    if tiny_stack is not None:
        cfg["datasets"] = {"cells": {"path": str(tiny_stack)}}
    cfg_edit(cfg)
    return cfg


BAD_CONFIGS = {
    "order.radius": (lambda c: c["order"].update(radius=-5), "order.radius"),
    "layer range": (lambda c: c["layers"]["apical"].update(range=[10, 6]), "layers.apical.range"),
    "unknown layer": (lambda c: c.update(alignment=[["basal", "nope"]]), "alignment.0"),
    "typo key": (lambda c: c["mesh"].update(stepp=2), "mesh"),
    "threshold": (lambda c: c["mesh"].update(threshold="median"), "mesh.threshold"),
    "split none": (lambda c: c["mesh"].update(split="none"), "mesh.split"),
    "negative seed": (lambda c: c["directors"].update(seed=-1), "directors.seed"),
    "missing file": (lambda c: c["datasets"]["demo"].update(path="nothere.tif", synthetic=None),
                     "datasets.demo.path"),
    "shift": (lambda c: c["layers"]["apical"].update(shift=0.2, surface="outer"), "layers.apical.shift"),
    "no datasets": (lambda c: c.update(datasets={}), "datasets"),
}


@pytest.mark.parametrize("name", list(BAD_CONFIGS))
def test_bad_config_fails_before_any_job_naming_the_key(tmp_path, name):
    edit, key = BAD_CONFIGS[name]
    cfg = write_config(tmp_path / "bad.yaml", _bad(edit))
    proc = smk(tmp_path, "--cores", "1", "--configfile", cfg, check=False)
    assert proc.returncode != 0
    err = proc.stderr
    assert f"config key '{key}" in err, err[-2000:]
    assert "Traceback" not in err
    assert not (tmp_path / "results").exists() and not (tmp_path / "resources").exists()


@pytest.mark.parametrize(
    "edit, key, words",
    [
        pytest.param(lambda d: d.update(c=[0, 1]), "datasets.cells.c", "1 channel", id="channel"),
        # the same check on the other axes: ≈ 26 s each, run with the slow tests (suite budget)
        pytest.param(lambda d: d.update(t=[0, 5]), "datasets.cells.t", "2 time points", id="time",
                     marks=pytest.mark.slow),
        pytest.param(lambda d: d.update(segment_channel=2), "datasets.cells.segment_channel", "channel 2",
                     id="segment-channel", marks=pytest.mark.slow),
        pytest.param(lambda d: d.update(mask=str(Path(d["path"]).with_name("mask_7_planes.tif"))),
                     "datasets.cells.mask", "(7, 16, 16) but the image has (8, 16, 16)", id="mask-shape",
                     marks=pytest.mark.slow),
        # a mask of 2 time points for a movie of 3 (an independent review: it failed in the t = 2 job)
        pytest.param(lambda d: d.update(path=str(Path(d["path"]).with_name("stack_3t.tif")),
                                        mask=str(Path(d["path"]).with_name("mask_2t.tif"))),
                     "datasets.cells.mask", "has 2 time points, so none for the analysed time point(s) [2]",
                     id="mask-time-points", marks=pytest.mark.slow),
        pytest.param(lambda d: d.update(mask=str(Path(d["path"]).with_name("mask_2c.tif")), mask_channel=2),
                     "datasets.cells.mask_channel", "has 2 channels (0 to 1), none is 2", id="mask-channel",
                     marks=pytest.mark.slow),
    ],
)
def test_hyperstack_header_checked_at_parse_time(tmp_path, tiny_stack, edit, key, words):
    cfg = _bad(lambda c: edit(c["datasets"]["cells"]), tiny_stack)
    proc = smk(tmp_path, "-n", "--configfile", write_config(tmp_path / "c.yaml", cfg), check=False)
    assert proc.returncode != 0
    assert f"config key '{key}'" in proc.stderr and words in proc.stderr, proc.stderr[-2000:]
    # the same file with valid keys parses and plans one mesh per frame
    ok = _bad(lambda c: None, tiny_stack)
    counts = job_counts(smk(tmp_path, "-n", "--configfile", write_config(tmp_path / "ok.yaml", ok)))
    assert counts["mesh"] == 2


def test_not_a_tiff_named_at_parse_time(tmp_path):
    (tmp_path / "junk.tif").write_text("not an image")
    cfg = _bad(lambda c: c.update(datasets={"x": {"path": str(tmp_path / "junk.tif")}}))
    proc = smk(tmp_path, "-n", "--configfile", write_config(tmp_path / "c.yaml", cfg), check=False)
    assert proc.returncode != 0 and "config key 'datasets.x.path'" in proc.stderr


# ----------------------------------------------------------------------------- the real default run
@pytest.fixture(scope="session")
def demo_run(tmp_path_factory):
    """`snakemake --cores 2` on the bundled default config, once per test run.

    Shared between pytest-xdist workers through a lock file in the common temporary folder,
    so `pytest -n 2` does not run the workflow twice.
    """
    import fcntl

    base = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        base = base.parent
    work = base / "demo-run"
    with open(base / "demo-run.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (work / "done").exists():
            shutil.rmtree(work, ignore_errors=True)
            work.mkdir()
            start = time.perf_counter()
            smk(work, "--cores", "2")
            (work / "done").write_text(f"{time.perf_counter() - start:.1f}")
        fcntl.flock(lock, fcntl.LOCK_UN)
    print(f"\ndefault workflow: {(work / 'done').read_text()} s with --cores 2")
    return work


def _summary(work: Path, name: str, dataset: str = "demo") -> pd.DataFrame:
    from nemo.tables import read_table

    return read_table(work / "results" / dataset / "summary" / f"{name}.parquet")


# Systematic bias of the wall placement in the demo (2 µm voxels, Yen threshold on the blurred
# shell): the segmented wall is too thick, both walls are displaced away from the shell's
# mid-surface (inner wall at r = 99.89 µm instead of 100, outer at 110.53 instead of 110,
# from the volumes), so the thickness is 10.65 µm, not the generator's 10 (10.84 before the
# marching-cubes vertices were snapped onto the cubic-spline iso-surface). An open issue
# (walls biased outward): test_default_run_thickness_is_unbiased below is its strict xfail.
# The bias shrinks with the voxel size (benchmarks/README.md: 10.26 at the paper's 2 µm step on
# R 200, 10.03 at 1 µm voxels). `mesh.refine: true` (sub-voxel walls, off by default) gave
# 10.56 here before the snap and 10.02 on the paper's vesicle (docs/validation.md).
DEMO_THICKNESS_BIAS = 0.65  # µm, measured: 0.646 - 0.656 over the 3 frames


def test_default_run_summaries(demo_run):
    cfg = default_config()
    frames = cfg["datasets"]["demo"]["synthetic"]["frames"]
    f = _summary(demo_run, "frames")
    assert FRAMES_COLUMNS <= set(f.columns)
    assert len(f) == frames * len(cfg["layers"])
    R = cfg["datasets"]["demo"]["synthetic"]["radius"]
    print("\ndemo frames:\n", f[["t", "layer", "area", "volume", "H_mean", "thickness_mean", "S_mean",
                                  "charge_sum"]].to_string())
    # inner wall of the synthetic shell: a sphere of radius R (measured relative errors: area
    # -0.10 %, volume -0.64 % = the inner wall 0.21 µm inside R, H +0.19 %)
    assert np.allclose(f["area"], 4 * np.pi * R**2, rtol=0.003)
    assert np.allclose(f["volume"], 4 / 3 * np.pi * R**3, rtol=0.01)
    assert np.allclose(f["H_mean"], 1 / R, rtol=0.005)
    shell = read_truth(demo_run / "resources/demo/vesicle.truth.json")["shell_thickness"]
    assert shell == 10.0
    # the known outward bias of the walls (see DEMO_THICKNESS_BIAS), pinned within 0.05 µm so
    # that any change of it, better or worse, is seen
    np.testing.assert_allclose(f["thickness_mean"] - shell, DEMO_THICKNESS_BIAS, atol=0.05)
    # Σ charge = χ = 2 on the closed vesicle, 4 × +½ in every frame and layer (measured: 2.002 - 2.006)
    assert (f["n_defects"] == 4).all(), f[["t", "layer", "n_defects"]]
    assert np.allclose(f["charge_sum"], 2.0, atol=0.01)
    # ordered field away from the 4 defect cores (measured S_mean 0.917 - 0.919)
    assert (f["S_mean"] > 0.9).all(), f["S_mean"]


@pytest.mark.xfail(strict=True, reason="open issue: the walls of the segmented shell are biased outward "
                                       "(thickness 10.65 µm for a 10 µm shell at 2 µm voxels)")
def test_default_run_thickness_is_unbiased(demo_run):
    f = _summary(demo_run, "frames")
    shell = read_truth(demo_run / "resources/demo/vesicle.truth.json")["shell_thickness"]
    assert np.abs(f["thickness_mean"] - shell).max() <= 0.25


def _truth_speed(truth: dict, defect: pd.Series) -> float:
    """Speed (µm per frame) of a true defect from the generator's motion: the texture turns
    rigidly by ``frame_rotation`` degrees per frame about ``frame_axis`` through the centre, so a
    defect at unit direction u on the sphere of radius r moves by the chord
    2 r sin(θ/2) |u × axis| every frame."""
    p = truth["parameters"]
    axis = np.asarray(p["frame_axis"], float)
    axis /= np.linalg.norm(axis)
    r = np.linalg.norm(defect[["x", "y", "z"]].to_numpy(float) - np.asarray(truth["centre"]))
    u = defect[["ux", "uy", "uz"]].to_numpy(float)
    return float(2 * r * np.sin(np.radians(p["frame_rotation"]) / 2) * np.linalg.norm(np.cross(u, axis)))


def test_default_run_defects_match_truth_and_track(demo_run):
    truth = read_truth(demo_run / "resources/demo/vesicle.truth.json")
    td = truth_defects(truth)
    layer_index = {"basal": 0, "apical": 1}  # truth layers: first (depth 2.5 µm), second (8.5 µm)
    d = _summary(demo_run, "defects")
    assert DEFECTS_COLUMNS <= set(d.columns)
    assert (d["charge_rounded"] == 0.5).all()
    errors = []
    # every detected defect lies close to a true defect of its frame and layer (2 µm voxels)
    for (t, layer), group in d.groupby(["t", "layer"]):
        true = td[(td["t"] == t) & (td["layer"] == layer_index[layer])][["x", "y", "z"]].to_numpy()
        dist = np.linalg.norm(group[["x", "y", "z"]].to_numpy()[:, None] - true[None], axis=2)
        # measured (session 37): 0.58 - 2.67 µm, mean 1.28 µm (2 µm voxels; with the former fit radius
        # 0.30 - 1.81, mean 1.16: the basal layer's defects worse, the apical's better); the 3 µm bound
        assert dist.min(axis=1).max() < 3.0, (t, layer, dist.min(axis=1))
        assert len(set(dist.argmin(axis=1))) == 4  # each true defect found once
        errors.extend(dist.min(axis=1))
    assert np.mean(errors) < 1.6, np.mean(errors)
    tr = _summary(demo_run, "tracks")
    assert TRACKS_COLUMNS <= set(tr.columns)
    frames = truth["shape"]["T"]
    # one track per true defect and layer, over all frames, with the right charge
    assert len(tr) == 4 * 2
    assert (tr["first_t"] == 0).all() and (tr["last_t"] == frames - 1).all()
    assert (tr["charge_rounded"] == 0.5).all() and (tr["length"] == frames).all()
    # the truth speed from the generator's motion (demo: 6° per frame about y, on R = 100 µm)
    p = truth["parameters"]
    assert p["frame_rotation"] == 6.0 and p["frame_axis"] == [0.0, 1.0, 0.0]
    linked = d.sort_values("t")
    offsets, speeds = [], []
    for _, track in tr.iterrows():
        rows = linked[linked["track_id"] == track["track_id"]]
        assert rows["layer"].nunique() == 1 and rows["t"].tolist() == list(range(frames))
        # the track follows one true defect: same nearest truth in every frame, and its speed
        true = td[td["layer"] == layer_index[track["layer"]]]
        ids, steps = [], []
        for _, row in rows.iterrows():
            cand = true[true["t"] == row["t"]]
            k = np.linalg.norm(cand[["x", "y", "z"]].to_numpy() - row[["x", "y", "z"]].to_numpy(float), axis=1).argmin()
            ids.append(k)
            steps.append(cand[["x", "y", "z"]].to_numpy()[k])
        assert len(set(ids)) == 1, ids
        true_speed = _truth_speed(truth, true[true["t"] == 0].iloc[ids[0]])
        speeds.append(true_speed)
        # the generator's truth table moves its defects by exactly that chord per frame
        np.testing.assert_allclose(np.linalg.norm(np.diff(np.array(steps), axis=0), axis=1), true_speed,
                                   rtol=1e-9)
        # measured: |mean_speed − truth| 0.005 - 0.90 µm/frame (truth 8.546) from the 1–2 µm
        # localisation scatter over 2 steps
        assert abs(track["mean_speed"] - true_speed) < 1.0, (track["mean_speed"], true_speed)
        offsets.append(track["mean_speed"] - true_speed)
    # no systematic speed bias over the 8 tracks (measured mean offset +0.08 µm/frame)
    print(f"\ntrack speed − truth: {np.round(offsets, 3)}, truth {np.round(speeds, 3)}; "
          f"localisation error mean {np.mean(errors):.2f}, max {np.max(errors):.2f} µm")
    assert abs(np.mean(offsets)) < 0.15, offsets


def test_default_run_alignment_orthogonal_layers(demo_run):
    a = _summary(demo_run, "alignment")
    assert set(a["layer_a"]) == {"basal"} and set(a["layer_b"]) == {"apical"}
    # second layer rotated by 90°: c = cos 2·90° = −1 (measured c_mean −0.945 to −0.947); the
    # averaged directors' alignment is closer to it (noise does not pull it towards 0)
    assert (a["c_mean"] <= -0.93).all(), a
    assert (a["c_avg_mean"] <= a["c_mean"]).all() and (a["c_avg_mean"] <= -0.97).all(), a


def test_nothing_reruns_after_a_complete_run(demo_run, tmp_path):
    assert job_counts(smk(demo_run, "-n", "--nolock", "--cores", "2")) == {}
    # the same config with its keys in another order is the same config
    shuffled = tmp_path / "sorted.yaml"
    shuffled.write_text(yaml.safe_dump(default_config(), sort_keys=True))
    assert job_counts(smk(demo_run, "-n", "--nolock", "--configfile", shuffled)) == {}


def _rerun_counts(work: Path, tmp_path: Path, edit) -> dict[str, int]:
    cfg = default_config()
    edit(cfg)
    return job_counts(smk(work, "-n", "--nolock", "--cores", "2", "--configfile",
                          write_config(tmp_path / "c.yaml", cfg)))


def test_changing_the_averaging_radius_reruns_only_order_and_below(demo_run, tmp_path):
    counts = _rerun_counts(demo_run, tmp_path, lambda c: c["order"].update(radius=c["order"]["radius"] + 5))
    n = default_config()["datasets"]["demo"]["synthetic"]["frames"] * 2
    assert counts.pop("order") == n and counts.pop("defects") == n
    assert counts.pop("align") == n // 2  # c_avg reads both layers' order tables
    # the per-frame renders of the first and last frame (report.frames: ends) and the report tables too
    assert set(counts) <= {"aggregate_frames", "aggregate_defects", "aggregate_alignment", "track", "render_summary",
                           "render", "report_tables", "report_config", "all"}, counts


def test_changing_one_layer_reruns_that_layer_only(demo_run, tmp_path):
    counts = _rerun_counts(demo_run, tmp_path, lambda c: c["layers"]["apical"].update(range=[6, 11]))
    frames = default_config()["datasets"]["demo"]["synthetic"]["frames"]
    for rule in ("peel", "directors", "order", "defects", "align"):
        assert counts.get(rule) == frames, (rule, counts)
    assert not {"mesh", "synth_demo", "curvature", "thickness", "measure"} & set(counts), counts


def test_changing_tracking_reruns_only_tracking(demo_run, tmp_path):
    counts = _rerun_counts(demo_run, tmp_path, lambda c: c["tracking"].update(max_distance=30))
    # and what shows its tables: the summary figures, the report's table previews and configuration
    assert set(counts) <= {"track", "render_summary", "report_tables", "report_config", "all"}, counts
    assert counts["track"] == 1, counts


def test_nemo_run_with_the_workflow_config_gives_the_workflows_numbers(demo_run, tmp_path):
    """The same config file through snakemake and through `nemo run`: identical per-frame tables."""
    from nemo import layout
    from nemo.summary import ALIGN_COLUMNS
    from nemo.tables import read_table

    out = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-m", "nemo", "run", "--config", str(DEFAULT_CONFIG), "--dataset", "demo",
                           "--t", "1", "-o", str(out)], cwd=demo_run, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    frame = demo_run / "results" / "demo" / "t1" / "c0"
    cfg = default_config()
    for layer in cfg["layers"]:
        a = read_table(frame / layout.layer_file("defects", layer), "defects")
        b = read_table(out / layout.layer_file("defects", layer), "defects")
        assert len(a) == len(b) == 4
        np.testing.assert_allclose(a[["x", "y", "z"]], b[["x", "y", "z"]], atol=0.05)  # measured: 0.0
        np.testing.assert_array_equal(a["charge_rounded"], b["charge_rounded"])
        np.testing.assert_allclose(a["charge"], b["charge"], atol=1e-9)
        for kind in ("layer", "directors", "order"):
            pd.testing.assert_frame_equal(read_table(frame / layout.layer_file(kind, layer)),
                                          read_table(out / layout.layer_file(kind, layer)))
    for name in ("curvature_inner.parquet", "thickness.parquet", "align_basal_apical.parquet"):
        pd.testing.assert_frame_equal(read_table(frame / name), read_table(out / name))
    measure = "measure_inner.json"
    assert json.loads((frame / measure).read_text()) == json.loads((out / measure).read_text())
    # the same quality control: frames.parquet's rows of t1, and nemo run's summary and report
    frames = pd.read_parquet(demo_run / "results" / "demo" / "summary" / "frames.parquet")
    frames = frames[frames["t"] == 1].sort_values("layer")
    qc = sorted(json.loads((out / "summary.json").read_text())["qc"], key=lambda q: q["layer"])
    assert [q["layer"] for q in qc] == frames["layer"].tolist() and len(qc) == len(cfg["layers"])
    assert [q["qc_pass"] for q in qc] == frames["qc_pass"].tolist()
    assert [q["qc_flags"] for q in qc] == frames["qc_flags"].tolist()
    assert proc.stdout.count("quality control (layer ") == len(qc)
    # and the same alignment summary: alignment.parquet's row of t1 and summary.json's entry
    row = pd.read_parquet(demo_run / "results" / "demo" / "summary" / "alignment.parquet").query("t == 1").iloc[0]
    (pair,) = json.loads((out / "summary.json").read_text())["alignment"]
    assert set(pair) == set(ALIGN_COLUMNS)
    for key in ("t", "c", "layer_a", "layer_b", "n", "qc_pass", "qc_flags"):
        assert pair[key] == row[key], key
    for key in ("c_mean", "c_median", "c_std", "fraction_parallel", "fraction_orthogonal", "c_avg_mean", "c_avg_median"):
        assert pair[key] == pytest.approx(row[key], abs=1e-12), key
    assert f"alignment {pair['layer_a']} / {pair['layer_b']}: c_avg" in proc.stdout


def _droplets(path: Path, radii, spacing=(1.0, 0.42, 0.42)) -> None:
    """An uncalibrated time-lapse of a filled droplet (one wall) of growing radius."""
    import tifffile

    dz, dy, dx = spacing
    shape = (40, 72, 72)
    z, y, x = np.meshgrid(*(np.arange(n) * d for n, d in zip(shape, spacing)), indexing="ij")
    c = np.array([n * d for n, d in zip(shape, spacing)]) / 2
    frames = []
    for r in radii:
        dist = np.sqrt((z - c[0]) ** 2 + (y - c[1]) ** 2 + (x - c[2]) ** 2)
        frames.append((30 + 150 / (1 + np.exp((dist - r) / 0.4))).astype(np.uint8))
    tifffile.imwrite(path, np.stack(frames)[:, :, None], imagej=True, metadata={"axes": "TZCYX"})


@pytest.mark.slow  # > 1 min on 2 cores (the default suite stays under ~15 min)
def test_morphology_only_single_wall_uncalibrated_timelapse(tmp_path):
    """A droplet time-lapse with one wall, no layers, spacing from the config, the default split
    (auto) and thickness: every frame meshed, measured and summarised (area, volume, H of the
    analytic sphere); one wall, so inner = outer and no thickness (not flagged); nemo run on a
    frame gives the workflow's numbers."""
    from nemo.io import read_info
    from nemo.tables import read_table

    radii = [8.0, 9.0, 10.0]
    _droplets(tmp_path / "drops.tif", radii)
    assert not read_info(tmp_path / "drops.tif").calibrated
    cfg = {"datasets": {"drops": {"path": "drops.tif", "spacing": [1.0, 0.42, 0.42]}},
           "layers": {}, "alignment": [], "report": {"summary": False}}
    smk(tmp_path, "--cores", "2", "--configfile", write_config(tmp_path / "c.yaml", cfg))
    every = _summary(tmp_path, "frames", "drops")
    assert set(every["surface"]) == {"inner", "outer"} and (every["walls"] == 1).all()
    assert every["qc_pass"].all(), every["qc_flags"]
    f = every[every["surface"] == "outer"].reset_index(drop=True)
    inner = every[every["surface"] == "inner"].reset_index(drop=True)
    assert (inner["thickness_valid"] == 0).all()  # the thickness's rows: from inner, NaN everywhere
    proc = subprocess.run([sys.executable, "-m", "nemo", "run", "--config", "c.yaml", "--dataset", "drops",
                           "--t", "1", "-o", "run"], cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    frame = tmp_path / "results" / "drops" / "t1" / "c0"
    for name in ("measure_outer.json", "measure_inner.json"):
        assert json.loads((frame / name).read_text()) == json.loads((tmp_path / "run" / name).read_text())
    pd.testing.assert_frame_equal(read_table(frame / "curvature_outer.parquet"),
                                  read_table(tmp_path / "run" / "curvature_outer.parquet"))
    assert read_table(tmp_path / "run" / "thickness.parquet")["thickness"].isna().all()
    assert f["t"].tolist() == [0, 1, 2]
    R = np.array(radii)
    np.testing.assert_allclose(f["area"], 4 * np.pi * R**2, rtol=0.03)
    np.testing.assert_allclose(f["volume"], 4 / 3 * np.pi * R**3, rtol=0.03)
    np.testing.assert_allclose(f["H_fit_mean"] * R, 1.0, atol=0.05)
    assert (f["euler_characteristic"] == 2).all() and f["n_defects"].isna().all()
    assert len(_summary(tmp_path, "defects", "drops")) == 0 and len(_summary(tmp_path, "tracks", "drops")) == 0


@pytest.mark.slow  # a dry run ≈ 15 s; the default suite's budget
def test_an_uncalibrated_stack_is_named_at_parse_time(tmp_path):
    """The dry run says the analysis would run in pixels (Snakemake hides Python warnings)."""
    _droplets(tmp_path / "drops.tif", [8.0])
    cfg = {"datasets": {"drops": {"path": "drops.tif"}}, "mesh": {"split": "none"}, "layers": {},
           "thickness": None, "alignment": [], "report": {"summary": False}}
    proc = smk(tmp_path, "-n", "--configfile", write_config(tmp_path / "c.yaml", cfg))
    assert "drops.tif has no spatial calibration" in proc.stdout + proc.stderr


def test_one_config_holds_a_vesicle_and_a_droplet(tmp_path):
    """Per-dataset overrides: the droplet is single-walled and morphology-only, the vesicle not."""
    _droplets(tmp_path / "drops.tif", [8.0, 9.0])
    cfg = default_config()
    cfg["datasets"]["drops"] = {"path": "drops.tif", "spacing": [1.0, 0.42, 0.42],
                                "mesh": {"split": "none"}, "layers": {}, "alignment": [], "curvature": None,
                                "thickness": None}
    counts = job_counts(smk(tmp_path, "-n", "--configfile", write_config(tmp_path / "c.yaml", cfg)))
    frames = cfg["datasets"]["demo"]["synthetic"]["frames"]
    assert counts["mesh"] == frames and counts["mesh_single"] == 2
    assert counts["peel"] == frames * 2 and counts["measure"] == frames * 2 + 2
    assert counts["curvature"] == frames * 2  # the droplet's curvature: null
    assert counts["thickness"] == frames


def test_odd_dataset_paths_are_quoted(tmp_path):
    """A dataset folder with spaces, a quote and shell syntax: every job runs, nothing is executed."""
    folder = tmp_path / "my data's $(touch PWNED); echo"
    folder.mkdir()
    _droplets(folder / "drop s.tif", [8.0])
    cfg = {"datasets": {"drops": {"path": str(folder / "drop s.tif"), "spacing": [1.0, 0.42, 0.42]}},
           "mesh": {"split": "none"}, "layers": {}, "thickness": None, "curvature": None, "alignment": [],
           "report": {"summary": False}}
    smk(tmp_path, "--cores", "2", "--configfile", write_config(tmp_path / "c.yaml", cfg))
    f = _summary(tmp_path, "frames", "drops")
    np.testing.assert_allclose(f["area"], 4 * np.pi * 8.0**2, rtol=0.03)
    assert not list(tmp_path.rglob("PWNED")) and not Path("PWNED").exists()


@pytest.mark.slow  # ≈ 75 s (kills and reruns a real workflow); the suite's budget is ~15 min on 2 cores
def test_a_killed_run_recovers_with_unlock_and_rerun_incomplete(tmp_path):
    """kill -9 mid-run leaves a lock and incomplete files; the documented commands recover."""
    radii = [7.0, 7.5, 8.0, 8.5, 9.0, 9.5]
    _droplets(tmp_path / "drops.tif", radii)
    cfg = {"datasets": {"drops": {"path": "drops.tif", "spacing": [1.0, 0.42, 0.42]}},
           "mesh": {"split": "none"}, "layers": {}, "thickness": None, "alignment": [],
           "report": {"summary": False}}
    config = write_config(tmp_path / "c.yaml", cfg)
    cmd = [*SNAKEMAKE, "-s", str(SNAKEFILE), "-d", str(tmp_path), "--cores", "1", "--configfile", str(config)]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
                            env=snakemake_env())
    deadline = time.monotonic() + 300
    while not list(tmp_path.glob("results/drops/t*/c*/mesh.ply")) and time.monotonic() < deadline:
        time.sleep(0.2)
    time.sleep(1.0)  # the next job is running
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    again = smk(tmp_path, "--cores", "2", "--configfile", config, check=False)
    text = again.stdout + again.stderr
    # a stale lock ("Directory cannot be locked") and/or incomplete files, depending on the moment
    assert again.returncode != 0 and ("lock" in text.lower() or "incomplete" in text.lower()), text[-2000:]
    smk(tmp_path, "--unlock", "--configfile", config)
    smk(tmp_path, "--cores", "2", "--configfile", config, "--rerun-incomplete")
    f = _summary(tmp_path, "frames", "drops")
    assert f["t"].tolist() == list(range(len(radii)))
    np.testing.assert_allclose(f["area"], 4 * np.pi * np.array(radii) ** 2, rtol=0.03)


# ----------------------------------------------------------------------------- slow: real-looking data, failures, SLURM
def _movie_config(path: Path, frames: int) -> dict:
    cfg = default_config()
    cfg["datasets"] = {"movie": {"path": str(path), "t": "all", "c": "all"}}
    cfg["segment_channel"] = 0
    cfg["layers"]["basal"]["channels"] = [0]
    cfg["layers"]["apical"]["channels"] = [1]
    cfg["layers"]["apical"]["range"] = [6, 11]
    cfg["alignment"] = []
    return cfg


@pytest.mark.slow
def test_multiframe_two_channel_hyperstack(tmp_path):
    """T = 6, C = 2, anisotropic voxels (dz = 2 dx), noise: each layer in its own channel."""
    from nemo.cli import main as nemo_main

    movie = tmp_path / "movie.tif"
    assert nemo_main(["synth", str(movie), "--radius", "60", "--spacing", "2", "1", "1",
                      "--frames", "6", "--frame-rotation", "5", "--channels", "2",
                      "--second-layer-depth", "8.5", "--second-layer-channel", "1",
                      "--noise", "8", "--rotate-random", "4", "--seed", "2"]) == 0
    cfg = _movie_config(movie, 6)
    cfg["curvature"]["radius"] = 10
    # the fan-out over frames and channels is tested here, at the integration scale of the
    # paper (half the 10 µm patch: pixel 0.5 µm, σ 10 px). At the default scale (σ 4 px of
    # ¼ edge ≈ 1 µm) this noisy, dz = 2 dx movie misses one defect in 2 of 12 frame-layers
    # (Σ charge 1.5): noise-aware defaults are issue 12's.
    cfg["directors"].update(patch_radius=10, pixel=0.5, sigma=10)
    cfg["order"]["radius"] = 20
    cfg["defects"]["min_distance"] = 20
    cfg["defects"]["contour_radius"] = 12
    smk(tmp_path, "--cores", "2", "--configfile", write_config(tmp_path / "movie.yaml", cfg))
    f = _summary(tmp_path, "frames", "movie")
    assert len(f) == 6 * 2 and set(zip(f["c"], f["layer"])) == {(0, "basal"), (1, "apical")}
    assert np.allclose(f["charge_sum"], 2.0, atol=0.15)
    tr = _summary(tmp_path, "tracks", "movie")
    full = tr[(tr["first_t"] == 0) & (tr["last_t"] == 5)]
    assert len(full) == 8, tr  # 4 defects × 2 layers followed over all frames
    assert (full["charge_rounded"] == 0.5).all()


@pytest.mark.slow
def test_failing_frame_does_not_corrupt_others(tmp_path):
    """A dark frame fails its mesh; --keep-going completes the other frame, no partial files."""
    from nemo.cli import main as nemo_main
    from nemo.io import read_stack, write_hyperstack

    src = tmp_path / "src.tif"
    assert nemo_main(["synth", str(src), "--radius", "40", "--spacing", "2", "2", "2",
                      "--frames", "2", "--frame-rotation", "5"]) == 0
    frames = [read_stack(src, t=t, c=0)[0] for t in range(2)]
    frames[1][:] = 0  # t = 1 is empty: nemo mesh fails with a clear message
    data = np.stack(frames)[:, :, None]
    write_hyperstack(tmp_path / "broken.tif", data, spacing=(2, 2, 2), axes="TZCYX")
    cfg = default_config()
    cfg["datasets"] = {"broken": {"path": str(tmp_path / "broken.tif")}}
    for layer in cfg["layers"].values():
        layer["channels"] = "all"
    cfg["curvature"]["radius"] = 8
    cfg["directors"].update(patch_radius=8, n_patches=800)
    cfg["order"]["radius"] = 15
    cfg["defects"].update(min_distance=15, contour_radius=10)
    proc = smk(tmp_path, "--cores", "2", "--keep-going", "--configfile",
               write_config(tmp_path / "b.yaml", cfg), check=False)
    assert proc.returncode != 0
    good = tmp_path / "results/broken/t0/c0"
    bad = tmp_path / "results/broken/t1/c0"
    for layer in ("basal", "apical"):
        assert (good / f"defects_{layer}.parquet").exists()
    assert not (bad / "mesh.ply").exists()
    leftovers = [p for p in (tmp_path / "results").rglob("*") if ".tmp" in p.name]
    assert not leftovers, leftovers
    log = (tmp_path / "results/broken/logs/mesh/t1_c0.log").read_text()
    assert "error" in log.lower()


def _slurm_up() -> bool:
    return shutil.which("scontrol") is not None and subprocess.run(
        ["scontrol", "ping"], capture_output=True).returncode == 0


@pytest.fixture(scope="module")
def slurm_cluster():
    """A real single-node SLURM (brought up by tests/slurm/slurm-up.sh unless already up)."""
    started = False
    if not _slurm_up():
        if os.geteuid() != 0:
            pytest.skip("bringing up SLURM needs root (apt-get, daemons)")
        subprocess.run(["bash", str(ROOT / "tests/slurm/slurm-up.sh")], check=True, timeout=1800)
        started = True
    try:
        import snakemake_executor_plugin_slurm  # noqa: F401
    except ImportError:
        pytest.skip("snakemake-executor-plugin-slurm is not installed (pip install '.[slurm]')")
    yield
    if started:
        subprocess.run(["bash", str(ROOT / "tests/slurm/slurm-down.sh")], check=False)


@pytest.mark.slow
def test_slurm_profile_runs_under_slurm_and_matches_local(slurm_cluster, demo_run, tmp_path):
    start = time.strftime("%Y-%m-%dT%H:%M:%S")
    t0 = time.perf_counter()
    # poll SLURM every few seconds (the profile's defaults are gentler, for real clusters)
    smk(tmp_path, "--profile", ROOT / "profiles" / "slurm", "--seconds-between-status-checks", "3",
        "--slurm-init-seconds-before-status-checks", "2", timeout=3600, slurm=True)
    print(f"\nSLURM run of the default workflow: {time.perf_counter() - t0:.0f} s")
    # the jobs really ran under SLURM: sacct knows them (the plugin stores the rule in the comment)
    sacct = subprocess.run(["sacct", "-X", "-n", "-P", "-S", start, "-o", "JobID,State,Comment,WorkDir"],
                           capture_output=True, text=True, check=True).stdout
    rows = [line.split("|") for line in sacct.splitlines() if line.strip()]
    ours = [r for r in rows if Path(r[3]).resolve() == tmp_path.resolve()]
    local_jobs = job_counts(smk(tmp_path, "-n", "--forceall", "--cores", "1"))
    per_frame = {"deconvolve", "mesh", "measure", "curvature", "thickness", "peel", "directors", "order", "defects",
                 "align"}  # deconvolve: psf: auto, the default, one per frame in its group
    local_rules = {"all", "report_config", "report_tables"}  # run beside Snakemake (localrules)
    n_other = sum(v for k, v in local_jobs.items() if k not in per_frame | local_rules)
    frames = default_config()["datasets"]["demo"]["synthetic"]["frames"]
    # one submission per time point (the group 'frame': its mesh, morphology and every layer's
    # jobs), one per other job (synth, aggregation, tracking, figures)
    assert len(ours) == frames + n_other, (len(ours), frames, n_other, sacct[-2000:])
    assert all(r[1] == "COMPLETED" for r in ours), ours
    assert sum(r[2].startswith("rule_frame_") for r in ours) == frames, [r[2] for r in ours]
    for rule in ("synth", "aggregate_frames", "track"):
        assert any(rule in r[2] for r in ours), (rule, ours[:5])
    # and gave the same summaries as the local run
    for name in ("frames", "defects", "tracks", "alignment"):
        local = _summary(demo_run, name)
        remote = _summary(tmp_path, name)
        pd.testing.assert_frame_equal(local, remote, check_exact=False, rtol=1e-6, atol=1e-9)


# ----------------------------------------------------------------------------- HTML report
def test_report_of_the_default_run_has_figures_and_captions(demo_run, tmp_path):
    """`snakemake --report` on the default run: a self-contained HTML with the summary figures
    (tracks per layer, per-frame summaries), each figure not blank, and the captions."""
    from PIL import Image

    work = tmp_path / "run"
    shutil.copytree(demo_run, work, symlinks=True)  # the shared run stays untouched
    figures = work / "results" / "demo" / "summary" / "figures"
    pngs = sorted(figures.glob("*.png"))
    layers = default_config()["layers"]
    assert {p.stem for p in pngs} >= {"frames", *(f"tracks_{name}" for name in layers)}
    for png in pngs:
        pixels = np.asarray(Image.open(png).convert("L"), dtype=float)
        assert pixels.std() > 5, f"{png.name} looks blank"
    # per-frame renders of the first and the last time point (report.frames: ends, the default)
    frames = default_config()["datasets"]["demo"]["synthetic"]["frames"]
    rendered = sorted(p.relative_to(work / "results/demo").as_posix() for p in
                      (work / "results/demo").glob("t*/c*/figures/*") if p.is_dir())
    assert rendered == sorted(f"t{t}/c0/figures/{layer}" for t in (0, frames - 1) for layer in layers)
    report = work / "report.html"
    proc = smk(work, "--report", report)
    # every report item has a known type: the tables are previewed as HTML, not as Parquet
    assert "Could not detect mimetype" not in proc.stdout + proc.stderr, proc.stderr[-3000:]
    html = report.read_text(encoding="utf-8", errors="replace")
    assert report.stat().st_size > 50_000
    for needle in ("tracks_basal", "tracks_apical", "frames.png", "Per-frame summary",
                   "Defect tracks of dataset", "frames.html", "defects.html", "tracks.html",
                   "alignment.html", "config.html", "Configuration of dataset", "t0/c0/figures/basal/"):
        assert needle in html, needle
    summary = work / "results/demo/summary"
    frames_html = (summary / "frames.html").read_text(encoding="utf-8")
    for header in ("area (µm²)", "volume (µm³)", "H_mean (1/µm)", "K_mean (1/µm²)", "thickness_mean (µm)",
                   "charge_sum", "qc_pass", "qc_flags"):
        assert f"<th>{header}</th>" in frames_html, header
    assert "<th>x (µm)</th>" in (summary / "defects.html").read_text(encoding="utf-8")
    assert "<th>path_length (µm)</th>" in (summary / "tracks.html").read_text(encoding="utf-8")
    # the resolved configuration beside the summaries: a valid config with every default filled
    from nemo import config as nconfig

    resolved = yaml.safe_load((summary / "config.yaml").read_text(encoding="utf-8"))
    skipped = ("resources", "worker", "validation")  # not analysis parameters: left out of the page
    assert {k: v for k, v in nconfig.validate(resolved).items() if k not in skipped} == resolved
    assert list(resolved["datasets"]) == ["demo"] and resolved["order"]["radius"] == 25
    assert "resources" not in resolved and resolved["report"]["frames"] == "ends"


# ----------------------------------------------------------------------------- catalog standard
def test_lint_is_clean_and_rules_are_formatted(tmp_path):
    """`snakemake --lint` reports nothing (default and validation configs) and snakefmt would change
    nothing (the Snakemake workflow catalog's checks; .ci/run runs them too)."""
    for cfg in (DEFAULT_CONFIG, ROOT / "config" / "validation-ci.yaml"):
        proc = subprocess.run([*SNAKEMAKE, "-s", str(SNAKEFILE), "-d", str(tmp_path), "--lint",
                               "--configfile", str(cfg)], capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, (cfg.name, (proc.stdout + proc.stderr)[-4000:])
        assert "Lints for" not in proc.stdout + proc.stderr
    snakefmt = Path(sys.executable).parent / "snakefmt"
    if not snakefmt.exists():
        pytest.skip("snakefmt is not installed (pip install snakefmt)")
    proc = subprocess.run([str(snakefmt), "--check", "Snakefile", "workflow"], cwd=ROOT, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]


@pytest.mark.parametrize("frames, expected", [
    (None, [0, 2]),         # the default: the first and the last time point
    (False, []),
    (True, [0, 1, 2]),
    ("all", [0, 1, 2]),
    ([1], [1]),
])
def test_report_frames_chooses_the_rendered_time_points(tmp_path, frames, expected):
    cfg = default_config()
    if frames is None:
        cfg["report"].pop("frames")
    else:
        cfg["report"]["frames"] = frames
    counts = job_counts(smk(tmp_path, "-n", "--configfile", write_config(tmp_path / "c.yaml", cfg)))
    assert counts.get("render", 0) == len(expected) * len(cfg["layers"]), counts
    assert counts["report_tables"] == counts["report_config"] == 1


def test_report_frames_not_analysed_is_a_config_error(tmp_path):
    cfg = default_config()
    cfg["report"]["frames"] = [0, 7]
    proc = smk(tmp_path, "-n", "--configfile", write_config(tmp_path / "c.yaml", cfg), check=False)
    assert proc.returncode != 0 and "Traceback" not in proc.stderr
    assert "config key 'report.frames'" in proc.stderr and "[7]" in proc.stderr, proc.stderr[-2000:]


@pytest.mark.parametrize("profile", ["local", "slurm"])
def test_workflow_profiles_dry_run(tmp_path, profile):
    """Both profiles load with --workflow-profile (executor-plugin form of Snakemake 8+)."""
    if profile == "slurm":
        pytest.importorskip("snakemake_executor_plugin_slurm")
    proc = smk(tmp_path, "-n", "--workflow-profile", ROOT / "workflow" / "profiles" / profile)
    assert "Using workflow specific profile" in proc.stdout + proc.stderr
    assert job_counts(proc)["mesh"] == default_config()["datasets"]["demo"]["synthetic"]["frames"]


def test_catalog_test_config_runs(tmp_path):
    """.test/config/config.yaml (the catalog's small test case, run in CI): a 40 µm vesicle at 2 µm
    voxels, 2 frames, one layer, every length from the data; four +½ defects per frame, tracked."""
    cfg = ROOT / ".test" / "config" / "config.yaml"
    start = time.perf_counter()
    smk(tmp_path, "--cores", "2", "--configfile", cfg, timeout=600)
    print(f"\n.test config: {time.perf_counter() - start:.1f} s with --cores 2")
    f = _summary(tmp_path, "frames", "tiny")
    assert f["t"].tolist() == [0, 1] and (f["layer"] == "fibres").all()
    R = yaml.safe_load(cfg.read_text())["datasets"]["tiny"]["synthetic"]["radius"]
    assert np.allclose(f["area"], 4 * np.pi * R**2, rtol=0.02)
    assert (f["n_defects"] == 4).all() and np.allclose(f["charge_sum"], 2.0, atol=0.05), f
    tracks = _summary(tmp_path, "tracks", "tiny")
    assert len(tracks) == 4 and (tracks["length"] == 2).all() and np.allclose(tracks["charge"], 0.5, atol=0.05)
    summary = tmp_path / "results" / "tiny" / "summary"
    for name in ("frames", "defects", "tracks", "alignment", "config"):
        assert (summary / f"{name}.html").stat().st_size > 200, name
    proc = smk(tmp_path, "--configfile", cfg, "--report", tmp_path / "report.zip")
    assert "Could not detect mimetype" not in proc.stdout + proc.stderr
    assert (tmp_path / "report.zip").stat().st_size > 10_000


# ----------------------------------------------------------------------------- directors from other tools
@pytest.mark.slow  # ≈ 55 s (a two-frame workflow plus nemo run); tests/test_import_directors.py covers the import
def test_directors_from_files_replace_peel_and_directors(tmp_path):
    """A layer with `directors_from` (issue 17): the dry run plans `directors_import` instead of
    peel + directors for it (and the rest unchanged), a missing file stops the parse naming the
    key, and a real run on a small vesicle whose analytic field is given as angles finds its four
    +½ defects in every frame and tracks them."""
    from nemo.pipeline import run_frame
    from nemo.synthetic import truth_directors, write_vesicle

    cfg = default_config()
    frames = cfg["datasets"]["demo"]["synthetic"]["frames"]
    (tmp_path / "ext").mkdir()
    for t in range(frames):
        (tmp_path / "ext" / f"t{t}_c0.csv").write_text("x,y,z,nx,ny,nz\n")
    cfg["layers"]["ext"] = {"surface": "inner", "directors_from": "ext/t{t}_c{c}.csv"}
    cfg["alignment"].append(["basal", "ext"])
    counts = job_counts(smk(tmp_path, "-n", "--configfile", write_config(tmp_path / "c.yaml", cfg)))
    peeled = len(cfg["layers"]) - 1
    assert counts["directors_import"] == frames
    assert counts["peel"] == counts["directors"] == frames * peeled
    assert counts["order"] == counts["defects"] == frames * (peeled + 1)
    assert counts["align"] == frames * 2 and counts["aggregate_frames"] == 1
    (tmp_path / "ext" / "t1_c0.csv").unlink()
    proc = smk(tmp_path, "-n", "--configfile", tmp_path / "c.yaml", check=False)
    assert proc.returncode != 0 and "Traceback" not in proc.stderr
    assert "config key 'layers.ext.directors_from'" in proc.stderr and "ext/t1_c0.csv (t=1, c=0)" in proc.stderr

    # a real run: a small vesicle, its analytic field at scattered points as angles in degrees
    # from the projection of ẑ (what another tool would give), the imported layer only
    R, work = 60.0, tmp_path / "run"
    (work / "dirs").mkdir(parents=True)
    truth = write_vesicle(work / "ves.tif", radius=R, spacing=(2, 2, 2), frames=2, frame_rotation=10, seed=1)
    rng = np.random.default_rng(0)
    for t in range(2):
        u = rng.normal(size=(6000, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        p = np.asarray(truth["centre"]) + u * (R + rng.uniform(-0.5, 0.5, (len(u), 1)))
        n = truth_directors(truth, p, t=t)
        e1 = np.array([0.0, 0.0, 1.0]) - u[:, 2:3] * u
        e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
        angle = np.degrees(np.arctan2(np.einsum("ij,ij->i", n, np.cross(u, e1)), np.einsum("ij,ij->i", n, e1)))
        pd.DataFrame({"x": p[:, 0], "y": p[:, 1], "z": p[:, 2], "angle": angle}).to_csv(work / f"dirs/t{t}.csv",
                                                                                         index=False)
    run_cfg = {"datasets": {"ves": {"path": "ves.tif"}}, "curvature": None, "thickness": None, "alignment": [],
               "layers": {"ext": {"directors_from": "dirs/t{t}.csv",
                                  "import": {"basis": "axis", "axis": [0, 0, 1], "angle_unit": "degrees"}}},
               "order": {"radius": 15}, "tracking": {"max_distance": 20}, "report": {"summary": False}}
    proc = smk(work, "--cores", "2", "--configfile", write_config(work / "c.yaml", run_cfg))
    assert "peel" not in job_counts(proc) and not list(work.rglob("layer_ext.parquet"))
    f = _summary(work, "frames", "ves")
    assert f["t"].tolist() == [0, 1] and f["intensity_mean"].isna().all() and (f["n_directors"] > 4000).all()
    assert (f["n_defects"] == 4).all() and np.allclose(f["charge_sum"], 2.0, atol=0.02), f
    defects = _summary(work, "defects", "ves")
    for t in range(2):
        true = np.array([[d["x"], d["y"], d["z"]] for d in truth["frames"][t]["layers"][0]["defects"]])
        found = defects.loc[defects["t"] == t, ["x", "y", "z"]].to_numpy()
        assert np.linalg.norm(found[:, None] - true[None], axis=2).min(axis=0).max() < 0.1 * R
    tracks = _summary(work, "tracks", "ves")
    assert len(tracks) == 4 and (tracks["length"] == 2).all()
    # nemo run with the same config imports the same file and gives the workflow's numbers
    from nemo.tables import read_table

    cwd = os.getcwd()
    os.chdir(work)  # relative dataset and directors_from paths, as for the workflow (-d work)
    try:
        run_frame(None, work / "one", work / "c.yaml", t=1, c=0, dataset="ves")
    finally:
        os.chdir(cwd)
    frame = work / "results" / "ves" / "t1" / "c0"
    for kind in ("directors", "order", "defects"):
        a = read_table(work / "one" / f"{kind}_ext.parquet")
        b = read_table(frame / f"{kind}_ext.parquet")
        pd.testing.assert_frame_equal(a, b, check_exact=False, rtol=1e-9)
    assert not (work / "one" / "layer_ext.parquet").exists()


# ----------------------------------------------------------------------------- real microscopy
def test_real_stacks_run_end_to_end_with_quality_control(tmp_path):
    """config/real.yaml on the two real stacks shipped in data/real/ (a neural-tube organoid at
    3.4 µm voxels, an uncalibrated Drosophila embryo cut by the field of view): the workflow runs
    through, every frame has its QC verdict, what is wrong with the data is named, the organoid
    (one object, mesh.keep: all) gets its row, and the input files are not modified."""
    import hashlib

    (tmp_path / "data").symlink_to(ROOT / "data")
    stacks = sorted((ROOT / "data" / "real").glob("*.tif"))
    digest = {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in stacks}
    smk(tmp_path, "--cores", "2", "--configfile", ROOT / "config" / "real.yaml", timeout=900)
    organoid = _summary(tmp_path, "frames", "organoid")  # one ring of epithelium (keep: all)
    assert organoid["object"].tolist() == [0] and (organoid["n_objects"] == 1).all()
    assert organoid["c"].tolist() == [1] and organoid["layer"].tolist() == ["apical"]
    assert not organoid["qc_pass"].any()  # a porous, cut nuclear shell: flagged, with reasons
    assert organoid["qc_flags"].str.contains("pieces").all() and organoid["qc_flags"].str.contains("holes").all()
    assert organoid["S_mean"].between(0, 1).all() and (organoid["snr"] > 3).all()
    fly = _summary(tmp_path, "frames", "drosophila")
    assert len(fly) == 1 and fly["n_objects"].iloc[0] == 1 and fly["area"].iloc[0] > 1000  # pixel² units
    # membranes have no nematic texture at this scale: the directors are noise, less coherent than white
    # noise at the scale they were measured at (the noise-aware default widens it), and the QC says so
    assert fly["qc_flags"].str.contains("no texture to orient").all()
    assert (fly["coherency_median"] < fly["coherency_noise"]).all()
    for name in ("organoid", "drosophila"):
        figures = tmp_path / "results" / name / "summary" / "figures"
        assert (figures / "frames.png").stat().st_size > 10_000
    assert {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in stacks} == digest


@pytest.mark.slow  # ≈ 75 s; the default suite runs keep: all through the workflow on the real organoid
def test_several_objects_through_the_workflow_and_nemo_run(tmp_path, write_two_vesicles):
    """mesh.keep: all through snakemake: a row per object, each with its own Σ charge = χ = 2 and
    its defects at the truth; `nemo run` with the same config gives the same tables."""
    from nemo import layout
    from nemo.tables import read_table

    truth = write_two_vesicles(tmp_path / "two.tif")
    cfg = {"datasets": {"two": {"path": "two.tif"}}, "mesh": {"keep": "all", "split": "centre"},
           "layers": {"film": {"surface": "inner", "range": [0, 4]}}, "alignment": [],
           "report": {"summary": False, "frames": False}}
    config = write_config(tmp_path / "c.yaml", cfg)
    smk(tmp_path, "--cores", "2", "--configfile", config)
    f = _summary(tmp_path, "frames", "two")
    assert f["object"].tolist() == [0, 1] and f["qc_pass"].all(), f["qc_flags"].tolist()
    np.testing.assert_allclose(f["charge_sum"], 2.0, atol=0.05)
    d = _summary(tmp_path, "defects", "two")
    for label, true in enumerate(truth):
        xyz = d.loc[d["object"] == label, ["x", "y", "z"]].to_numpy()
        err = np.linalg.norm(xyz[:, None] - true["defects"][None], axis=2).min(axis=1)
        assert len(xyz) == 4 and err.max() < 3.0, err
    proc = subprocess.run([sys.executable, "-m", "nemo", "run", "--config", str(config), "--dataset", "two",
                           "-o", str(tmp_path / "run")], cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    frame = tmp_path / "results" / "two" / "t0" / "c0"
    for name in (layout.layer_file("defects", "film"), layout.layer_file("order", "film"), "curvature_inner.parquet",
                 "thickness.parquet"):
        pd.testing.assert_frame_equal(read_table(frame / name), read_table(tmp_path / "run" / name))


@pytest.mark.slow  # > 1 min on 2 cores (the default suite stays under ~15 min)
def test_each_channel_is_deconvolved_by_its_own_psf(tmp_path):
    """datasets.NAME.psf as one PSF per channel: the deconvolve, mesh and peel jobs of each channel
    get that channel's PSF (dry run), a channel with null is not deconvolved, and a list without
    an analysed channel is refused naming the key."""
    cfg = {"datasets": {"two": {"path": "two.tif", "psf": [[2.0, 1.0, 1.0], [3.0, 1.5, 1.5]],
                                "synthetic": {"radius": 30, "spacing": [2, 1, 1], "channels": 2,
                                              "second_layer_depth": 6, "second_layer_channel": 1, "seed": 3}}},
           "curvature": None, "layers": {"fibres": {"surface": "inner", "range": [0, 4], "channels": [1]}},
           "alignment": [], "report": {"summary": False, "frames": False}}
    proc = smk(tmp_path, "-n", "-p", "--configfile", write_config(tmp_path / "c.yaml", cfg))
    lines = [line for line in proc.stdout.splitlines() if "nemo" in line and "--psf" in line]
    psf_of = {(cmd, c): " ".join(line.split("--psf ")[1].split()[:3]) for line in lines
              for cmd in ("deconvolve", "mesh", "peel") for c in (0, 1) if f" {cmd} " in line and f"--c {c}" in line}
    assert psf_of == {("deconvolve", 0): "2.0 1.0 1.0", ("mesh", 0): "2.0 1.0 1.0",
                      ("deconvolve", 1): "3.0 1.5 1.5", ("peel", 1): "3.0 1.5 1.5"}, psf_of
    assert any(" peel " in line and "c1/deconvolved.tif" in line for line in lines), lines
    cfg["datasets"]["two"]["psf"] = [[2.0, 1.0, 1.0], None]  # channel 1 as recorded: not deconvolved
    proc = smk(tmp_path, "-n", "-p", "--configfile", write_config(tmp_path / "c2.yaml", cfg))
    peel = [line for line in proc.stdout.splitlines() if " peel " in line and "--c 1" in line]
    assert peel and all("--psf none " in line and "--deconvolved" not in line for line in peel), peel
    cfg["datasets"]["two"]["psf"] = [None, "auto"]  # channel 1's estimated from the image, by each step alike
    proc = smk(tmp_path, "-n", "-p", "--configfile", write_config(tmp_path / "c5.yaml", cfg))
    auto = [line for line in proc.stdout.splitlines() if "--psf auto" in line]
    assert {cmd for cmd in ("deconvolve", "mesh", "peel") for line in auto if f" {cmd} " in line} == {"deconvolve", "peel"}
    assert all("--psf auto " in line and "--c 1" in line for line in auto), auto
    mesh = [line for line in proc.stdout.splitlines() if " mesh " in line and " -o " in line]
    assert mesh and all("--psf none " in line for line in mesh), mesh  # the commands' default is auto: none said
    cfg["datasets"]["two"]["psf"] = [[2.0, 1.0, 1.0], None, [3.0, 1.0, 1.0]]  # three PSFs for two channels
    proc = smk(tmp_path, "-n", "--configfile", write_config(tmp_path / "c4.yaml", cfg))
    assert "datasets.two.psf lists 3 PSFs but the image has 2 channels" in proc.stderr, proc.stderr[-2000:]
    cfg["datasets"]["two"]["psf"] = [[2.0, 1.0, 1.0]]
    proc = smk(tmp_path, "-n", "--configfile", write_config(tmp_path / "c3.yaml", cfg), check=False)
    assert proc.returncode != 0 and "datasets.two.psf" in proc.stderr and "not for channel 1" in proc.stderr


def test_edge_profile_under_the_default_auto_meshes_the_image_itself(tmp_path):
    """mesh.edge: profile with the default psf: auto: the mesh job reads no deconvolved frame, and
    without layers no deconvolve job runs at all (dry run); with a layer only its peel reads it."""
    cfg = {"datasets": {"one": {"path": "one.tif", "synthetic": {"radius": 30, "spacing": [2, 1, 1], "seed": 3}}},
           "mesh": {"edge": "profile"}, "layers": {}, "curvature": None, "thickness": None, "alignment": [],
           "report": {"summary": False, "frames": False}}
    proc = smk(tmp_path, "-n", "-p", "--configfile", write_config(tmp_path / "c.yaml", cfg))
    counts = job_counts(proc)
    assert counts.get("mesh") == 1 and "deconvolve" not in counts, counts
    cfg["layers"] = {"fibres": {"surface": "inner", "range": [0, 4]}}
    proc = smk(tmp_path, "-n", "-p", "--configfile", write_config(tmp_path / "c2.yaml", cfg))
    lines = proc.stdout.splitlines()
    mesh = [line for line in lines if " mesh " in line and " -o " in line]
    peel = [line for line in lines if " peel " in line and " -o " in line]
    assert mesh and not any("--deconvolved" in line for line in mesh), mesh
    assert peel and all("--deconvolved" in line and "--psf auto" in line for line in peel), peel
    assert job_counts(proc).get("deconvolve") == 1


def test_the_masks_channel_reaches_the_mesh_job(tmp_path):
    """datasets.NAME.mask_channel: the mesh job reads that channel of the mask (dry run)."""
    import tifffile

    tifffile.imwrite(tmp_path / "classes.tif", np.zeros((30, 2, 60, 60), np.float32), imagej=True,
                     metadata={"axes": "ZCYX"})
    cfg = {"datasets": {"one": {"path": "one.tif", "mask": str(tmp_path / "classes.tif"), "mask_channel": 1,
                                "synthetic": {"radius": 30, "spacing": [2, 1, 1], "seed": 3}}},
           "curvature": None, "alignment": [], "report": {"summary": False, "frames": False}}
    proc = smk(tmp_path, "-n", "-p", "--configfile", write_config(tmp_path / "c.yaml", cfg))
    mesh = [line for line in proc.stdout.splitlines() if " mesh " in line and "--mask " in line]
    assert mesh and all("--mask-channel 1" in line for line in mesh), proc.stdout[-3000:]


def test_curvature_options_reach_the_curvature_job(tmp_path):
    """curvature.adaptive: false and curvature.local_fraction reach `nemo curvature` (dry run):
    --no-adaptive (the option is on by default) and --local-fraction."""
    cfg = {"datasets": {"one": {"path": "one.tif", "synthetic": {"radius": 30, "spacing": [2, 1, 1], "seed": 3}}},
           "curvature": {"adaptive": False, "local_fraction": 0.65}, "alignment": [],
           "report": {"summary": False, "frames": False}}
    proc = smk(tmp_path, "-n", "-p", "--configfile", write_config(tmp_path / "c.yaml", cfg))
    jobs = [line for line in proc.stdout.splitlines() if " curvature " in line and " -o " in line]
    assert jobs and all("--no-adaptive" in line and "--local-fraction 0.65" in line for line in jobs), proc.stdout[-3000:]


@pytest.mark.slow  # > 1 min on 2 cores (the default suite stays under ~15 min)
@pytest.mark.parametrize("psf", [[2.0, 1.0, 1.0], pytest.param("auto", id="auto (the default: no psf key)")])
def test_psf_is_deconvolved_alike_by_the_workflow_and_nemo_run(tmp_path, psf):
    """datasets.NAME.psf through snakemake: the frame is deconvolved once (rule deconvolve) and the
    mesh and both peels use that one deconvolution (their provenance records the same run),
    `nemo run` with the same config gives the same tables, a new PSF reruns the deconvolution, the
    mesh and the peels (and what depends on them), not the synthesis, and a peel's parameter
    reruns that peel alone. ``psf: auto``, the default (the dataset gives no psf): the z blur
    beyond the lateral (√3 µm here) estimated from the image by each step alike."""
    from nemo import layout
    from nemo.mesh import load_mesh
    from nemo.tables import read_provenance, read_table

    given = {} if psf == "auto" else {"psf": psf}
    cfg = {"datasets": {"z": {"path": "z.tif", **given,
                              "synthetic": {"radius": 30, "spacing": [2, 1, 1], "blur": [2, 1, 1], "seed": 3}}},
           "curvature": None, "thickness": None,
           "layers": {"fibres": {"surface": "inner", "range": [0, 4]}, "deep": {"surface": "inner", "range": [4, 8]}},
           "alignment": [], "report": {"summary": False, "frames": False}}
    smk(tmp_path, "--cores", "2", "--configfile", write_config(tmp_path / "c.yaml", cfg))
    frame = tmp_path / "results" / "z" / "t0" / "c0"
    mesh_params = load_mesh(frame / layout.MESH["inner"]).metadata["nemo_params"]
    peel_params = read_provenance(frame / layout.layer_file("layer", "fibres"))["parameters"]
    for record in (mesh_params["deconvolution"], peel_params["deconvolution"]):
        assert record["estimated"] == (psf == "auto") and record["iterations"] > 0, record
        if psf == "auto":
            assert record["psf"][1:] == [0.0, 0.0] and abs(record["psf"][0] - 3**0.5) < 0.4, record
        else:
            assert record["psf"] == psf, record
    used = mesh_params["deconvolution"]["psf"]
    deep = read_provenance(frame / layout.layer_file("layer", "deep"))["parameters"]["deconvolution"]
    assert peel_params["deconvolution"]["seconds"] == deep["seconds"] == mesh_params["deconvolution"]["seconds"]
    assert (tmp_path / "results" / "z" / "logs" / "deconvolve" / "t0_c0.log").exists()
    proc = subprocess.run([sys.executable, "-m", "nemo", "run", "--config", str(tmp_path / "c.yaml"), "--dataset",
                           "z", "-o", str(tmp_path / "run")], cwd=tmp_path, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    once = json.loads((tmp_path / "run" / layout.SUMMARY_JSON).read_text())["mesh"]["deconvolution"]
    for layer in ("fibres", "deep"):  # nemo run deconvolves the channel once for the mesh and both peels
        for kind in ("layer", "directors", "order", "defects"):
            pd.testing.assert_frame_equal(read_table(frame / layout.layer_file(kind, layer)),
                                          read_table(tmp_path / "run" / layout.layer_file(kind, layer)))
        record = read_provenance(tmp_path / "run" / layout.layer_file("layer", layer))["parameters"]["deconvolution"]
        rule = read_provenance(frame / layout.layer_file("layer", layer))["parameters"]["deconvolution"]
        assert record.keys() == rule.keys() and record["psf"] == used and record["iterations"] > 0
        assert record["seconds"] == once["seconds"], (record, once)  # the same deconvolution, not another
    cfg["datasets"]["z"]["psf"] = [2.5, 1.0, 1.0]
    counts = job_counts(smk(tmp_path, "-n", "--nolock", "--configfile", write_config(tmp_path / "c2.yaml", cfg)))
    assert counts.get("deconvolve") == counts.get("mesh") == 1 and counts.get("peel") == 2, counts
    assert "synth_z" not in counts, counts
    cfg["datasets"]["z"].pop("psf")
    cfg["datasets"]["z"].update(given)  # back to the PSF the results were made with
    cfg["layers"]["deep"]["range"] = [4, 9]  # a peel's parameter: that peel, not the deconvolution or the mesh
    counts = job_counts(smk(tmp_path, "-n", "--nolock", "--configfile", write_config(tmp_path / "c3.yaml", cfg)))
    assert counts.get("peel") == 1 and "deconvolve" not in counts and "mesh" not in counts, counts
    (frame / layout.DECONVOLVED).unlink()  # deleted: nothing to do until a step needs it (docs/workflow.md)
    assert job_counts(smk(tmp_path, "-n", "--nolock", "--configfile", tmp_path / "c.yaml")) == {}
