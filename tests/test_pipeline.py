"""``nemo run`` / :func:`nemo.pipeline.run_frame` and ``nemo defects`` on synthetic vesicles.

Ground truth: the defect positions and charges written by nemo.synthetic beside each image.
The default (fast) tests use small vesicles with parameters scaled to their size; the paper-scale
runs (R = 200 µm, the paper's parameters) are marked slow.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from nemo.errors import NemoError
from nemo.pipeline import DEFAULTS, FILES, load_config, merge_config, run_frame
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
    "mesh": {"step_um": 1.0},
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


# ------------------------------------------------------------------------------------------------
# configuration


def test_config_defaults_are_the_papers():
    cfg = load_config(None)
    assert cfg["mesh"]["step_um"] == 2.0
    assert cfg["peel"]["range"] == [0.0, 5.0]
    assert cfg["directors"]["n_patches"] == 12000 and cfg["directors"]["patch_radius"] == 20.0
    assert cfg["order"]["radius"] == 50.0
    assert cfg["mesh"]["surface"] == "inner"


def test_config_override_and_unknown_keys(tmp_path):
    cfg = merge_config({"order": {"radius": 30}})
    assert cfg["order"]["radius"] == 30 and cfg["directors"] == DEFAULTS["directors"]
    with pytest.raises(NemoError, match="'order.radus'"):
        merge_config({"order": {"radus": 30}})
    with pytest.raises(NemoError, match="'ordre'"):
        merge_config({"ordre": {}})
    with pytest.raises(NemoError, match="must be a mapping"):
        merge_config({"order": 3})
    bad = tmp_path / "bad.yaml"
    bad.write_text("defects:\n  contour_radus: 3\n")
    with pytest.raises(NemoError, match="defects.contour_radus"):
        load_config(bad)
    bad.write_text("order: [unclosed\n")
    with pytest.raises(NemoError, match="not valid YAML"):
        load_config(bad)
    with pytest.raises(NemoError, match="not found"):
        load_config(tmp_path / "missing.yaml")
    from nemo.pipeline import _check

    for bad_value in (1.5, -0.1, True, "yes"):
        with pytest.raises(NemoError, match="defects.refine_directors"):
            _check(merge_config({"defects": {"refine_directors": bad_value}}))
    with pytest.raises(NemoError, match="directors.pixel"):
        _check(merge_config({"directors": {"pixel": 0}}))


def test_cli_run_config_errors(run_cli, tmp_path, small_vesicle):
    path, _ = small_vesicle
    cfg = tmp_path / "c.yaml"
    cfg.write_text("peel:\n  range: [5, 0]\n")
    code, _, err = run_cli("run", path, "-o", tmp_path / "o", "--config", cfg)
    assert code == 2 and "peel.range" in err and "Traceback" not in err
    cfg.write_text("mesh:\n  stepum: 2\n")
    code, _, err = run_cli("run", path, "-o", tmp_path / "o", "--config", cfg)
    assert code == 2 and "mesh.stepum" in err
    code, out, _ = run_cli("run", path, "--print-config")
    assert code == 0 and "radius: 50.0" in out
    code, _, err = run_cli("run", tmp_path / "nothere.tif", "-o", tmp_path / "o")
    assert code == 2


# ------------------------------------------------------------------------------------------------
# end to end on a small vesicle


def test_run_frame_writes_every_file_and_finds_the_defects(small_run):
    out, summary, truth = small_run
    for key in ("mesh", "inner", "outer", "layer", "directors", "order", "curvature", "defects", "summary",
                "refine_directors"):
        assert (out / FILES[key]).exists(), key
    saved = json.loads((out / FILES["summary"]).read_text())
    assert saved["euler_check"]["closed"] and saved["euler_check"]["euler_characteristic"] == 2
    assert saved["euler_check"]["matches"]
    assert set(saved["timings_s"]) >= {"mesh", "peel", "directors", "order", "curvature", "defects"}
    df = read_table(out / FILES["defects"], kind="defects")
    err = assert_matches_truth(df, truth, max_error=3.0)
    assert np.median(err) < 2.0  # measured 0.7-2.1 µm (fibre spacing 3 µm, mesh edge ≈ 0.9 µm)
    prov = read_provenance(out / FILES["defects"])
    assert prov["euler_check"]["matches"] and prov["parameters"]["avg_radius"] == 12.0
    assert read_provenance(out / FILES["order"])["radius"] == 12.0
    # refinement directors: near the defects only (within the fit radius 0.75 x 12 µm)
    extra = read_table(out / FILES["refine_directors"], kind="directors")
    assert saved["n_refine_directors"] == len(extra) > 0
    d = np.linalg.norm(extra[["x", "y", "z"]].to_numpy()[:, None] - df[["x", "y", "z"]].to_numpy()[None], axis=2)
    assert d.min(axis=1).max() <= 0.75 * 12.0 + 3.0  # refined positions moved at most a few µm


def test_cli_defects_on_run_outputs(run_cli, small_run, tmp_path):
    out, _, truth = small_run
    mesh, order, dirs = out / FILES["inner"], out / FILES["order"], out / FILES["directors"]
    code, stdout, _ = run_cli("defects", mesh, order, dirs, "-o", tmp_path / "d.parquet")
    assert code == 0
    assert "Euler check: sum of charges" in stdout and "chi = 2: ok" in stdout
    df = read_table(tmp_path / "d.parquet", kind="defects")
    assert_matches_truth(df, truth, max_error=3.0)
    # the K term from the curvature table instead of angle defects
    code, stdout, _ = run_cli("defects", mesh, order, dirs, "--curvature", out / FILES["curvature"],
                              "-o", tmp_path / "k.parquet")
    assert code == 0
    dk = read_table(tmp_path / "k.parquet", kind="defects")
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
    code, _, err = run_cli("defects", out / FILES["mesh"], order, dirs, "-o", tmp_path / "x.parquet")
    assert code == 2 and "another mesh" in err
    code, _, err = run_cli("defects", mesh, dirs, order, "-o", tmp_path / "x.parquet")
    assert code == 2 and "lacks column" in err


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
    summary = run_frame(path, tmp_path / "out")
    df = read_table(tmp_path / "out" / FILES["defects"], kind="defects")
    err = assert_matches_truth(df, truth, max_error=2.0 if case in HEADLINE else 3.58)
    print(f"{case}: errors {np.round(err, 2)} µm, charges {np.round(df['charge'].to_numpy(), 3)}, "
          f"{summary['total_s']:.1f} s")
    assert summary["euler_check"]["matches"]
