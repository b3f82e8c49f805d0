"""nemo.summary on small hand-built per-frame tables with answers worked out by hand."""

from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pytest

from nemo.errors import NemoError
from nemo.summary import (
    ALIGN_COLUMNS,
    DEFECT_COLUMNS,
    FRAME_COLUMNS,
    alignment_summary,
    collect_defects,
    frame_summary,
    quality_flags,
)
from nemo.tables import write_table

NAN = math.nan


def _defects(charges, rounded, **extra) -> pd.DataFrame:
    n = len(charges)
    return pd.DataFrame({"x": np.arange(n, dtype=float), "y": 0.0, "z": 0.0, "vertex": np.arange(n),
                         "S": 0.1, "charge": charges, "charge_winding": charges,
                         "charge_curvature": 0.0, "charge_rounded": rounded, **extra})


@pytest.fixture
def frame_files(tmp_path):
    """Files of one full frame-layer (t = 1, c = 0, basal) with known means."""
    d = tmp_path / "t1"
    d.mkdir()
    (d / "measure.json").write_text(json.dumps({"area": 12.5, "volume": 7.0, "euler_characteristic": 2,
                                                "mean_H": 0.1, "mean_K": 0.01}))
    write_table(pd.DataFrame({"vertex": [0, 1, 2], "H": [1.0, 2.0, NAN], "K": [0.5, NAN, 1.5],
                              "k1": [1.0, 2.0, NAN], "k2": [-4.0, 0.5, NAN]}),
                d / "curvature.parquet", parameters={"fit_scatter_H": 0.6, "radius": 0.2})
    write_table(pd.DataFrame({"vertex": [0, 1, 2, 3], "thickness": [1.0, 2.0, 6.0, NAN]}),
                d / "thickness.parquet")
    write_table(pd.DataFrame({"vertex": [0, 1, 2], "intensity": [1.0, 3.0, NAN]}), d / "layer.parquet")
    write_table(pd.DataFrame({"vertex": [0, 1], "x": 0.0, "y": 0.0, "z": 0.0, "nx": 1.0, "ny": 0.0,
                              "nz": 0.0, "coherency": [0.2, 0.4]}), d / "directors.parquet")
    write_table(pd.DataFrame({"vertex": [0, 1, 2, 3], "S": [0.1, 0.2, 0.9, NAN], "nx": 1.0, "ny": 0.0,
                              "nz": 0.0}), d / "order.parquet")
    write_table(_defects([0.48, 0.52, -0.45], [0.5, 0.5, -0.5]), d / "defects.parquet",
                parameters={"min_distance": 30.0})
    return {"t": 1, "c": 0, "layer": "basal", "surface": "inner", "measure": d / "measure.json",
            "curvature": d / "curvature.parquet", "thickness": d / "thickness.parquet",
            "layer_table": d / "layer.parquet", "directors": d / "directors.parquet",
            "order": d / "order.parquet", "defects": d / "defects.parquet"}


# ----------------------------------------------------------------------------- frame_summary
def test_frame_summary_means_ignore_nan(frame_files):
    out = frame_summary([frame_files])
    assert list(out.columns) == list(FRAME_COLUMNS) and len(out) == 1
    row = out.iloc[0]
    expected = {
        "t": 1, "c": 0, "layer": "basal", "surface": "inner", "area": 12.5, "volume": 7.0,
        "euler_characteristic": 2.0, "H_mean": 0.1, "K_mean": 0.01,
        "H_fit_mean": 1.5, "K_fit_mean": 1.0, "curvature_nan_fraction": 1 / 3,  # NaN dropped
        "curvature_noise": 0.6 / 3.0,  # the fits' scatter over the median largest |k| (4 and 2)
        "thickness_mean": 3.0, "thickness_median": 2.0, "thickness_valid": 0.75,  # 3 of 4 finite
        "intensity_mean": 2.0, "peel_nan_fraction": 1 / 3, "n_directors": 2, "coherency_mean": 0.3,
        "coherency_median": 0.3, "S_mean": 0.4, "S_median": 0.2, "order_nan_fraction": 0.25,
        "n_defects": 3, "charge_sum": 0.55, "charge_rounded_sum": 0.5, "qc_pass": False,
        "qc_flags": "curvature dominated by noise: the fits scatter by 20 % of the surface's typical curvature, "
                    "so H and K per vertex are noisy (median errors of 8 % or more in tests, a noisy wall, or a "
                    "surface curved on the scale of a few mesh edges); thickness found at 75 % of vertices; 33 % of "
                    "vertices have no layer intensity (samples outside the image?); 25 % of vertices have no order "
                    "value (no tangent plane or director in reach); Σ charge 0.55 ≠ χ 2 (3 defects)",
    }
    assert len(row["qc_flags"].split("; ")) == 5  # one part per reason (the first's own "; " read as ", ")
    for key, value in expected.items():
        if isinstance(value, str):
            assert row[key] == value, key
        else:
            assert row[key] == pytest.approx(value, abs=1e-12), key
    assert out["t"].dtype == np.int64 and out["c"].dtype == np.int64
    assert str(out["n_directors"].dtype) == "Int64" and str(out["n_defects"].dtype) == "Int64"


def test_frame_summary_counts_the_defects_where_the_fibres_are_faint(frame_files):
    """``defects_faint``: the defects whose coherency (nemo.defects: the directors' median within the
    contour over the surface's) is below 0.85, flagged; a defects table without the column (an
    older one) was not measured: NA, not 0; no defect found is 0."""
    write_table(_defects([0.5, 0.5, 0.5, 0.5], [0.5] * 4, coherency=[1.0, 0.97, 0.74, 0.88]), frame_files["defects"])
    row = frame_summary([frame_files]).iloc[0]
    assert row["defects_faint"] == 1 and "1 defect(s) where the fibres are faint (coherency 0.74 below" in row["qc_flags"]
    write_table(_defects([0.5, 0.5, 0.5, 0.5], [0.5] * 4), frame_files["defects"])
    row = frame_summary([frame_files]).iloc[0]
    assert row["defects_faint"] is pd.NA and "faint" not in row["qc_flags"]
    write_table(_defects([], []), frame_files["defects"])
    assert frame_summary([frame_files]).iloc[0]["defects_faint"] == 0


def test_frame_summary_reads_the_rejected_zeros_of_each_object(frame_files):
    """``rejected_zeros`` (nemo.stages.defects' resolved parameters: zeros of the averaged order with
    a nonzero winding rejected for their contour) is the row's column and flags it; per object on
    a mesh of several; NA for a table from before the count."""
    write_table(_defects([0.5] * 4, [0.5] * 4), frame_files["defects"], parameters={"rejected_zeros": 2})
    row = frame_summary([frame_files]).iloc[0]
    assert row["rejected_zeros"] == 2 and not row["qc_pass"] and "2 zero(s) of the averaged order" in row["qc_flags"]
    write_table(_defects([0.5] * 4, [0.5] * 4), frame_files["defects"], parameters={"rejected_zeros": 0})
    row = frame_summary([frame_files]).iloc[0]
    assert row["rejected_zeros"] == 0 and "zero(s) of the averaged order" not in row["qc_flags"]
    write_table(_defects([0.5] * 4, [0.5] * 4), frame_files["defects"], parameters={"s_threshold": 0.3})
    assert frame_summary([frame_files]).iloc[0]["rejected_zeros"] is pd.NA
    by_object = {"rejected_zeros": 0, "objects": [{"object": 0, "rejected_zeros": 0}, {"object": 1, "rejected_zeros": 3}]}
    write_table(_defects([0.5] * 4, [0.5] * 4), frame_files["defects"], parameters=by_object)
    from nemo import summary

    assert summary._step_params(frame_files, "defects", 1)["rejected_zeros"] == 3
    assert summary._step_params(frame_files, "defects", 0)["rejected_zeros"] == 0


def test_frame_summary_flags_a_skipped_defect_search_of_one_object(frame_files):
    """A frame of one object whose defect search could not run (nemo.stages.defects: an object
    too small for its derived lengths) fails the QC with the reason, as an object of several does;
    not also with "Σ charge 0 ≠ χ 2", which a search that did not run cannot meet (a review's tissue:
    33 of 255 nuclei had both); its count and charge sum are missing, not 0 (an end-to-end review:
    the summary figure plotted the empty frame's 0 defects as a count)."""
    reason = "the object is too small for the lengths derived from the data"
    write_table(_defects([], []), frame_files["defects"],
                euler_check={"sum_charge": 0.0, "euler_characteristic": 2, "closed": True, "matches": False,
                             "skipped": reason})
    row = frame_summary([frame_files]).iloc[0]
    assert not row["qc_pass"] and f"no defect search: {reason}" in row["qc_flags"]
    assert "Σ charge" not in row["qc_flags"], row["qc_flags"]
    assert row["n_defects"] is pd.NA and np.isnan(row["charge_sum"])  # not searched: not "none found"
    assert row["defects_faint"] is pd.NA


def test_frame_summary_flags_a_surface_open_where_the_series_is_closed(frame_files, tmp_path):
    """An object that drifts partly out of the field of view at t = 2 has an open surface (a rim):
    its area and centre are of the part in view and its Σ charge is not checked, so it passed with
    wrong numbers (an independent review: area −17 %, defects missed). It is flagged against the
    series; a series open at every time point (a tissue cut by the field) is not."""
    measure = json.loads(frame_files["measure"].read_text())
    records = []
    for t, loops in enumerate((0, 0, 1, 0)):
        path = tmp_path / f"measure{t}.json"
        path.write_text(json.dumps({**measure, "n_boundary_loops": loops, "rim_loops": loops}))
        records.append({**frame_files, "t": t, "measure": path})
    out = frame_summary(records)
    assert out["closed"].tolist() == [True, True, False, True]
    flagged = out["qc_flags"].str.contains("surface open where most time points are closed").tolist()
    assert flagged == [False, False, True, False] and not out["qc_pass"][2]
    cut = frame_summary([{**r, "measure": records[2]["measure"]} for r in records])
    assert not cut["closed"].any() and not cut["qc_flags"].str.contains("most time points").any()
    # two objects (keep: all) whose area ranks swap: one is always cut by the border, so a frame with
    # one open object is as usual whichever label it has; a frame where both are open is flagged
    for t, loops in enumerate(([0, 1], [1, 0], [0, 1], [1, 1])):
        objects = [{**measure, "object": k, "n_boundary_loops": n, "rim_loops": n} for k, n in enumerate(loops)]
        records[t]["measure"].write_text(json.dumps({**measure, "n_boundary_loops": 1, "objects": objects}))
    out = frame_summary(records)
    flagged = out["qc_flags"].str.contains("surface open where most time points are closed").tolist()
    assert out["closed"].tolist() == [True, False, False, True, True, False, False, False]
    assert flagged == [False] * 6 + [True, False], flagged


def test_frame_summary_flags_keep_largest_switching_objects(frame_files, tmp_path):
    """keep: largest with three objects in view: a shrinking shell is the largest at t 0–1 and a
    growing one from t 2, 54 µm away. The series mixes two objects (its area falls and rises), so
    the frame where the largest changed is flagged; a drift of a few µm is not, nor a frame of
    one object in view."""
    measure = json.loads(frame_files["measure"].read_text())
    records = []
    for t, (x, area, n) in enumerate(((50, 8500, 3), (52, 7200, 3), (108, 7800, 3), (110, 8500, 3), (170, 8600, 1),
                                      (230, 8600, 1))):
        path = tmp_path / f"measure{t}.json"
        path.write_text(json.dumps({**measure, "centre": [x, 65.0, 40.0], "area": area, "n_objects": n}))
        records.append({**frame_files, "t": t, "measure": path})
    out = frame_summary(records)
    flagged = out["qc_flags"].str.contains("another object than at t = ").tolist()
    # t 4: the other objects left the field, and the one in view is not the one of t 3 (flagged);
    # t 5: one object in view at both time points, moved (not flagged)
    assert flagged == [False, False, True, False, True, False], out["qc_flags"].tolist()
    assert "another object than at t = 1 (object_id 0 → 1)" in out["qc_flags"][2] and "keep: all" in out["qc_flags"][2]
    assert out["object_id"].tolist() == [0, 0, 1, 1, 2, 3]  # the same objects, by their centres


def test_a_layer_outside_one_wall_is_flagged_whoever_peeled_it(frame_files):
    """A layer outward of a one-walled object's outline samples the background: flagged from the
    record's surface, whether the peel's provenance names it (``nemo run``) or not (the workflow's
    ``nemo peel``, given a mesh file: the workflow never raised the flag, an independent review)."""
    measure = json.loads(frame_files["measure"].read_text())
    frame_files["measure"].write_text(json.dumps({**measure, "walls": 1}))
    layer = pd.DataFrame({"vertex": [0, 1, 2], "intensity": [1.0, 3.0, NAN]})
    for named in ({"surface": "inner"}, {"surface": None}):
        write_table(layer, frame_files["layer_table"], parameters={"range": [0.0, 5.0], "inward": False, **named})
        row = frame_summary([frame_files]).iloc[0]
        assert "the object has one wall, so the layer's range" in row["qc_flags"], named
    write_table(layer, frame_files["layer_table"], parameters={"range": [-1.0, 1.0], "inward": False})
    assert "the object has one wall" not in frame_summary([frame_files]).iloc[0]["qc_flags"]  # straddles it
    write_table(layer, frame_files["layer_table"], parameters={"range": [0.0, 5.0], "inward": False})
    assert "the object has one wall" not in frame_summary([{**frame_files, "surface": "whole"}]).iloc[0]["qc_flags"]


def test_frame_summary_walls_come_from_the_mesh_step(frame_files):
    """The mesh step's walls (1 or 2; one per object with several) reach the row; a frame of one
    wall with its NaN thickness is not flagged for it."""
    measure = json.loads(frame_files["measure"].read_text())
    assert frame_summary([frame_files]).iloc[0]["walls"] is pd.NA  # a mesh from elsewhere
    write_table(pd.DataFrame({"vertex": [0, 1, 2, 3], "thickness": NAN}), frame_files["thickness"])
    frame_files["measure"].write_text(json.dumps({**measure, "walls": 1}))
    row = frame_summary([frame_files]).iloc[0]
    assert row["walls"] == 1 and row["thickness_valid"] == 0.0 and "thickness" not in row["qc_flags"]
    frame_files["measure"].write_text(json.dumps({**measure, "walls": 2}))
    assert "thickness found at 0 %" in frame_summary([frame_files]).iloc[0]["qc_flags"]
    objects = [{**measure, "object": k} for k in (0, 1)]
    frame_files["measure"].write_text(json.dumps({**measure, "walls": [2, 1], "objects": objects}))
    out = frame_summary([frame_files])
    assert list(out["walls"]) == [2, 1] and str(out["walls"].dtype) == "Int64"


def test_frame_summary_flags_walls_that_change_over_time(frame_files, tmp_path):
    """split: auto counts walls per frame: the time point whose object lost its inner wall is
    flagged against the series' usual count; a series of constant walls is not."""
    measure = json.loads(frame_files["measure"].read_text())
    records = []
    for t, walls in enumerate((2, 2, 1, 2)):
        path = tmp_path / f"measure{t}.json"
        path.write_text(json.dumps({**measure, "walls": walls}))
        records.append({**frame_files, "t": t, "measure": path, "thickness": None})
    out = frame_summary(records)
    assert out["walls"].tolist() == [2, 2, 1, 2]
    flagged = out["qc_flags"].str.contains("where most time points have 2").tolist()
    assert flagged == [False, False, True, False] and not out["qc_pass"][2]
    same = frame_summary([{**r, "measure": records[0]["measure"]} for r in records])
    assert not same["qc_flags"].str.contains("most time points").any()
    # two objects (keep: all): a shell and a droplet whose area ranks swap at t = 1 are not
    # flagged; the droplet opening a cavity at t = 4 is
    objects = [{**measure, "object": k} for k in (0, 1)]
    records.append({**records[-1], "t": 4, "measure": tmp_path / "measure4.json"})
    for t, walls in enumerate(([2, 1], [1, 2], [2, 1], [2, 1], [2, 2])):
        records[t]["measure"].write_text(json.dumps({**measure, "walls": walls, "objects": objects}))
    out = frame_summary(records)
    flagged = out["qc_flags"].str.contains("where most time points have").tolist()
    assert out["walls"].tolist() == [2, 1, 1, 2, 2, 1, 2, 1, 2, 2]
    assert flagged == [False] * 9 + [True]


def _series_with(frame_files: dict, tmp_path, key: str, values: list) -> pd.DataFrame:
    """frames.parquet of a series of time points whose measure files carry ``key``: ``values[t]``."""
    measure = json.loads(frame_files["measure"].read_text())
    records = []
    for t, value in enumerate(values):
        path = tmp_path / f"{key}{t}.json"
        path.write_text(json.dumps({**measure, key: value}))
        records.append({**frame_files, "t": t, "measure": path, "thickness": None})
    return frame_summary(records)


def test_frame_summary_flags_a_level_correction_unlike_its_series(frame_files, tmp_path):
    """The half level's correction (``edge_check.correction``, the share of the way to the walls' profiles' level)
    is ``level_correction``; the time point whose share differs by more than 0.5 from its series' median time
    point's, either way, is flagged; a series that agrees, a tie of two frames and frames without a check (NaN) are
    not; an older record's ``corrected`` counts whole."""
    measure = json.loads(frame_files["measure"].read_text())

    def series(corrections):
        checks = [None if value is None else {"corrected": value > 0, "correction": value, "offset": 0.06}
                  for value in corrections]
        return _series_with(frame_files, tmp_path, "edge_check", checks)

    flag = "of the way to the walls' profiles' level"
    out = series([0.0, 0.1, 1.0, 0.0])
    assert out["level_correction"].tolist() == [0.0, 0.1, 1.0, 0.0]
    assert out["qc_flags"].str.contains(flag).tolist() == [False, False, True, False] and not out["qc_pass"][2]
    assert "moved 100 % of the way" in out["qc_flags"][2] and "walls step thinner" in out["qc_flags"][2]
    out = series([1.0, None, 0.0, 0.8])
    assert out["qc_flags"].str.contains(flag).tolist() == [False, False, True, False]
    assert "walls step thicker" in out["qc_flags"][2] and pd.isna(out["level_correction"][1])
    for values in ([0.5, 0.6, 0.4], [1.0, 0.0], [None, None], [0.45, 0.55, 0.5, 0.0]):
        assert not series(values)["qc_flags"].str.contains(flag).any(), values
    # each time point counts once, whatever its objects (keep: all): two two-object time points corrected, three
    # one-object ones not: the two are flagged (a review: counted by rows, 4 to 3, the three were)
    records = []
    for t, value in enumerate([1.0, 1.0, 0.0, 0.0, 0.0]):
        path = tmp_path / f"objects{t}.json"
        n = 2 if value else 1
        path.write_text(json.dumps({**measure, "objects": [{**measure, "object": k} for k in range(n)],
                                    "edge_check": {"corrected": value > 0, "correction": value}}))
        records.append({**frame_files, "t": t, "measure": path, "thickness": None})
    out = frame_summary(records)
    assert len(out) == 7 and out.groupby("t")["qc_flags"].agg(lambda f: f.str.contains(flag).all()).tolist() == [
        True, True, False, False, False]
    assert not out[out["t"] >= 2]["qc_flags"].str.contains(flag).any()
    path = tmp_path / "old.json"
    path.write_text(json.dumps({**measure, "edge_check": {"corrected": True, "offset": 0.05}}))
    assert frame_summary([{**frame_files, "measure": path}])["level_correction"][0] == 1.0

def test_frame_summary_morphology_only_and_sorting(frame_files, tmp_path):
    """Records without curvature, thickness or layer tables give NaN / <NA> there; missing
    measure values (null) are NaN; rows are sorted by t, c, layer whatever the input order."""
    (tmp_path / "m0.json").write_text(json.dumps({"area": 3.0, "volume": 1.0, "euler_characteristic": 2,
                                                  "mean_H": None}))
    bare = {"t": 0, "c": 1, "layer": "whole", "surface": "whole", "measure": tmp_path / "m0.json",
            "curvature": None, "thickness": None}
    apical = dict(frame_files, layer="apical")
    out = frame_summary([frame_files, bare, apical])
    assert list(zip(out["t"], out["c"], out["layer"])) == [(0, 1, "whole"), (1, 0, "apical"), (1, 0, "basal")]
    row = out.iloc[0]
    assert row["area"] == 3.0 and row["volume"] == 1.0
    for key in ("H_mean", "K_mean", "H_fit_mean", "thickness_mean", "thickness_valid", "S_mean",
                "intensity_mean", "charge_sum", "peel_nan_fraction", "coherency_median"):
        assert np.isnan(row[key]), key
    assert pd.isna(row["n_defects"]) and pd.isna(row["n_directors"])
    assert out.iloc[1]["n_defects"] == out.iloc[2]["n_defects"] == 3


GOOD = {"euler_characteristic": 2.0, "thickness_valid": 1.0, "n_directors": 100, "S_mean": 0.8,
        "charge_sum": 2.01, "n_defects": 4}
CLOSED = {"n_components": 1, "n_boundary_loops": 0}


def test_defects_the_model_did_not_place_count_as_misfit():
    """Where the model fit was asked for (refine: model) and found no core within reach, the defect was placed by
    the averaged field's zero or left at its vertex: in 75 frames of five generators each of the 14 such was
    11-76 µm from any defect (with sparse directors often right, but those frames miss defects too), so the
    frame's defects_misfit counts them; zeros (+1 among Q-zeros) do not."""
    from nemo.summary import _unfitted

    defects = pd.DataFrame({"refine": ["model", "q", "vertex", "zeros", "model"]})
    assert _unfitted(defects) == 2 and _unfitted(defects.iloc[[0, 3]]) == 0
    assert _unfitted(pd.DataFrame({"x": [1.0]})) == 0  # a table from before the column


def test_a_defects_misfit_is_its_residual_beyond_its_directors_scatter_and_its_cores_uncertainty():
    """defects_misfit counts a defect whose model residual exceeds its directors' own scatter by more than 20°
    (√(residual² − scatter²): noisy directors that follow a defect read their noise as both) or whose core's
    standard error exceeds 0.15 of the fit radius; a table from before fit_scatter is judged on its residual."""
    from nemo.summary import _layer_columns, defect_misfit

    defects = pd.DataFrame({
        "charge": [0.5] * 5, "charge_rounded": [0.5] * 5, "coherency": [1.0] * 5,
        "fit_residual": [25.0, 25.0, 10.0, 10.0, np.nan],
        "fit_scatter": [5.0, 24.0, 9.0, 9.0, np.nan],  # a misplaced core; noisy directors that follow it
        "fit_uncertainty": [1.0, 2.0, 1.0, 4.0, np.nan], "fit_radius": [15.0, 15.0, 15.0, 15.0, np.nan]})
    excess, uncertainty = defect_misfit(defects)
    np.testing.assert_allclose(excess[:4], [math.sqrt(25**2 - 5**2), 7.0, math.sqrt(19.0), math.sqrt(19.0)])
    np.testing.assert_allclose(uncertainty[:4], np.array([1.0, 2.0, 1.0, 4.0]) / 15.0)
    assert np.isnan(excess[4]) and np.isnan(uncertainty[4])
    tables = {"directors": pd.DataFrame({"coherency": [1.0]}), "order": pd.DataFrame({"S": [0.5]}), "defects": defects}
    row = _layer_columns(tables)
    assert row["defects_misfit"] == 2  # the misplaced core, and the uncertain one (4 / 15 > 0.15)
    assert row["defect_residual_max"] == pytest.approx(math.sqrt(600.0))
    assert row["defect_uncertainty_max"] == pytest.approx(4.0 / 15.0)
    old = defects.drop(columns=["fit_scatter", "fit_uncertainty"])  # a table from before the columns
    assert _layer_columns({**tables, "defects": old})["defects_misfit"] == 2  # both residuals of 25°
    assert np.isnan(defect_misfit(defects.drop(columns=["fit_radius"]))[1]).all()  # a hand-made table: no ratio
    infinite = defects.assign(fit_uncertainty=[math.inf] * 4 + [np.nan])  # a fit that does not fix the core
    assert _layer_columns({**tables, "defects": infinite})["defect_uncertainty_max"] == math.inf


@pytest.mark.parametrize("change, measure, expected", [
    ({}, CLOSED, []),
    ({"charge_sum": 1.5, "n_defects": 3}, CLOSED, ["Σ charge 1.50 ≠ χ 2 (3 defects)"]),
    ({"charge_sum": 2.24}, CLOSED, []),                      # within the ±0.25 tolerance
    ({"charge_sum": 0.0, "n_defects": 0}, CLOSED, ["Σ charge 0.00 ≠ χ 2 (0 defects)"]),
    ({"charge_sum": 0.5}, {"n_components": 1, "n_boundary_loops": 1}, []),   # open: not checked
    ({"euler_characteristic": 0.0, "charge_sum": 0.0}, CLOSED, []),          # a torus passes
    ({"euler_characteristic": -589.0, "charge_sum": 1.5}, CLOSED,
     ["surface χ = -589: holes or handles (porous mesh?)", "Σ charge 1.50 ≠ χ -589 (4 defects)"]),
    ({}, {"n_components": 3, "n_boundary_loops": 0}, ["surface has 3 pieces"]),
    ({"charge_sum": 0.5}, {"n_components": 1, "n_boundary_loops": 2}, []),   # two small tears
    ({"charge_sum": 0.0}, {"n_components": 1, "n_boundary_loops": 7, "rim_loops": 7}, []),  # cut by the border
    ({"charge_sum": 0.0}, {"n_components": 1, "n_boundary_loops": 9, "rim_loops": 2},
     ["surface has 7 holes besides its rim on the image border (a porous or torn wall?)"]),
    # one wide opening (a shell whose top faded with depth: a cup): the disc its loop spans, L² / 4π, against the area
    ({"charge_sum": 0.5}, {"n_components": 1, "n_boundary_loops": 1, "rim_loops": 0, "largest_hole": 185.0,
                           "area": 3370.0, "unit": "um"},
     ["surface has an opening 58.9 µm across besides its rim on the image border (the disc it spans is 81 % of the "
      "surface's area): a wall that faded below the level (with depth, or uneven light) or tore away, its area short "
      "and no volume, or an object open there (a cup)"]),
    ({"charge_sum": 0.5}, {"n_components": 1, "n_boundary_loops": 2, "rim_loops": 0, "largest_hole": 26.1,
                           "area": 4928.0}, []),  # a small tear: 1.1 % of the area
    ({"charge_sum": 0.5}, {"n_components": 1, "n_boundary_loops": 1, "rim_loops": 0, "largest_hole": None,
                           "area": 4928.0}, []),  # not recorded (an imported surface)
    ({"thickness_valid": 0.5}, CLOSED, ["thickness found at 50 % of vertices"]),
    ({"thickness_valid": 0.0, "walls": 1}, CLOSED, []),  # one wall (split: auto): no thickness to find
    ({"thickness_valid": 0.0, "walls": 2}, CLOSED, ["thickness found at 0 % of vertices"]),
    # cut by the border: the rays and samples that leave the field of view are not counted
    ({"thickness_valid": 0.8, "thickness_valid_in_view": 1.0, "thickness_beyond_view": 200, "peel_nan_fraction": 0.12,
      "peel_nan_in_view": 0.0}, {"n_components": 1, "n_boundary_loops": 1, "rim_loops": 1}, []),
    ({"thickness_valid": 0.7, "thickness_valid_in_view": 0.85, "thickness_beyond_view": 150, "peel_nan_fraction": 0.2,
      "peel_nan_in_view": 0.1}, {"n_components": 1, "n_boundary_loops": 1, "rim_loops": 1},
     ["thickness found at 85 % of vertices in view",
      "10 % of vertices have no layer intensity within the field of view (NaN voxels?)"]),
    # no ray in view found the other wall: the flag still says it counts those in view
    ({"thickness_valid": 0.0, "thickness_valid_in_view": 0.0, "thickness_beyond_view": 300},
     {"n_components": 1, "n_boundary_loops": 1, "rim_loops": 1}, ["thickness found at 0 % of vertices in view"]),
    ({"peel_nan_fraction": 0.12, "peel_nan_in_view": 0.0}, CLOSED,  # closed: every vertex counts
     ["12 % of vertices have no layer intensity (samples outside the image?)"]),
    # an imported open surface records no rim_loops: open, the samples beyond the view are forgiven
    ({"peel_nan_fraction": 0.12, "peel_nan_in_view": 0.0}, {"n_components": 1, "n_boundary_loops": 1,
                                                            "rim_loops": None}, []),
    # open through holes only, not cut by the border: every vertex counts
    ({"peel_nan_fraction": 0.12, "peel_nan_in_view": 0.0}, {"n_components": 1, "n_boundary_loops": 1, "rim_loops": 0},
     ["12 % of vertices have no layer intensity (samples outside the image?)"]),
    ({"n_directors": 0, "S_mean": NAN}, CLOSED, ["no directors"]),
    ({"peel_nan_fraction": 0.05, "order_nan_fraction": 0.0, "coherency_median": 0.2}, CLOSED, []),
    ({"peel_nan_fraction": 0.081}, CLOSED,
     ["8 % of vertices have no layer intensity (samples outside the image?)"]),
    ({"order_nan_fraction": 0.5}, CLOSED,
     ["50 % of vertices have no order value (no tangent plane or director in reach)"]),
    ({"coherency_median": 0.12}, CLOSED, ["median director coherency 0.12: hardly any orientation"]),
    ({"coherency_median": 0.35, "coherency_noise": 0.51}, CLOSED,
     ["median director coherency 0.35, below white noise's 0.51 with these patches: no texture to orient "
      "(noise, or no fibres at that depth)"]),
    ({"coherency_median": 0.8, "coherency_noise": 0.51}, CLOSED, []),
    # every ray left the field of view: no thickness in view, all count
    ({"thickness_valid": 0.0, "thickness_valid_in_view": NAN}, {"n_components": 1, "n_boundary_loops": 1},
     ["thickness found at 0 % of vertices"]),
    ({"curvature_nan_fraction": 0.5}, CLOSED, []),
    ({"curvature_noise": 0.11, "curvature_reach": 0.95}, CLOSED, []),
    ({"curvature_reach": 1.07}, CLOSED,
     ["curvature fitted over a radius 1.1 × the surface's typical radius of curvature: H and K are flattened (a "
      "tube or a neck narrower than the fit; a curvature.radius below the radius of curvature fits it)"]),
    ({"curvature_noise": NAN}, CLOSED, []),
    ({"curvature_noise": 0.25}, CLOSED,
     ["curvature dominated by noise: the fits scatter by 25 % of the surface's typical curvature, so H and K per "
      "vertex are noisy (median errors of 8 % or more in tests; a noisy wall, or a surface curved on the scale of a "
      "few mesh edges)"]),
    ({"curvature_nan_fraction": 0.65}, CLOSED, ["no curvature at 65 % of vertices (the fit radius reaches the rim)"]),
    ({"snr": 2.4}, CLOSED, ["low signal-to-noise ratio 2.4 in the segmented channel"]),
    ({"snr": 3.0}, {**CLOSED, "n_objects": 1}, []),
    ({}, {**CLOSED, "saturated": 0.25}, ["25.0 % of the object's core saturated: walls placed outward, thickness "
                                          "overestimated (lower the gain or the exposure)"]),
    ({}, {**CLOSED, "saturated": 0.10}, []),
    ({}, {**CLOSED, "saturated": None}, []),
    ({}, {**CLOSED, "n_objects": 3}, ["3 objects in the image (see the mesh step's warning)"]),
    # the half level checked against the walls' own profiles (nemo.surface._edge_check)
    ({}, {**CLOSED, "edge_check": {"offset": 0.13, "limit": 0.1, "misfit": 0.02}},
     ["the walls' own profiles put their edges 13 % of the contrast above the half level: walls placed outward, "
      "thickness overestimated (thin or z-blurred walls; mesh.edge: profile meshes at the profiles' level, "
      "with psf: auto or none)"]),
    ({}, {**CLOSED, "edge_check": {"offset": -0.2, "limit": 0.1, "misfit": 0.01}},
     ["the walls' own profiles put their edges 20 % of the contrast below the half level: walls placed inward, "
      "thickness underestimated (thin or z-blurred walls; mesh.edge: profile meshes at the profiles' level, "
      "with psf: auto or none)"]),
    ({}, {**CLOSED, "edge_check": {"offset": 0.05, "limit": 0.1}}, []),
    # partly corrected: the offset the correction leaves is judged (0.75 of 0.105 left passes, 0.9 of 0.12 does not)
    ({}, {**CLOSED, "edge_check": {"offset": 0.105, "limit": 0.1, "correction": 0.25, "corrected": True}}, []),
    ({}, {**CLOSED, "edge_check": {"offset": 0.12, "limit": 0.1, "correction": 0.1, "corrected": True}},
     ["the walls' own profiles put their edges 12 % of the contrast above the half level: walls placed outward, "
      "thickness overestimated (thin or z-blurred walls; mesh.edge: profile meshes at the profiles' level, "
      "with psf: auto or none)"]),
    ({}, {**CLOSED, "edge_check": {"offset": None, "limit": 0.1, "misfit": 0.3}}, []),  # textured walls: no check
    ({}, {**CLOSED, "edge_check": None}, []),
    ({}, {**CLOSED, "edge_check": {"offset": None, "limit": 0.1, "misfit": 0.01, "thinner_than_blur": 0.14}},
     ["the walls are thinner than the image's blur on 14 % of their profiles: they come out about as thick as the "
      "blur, thickness overestimated (a z-elongated PSF? psf: deconvolves by a known PSF; or a bright film by the "
      "wall's surface)"]),
    ({}, {**CLOSED, "edge_check": {"offset": None, "limit": 0.1, "misfit": 0.01, "thinner_than_blur": 0.3,
                                   "image": "before deconvolution"}},  # a deconvolved frame: no advice to deconvolve
     ["the walls are thinner than the image's blur on 30 % of their profiles: they come out about as thick as the "
      "blur, thickness overestimated (a z-elongated PSF? deconvolving did not thin them; or a bright film by the "
      "wall's surface)"]),
    ({}, {**CLOSED, "edge_check": {"offset": 0.02, "limit": 0.1, "misfit": 0.01, "thinner_than_blur": None}}, []),
    ({"regions": 2}, CLOSED, ["the surface holds 2 separate bright regions of the image: touching objects meshed as "
                              "one, their area and volume together (a mask that labels them apart separates them)"]),
    ({"regions": 1}, CLOSED, []),
    ({"regions": 3}, {**CLOSED, "mask_offset": 0.1, "mask_offset_limit": 0.5, "mask_contrast": 45.0},
     ["the surface holds 3 large labels of the mask that touch: objects meshed as one, their area and volume "
      "together (mask_labels selects one; mesh.keep: all keeps every label apart)"]),
    ({}, {**CLOSED, "mask_offset": 1.4, "mask_offset_limit": 0.5, "mask_contrast": 45.0},
     ["the mask lies 1.4 (median) from the segmented channel's edges, more than 0.5 (a mask of another time point, "
      "channel or class?)"]),
    ({}, {**CLOSED, "mask_offset": 0.09, "mask_offset_limit": 0.5, "mask_contrast": 86.0}, []),
    ({}, {**CLOSED, "mask_offset": 0.2, "mask_offset_limit": 0.5, "mask_contrast": -40.0},
     ["the mask holds the darker side of the segmented channel (a background or cavity class? check mask_channel)"]),
    ({"regions": None}, CLOSED, []),
    ({"regions": pd.NA}, CLOSED, []),
    ({"defects_faint": 1, "defect_coherency_min": 0.72}, CLOSED,
     ["1 defect(s) where the fibres are faint (coherency 0.72 below 0.85 of the surface's): a low S there says "
      "little, the position is uncertain (fibres across a z-elongated PSF fade; where the frame was not "
      "deconvolved (psf: none, or auto found no z blur), the measured PSF as datasets.NAME.psf helps)"]),
    ({"defects_faint": 2}, CLOSED,  # a row of frames.parquet: the count only
     ["2 defect(s) where the fibres are faint (coherency below 0.85 of the surface's): a low S there says "
      "little, the position is uncertain (fibres across a z-elongated PSF fade; where the frame was not "
      "deconvolved (psf: none, or auto found no z blur), the measured PSF as datasets.NAME.psf helps)"]),
    ({"defects_faint": 0, "defect_coherency_min": 0.9}, CLOSED, []),
    ({"defects_faint": pd.NA}, CLOSED, []),
    ({"defects_misfit": 1, "defect_residual_max": 31.2, "defect_uncertainty_max": 0.12}, CLOSED,
     ["1 defect(s) the directors do not place (their fit residual beyond their own scatter up to 31° (limit 20°), the "
      "core's standard error up to 0.12 (limit 0.15) of the fit radius, or no core within reach): the position is "
      "uncertain (placed off the core, a texture the directors do not read, or directors too noisy or sparse; the "
      "defects table's fit_residual, fit_scatter, fit_uncertainty and refine)"]),
    ({"defects_misfit": 1, "defect_residual_max": 4.0, "defect_uncertainty_max": math.inf}, CLOSED,
     ["1 defect(s) the directors do not place (their fit residual beyond their own scatter up to 4° (limit 20°), the "
      "core's standard error unbounded (limit 0.15) of the fit radius, or no core within reach): the position is "
      "uncertain (placed off the core, a texture the directors do not read, or directors too noisy or sparse; the "
      "defects table's fit_residual, fit_scatter, fit_uncertainty and refine)"]),
    ({"defects_misfit": 2}, CLOSED,  # a row of frames.parquet: the count only (or unfitted defects alone)
     ["2 defect(s) the directors do not place (their fit residual beyond their own scatter above 20°, the core's "
      "standard error above 0.15 of the fit radius, or no core within reach): the position is uncertain (placed off "
      "the core, a texture the directors do not read, or directors too noisy or sparse; the defects table's "
      "fit_residual, fit_scatter, fit_uncertainty and refine)"]),
    ({"defects_misfit": 0, "defect_residual_max": 12.0}, CLOSED, []),
    ({"defects_misfit": pd.NA}, CLOSED, []),
    ({"rejected_zeros": 2}, CLOSED,
     ["2 zero(s) of the averaged order rejected (a disordered contour or an unresolved winding, or a zero charge "
      "round them): defects closer together than the contour radius may be missed there (a missed ± pair keeps "
      "Σ charge = χ)"]),
    ({"rejected_zeros": 0}, CLOSED, []),
    ({"rejected_zeros": pd.NA}, CLOSED, []),
    # a layer outward from the outline of an object of one wall samples the background (an independent
    # review: a hollow torus taken for one wall read its edge's directors, 79° off, and passed)
    ({"reaches_out": True, "walls": 1}, CLOSED,
     ["the object has one wall, so the layer's range from its outline reaches outside it: its directors are the "
      "background's or the edge's (peel inward: layers.NAME.inward true; for a shell, mesh.split: centre)"]),
    ({"reaches_out": True, "walls": 2}, CLOSED, []),
    ({"reaches_out": False, "walls": 1}, CLOSED, []),
])
def test_quality_flags_name_each_reason(change, measure, expected):
    assert quality_flags({**GOOD, **change}, measure) == expected


def test_quality_flags_of_a_morphology_only_row_check_the_surface():
    row = {"euler_characteristic": 2.0, "thickness_valid": NAN}
    assert quality_flags(row, CLOSED) == []
    assert quality_flags({**row, "euler_characteristic": -40.0}, CLOSED) == [
        "surface χ = -40: holes or handles (porous mesh?)"]


def test_frame_summary_of_nothing_is_an_empty_table():
    out = frame_summary([])
    assert len(out) == 0 and list(out.columns) == list(FRAME_COLUMNS)


def test_frame_summary_bad_measure_file(frame_files, tmp_path):
    with pytest.raises(NemoError, match="measure file not found"):
        frame_summary([dict(frame_files, measure=tmp_path / "nope.json")])
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(NemoError, match="nemo measure --json"):
        frame_summary([dict(frame_files, measure=tmp_path / "bad.json")])
    with pytest.raises(NemoError, match="table not found"):
        frame_summary([dict(frame_files, order=tmp_path / "nope.parquet")])


# ----------------------------------------------------------------------------- collect_defects
def test_collect_defects_keys_order_and_tracking_distance(tmp_path):
    write_table(_defects([0.5, -0.5], [0.5, -0.5], extra_col=[7, 8]), tmp_path / "a.parquet",
                parameters={"min_distance": 30.0})
    write_table(_defects([1.0], [1.0]), tmp_path / "b.parquet", parameters={"min_distance": 12.0})
    write_table(_defects([], []), tmp_path / "empty.parquet", parameters={"min_distance": 5.0})
    write_table(_defects([0.5], [0.5]), tmp_path / "noprov.parquet")  # no parameters recorded
    records = [
        {"t": 2, "c": 0, "layer": "basal", "defects": tmp_path / "a.parquet"},
        {"t": 0, "c": 1, "layer": "apical", "defects": tmp_path / "b.parquet"},
        {"t": 0, "c": 0, "layer": "basal", "defects": tmp_path / "empty.parquet"},
        {"t": 0, "c": 0, "layer": "apical", "defects": tmp_path / "noprov.parquet"},
    ]
    out = collect_defects(records)
    assert list(out.columns[: len(DEFECT_COLUMNS)]) == list(DEFECT_COLUMNS)
    assert {"min_distance", "extra_col"} <= set(out.columns)
    assert list(zip(out["t"], out["c"], out["layer"])) == [(0, 0, "apical"), (0, 1, "apical"),
                                                          (2, 0, "basal"), (2, 0, "basal")]
    # input order kept within a frame-layer
    np.testing.assert_array_equal(out["charge"], [0.5, 1.0, 0.5, -0.5])
    np.testing.assert_array_equal(out["x"], [0.0, 0.0, 0.0, 1.0])
    assert np.isnan(out["min_distance"].iloc[0])
    np.testing.assert_array_equal(out["min_distance"].iloc[1:], [12.0, 30.0, 30.0])
    np.testing.assert_array_equal(out["extra_col"].iloc[2:], [7, 8])
    assert out["t"].dtype == np.int64 and out["c"].dtype == np.int64


def test_collect_defects_without_any_defect():
    assert len(collect_defects([])) == 0


def test_collect_defects_of_empty_tables_has_the_columns(tmp_path):
    """An empty dataset's table has the columns of one with defects (an independent review: it lacked
    min_distance and object_id, so datasets no longer concatenated)."""
    write_table(_defects([], []), tmp_path / "empty.parquet")
    write_table(_defects([0.5], [0.5]), tmp_path / "one.parquet", parameters={"min_distance": 5.0})
    empty = [{"t": 0, "c": 0, "layer": "basal", "defects": tmp_path / "empty.parquet"}]
    out = collect_defects(empty)
    assert len(out) == 0 and list(out.columns)[:len(DEFECT_COLUMNS)] == list(DEFECT_COLUMNS)
    frames = pd.DataFrame({"t": [0], "c": [0], "layer": ["basal"], "object": [0], "object_id": pd.array([0], "Int64"),
                           "qc_pass": [True], "qc_flags": [""]})
    one = [{**empty[0], "defects": tmp_path / "one.parquet"}]
    for got, full in ((out, collect_defects(one)), (collect_defects(empty, frames), collect_defects(one, frames)),
                      (collect_defects([], frames), None)):
        if full is not None:
            assert list(got.columns) == list(full.columns)
            assert got.dtypes.to_dict() == full.dtypes.to_dict()
        assert got["t"].dtype == np.int64 and got["vertex"].dtype == np.int64 and "min_distance" in got


def test_collect_defects_carries_each_frames_quality_control(tmp_path):
    """A time-lapse review's tracks ran through the defects of frames that failed the QC (a channel
    without texture, a frame that missed a defect) with nothing to tell them apart: each defect
    now carries its frame's (object's) qc_pass and qc_flags; one of no summarised frame is not
    vouched for."""
    write_table(_defects([0.5, 0.5], [0.5, 0.5]), tmp_path / "a.parquet", parameters={"min_distance": 5.0})
    write_table(_defects([0.5], [0.5]), tmp_path / "b.parquet", parameters={"min_distance": 5.0})
    records = [{"t": 0, "c": 0, "layer": "fibres", "defects": tmp_path / "a.parquet"},
               {"t": 1, "c": 0, "layer": "fibres", "defects": tmp_path / "b.parquet"},
               {"t": 2, "c": 0, "layer": "fibres", "defects": tmp_path / "b.parquet"}]
    frames = pd.DataFrame({"t": [0, 1], "c": [0, 0], "layer": ["fibres", "fibres"], "object": [0, 0],
                           "qc_pass": [True, False], "qc_flags": ["", "low SNR"]})
    out = collect_defects(records, frames)
    assert list(out["qc_pass"]) == [True, True, False, False]
    assert list(out["qc_flags"]) == ["", "", "low SNR", "no frame summary"]
    assert list(collect_defects([], frames).columns)[-2:] == ["qc_pass", "qc_flags"]
    assert "qc_pass" not in collect_defects(records).columns


# ----------------------------------------------------------------------------- alignment_summary
def test_alignment_summary_statistics(tmp_path):
    write_table(pd.DataFrame({"vertex": range(5), "c": [1.0, -1.0, 0.0, 0.8, NAN]}), tmp_path / "a.parquet")
    write_table(pd.DataFrame({"vertex": [0, 1], "c": [NAN, NAN]}), tmp_path / "none.parquet")
    out = alignment_summary([
        {"t": 1, "c": 0, "layer_a": "basal", "layer_b": "apical", "align": tmp_path / "a.parquet"},
        {"t": 0, "c": 0, "layer_a": "basal", "layer_b": "apical", "align": tmp_path / "none.parquet"},
    ])
    assert list(out.columns) == list(ALIGN_COLUMNS)
    assert out["t"].tolist() == [0, 1]
    empty, row = out.iloc[0], out.iloc[1]
    assert empty["n"] == 0
    for key in ALIGN_COLUMNS[5:-2]:
        assert np.isnan(empty[key]), key
    assert not empty["qc_pass"] and "no director of A was compared" in empty["qc_flags"]
    assert row["qc_pass"] and row["qc_flags"] == ""  # 4 of 5 compared; no frames given: no layer checked
    # finite c = [1, -1, 0, 0.8]
    assert row["n"] == 4
    assert row["c_mean"] == pytest.approx(0.2)
    assert row["c_median"] == pytest.approx(0.4)
    assert row["c_std"] == pytest.approx(math.sqrt((0.8**2 + 1.2**2 + 0.2**2 + 0.6**2) / 4))
    assert row["fraction_parallel"] == pytest.approx(0.5)      # 1.0 and 0.8 (> 0.5)
    assert row["fraction_orthogonal"] == pytest.approx(0.25)   # -1.0 (< -0.5)
    assert out["n"].dtype == np.int64
    assert np.isnan(row["c_avg_mean"]) and np.isnan(row["c_avg_median"])  # a table without c_avg


def test_alignment_summary_weights_the_averaged_alignment_by_order(tmp_path):
    """``c_avg_mean`` is the mean of c_avg weighted by S_A · S_B (``weight``); NaN or zero weights
    and NaN values are left out; ``c_avg_median`` is unweighted."""
    write_table(pd.DataFrame({"vertex": range(5), "c": [0.0] * 5, "c_avg": [-1.0, -0.8, 1.0, NAN, 0.5],
                              "weight": [0.9, 0.5, 0.1, 0.9, 0.0]}), tmp_path / "a.parquet")
    row = alignment_summary([{"t": 0, "c": 0, "layer_a": "a", "layer_b": "b", "align": tmp_path / "a.parquet"}]).iloc[0]
    assert row["c_avg_mean"] == pytest.approx((-0.9 - 0.4 + 0.1) / 1.5)
    assert row["c_avg_median"] == pytest.approx(-0.8)


def _layer_row(layer, **values):
    """A row of frames.parquet at t 0, c 0 that passes the alignment's checks unless ``values`` say otherwise."""
    return {"t": 0, "c": 0, "layer": layer, "object": 0, "snr": 12.0, "n_directors": 900, "coherency_median": 0.7,
            "coherency_noise": 0.5, "charge_sum": 2.0, **values}


@pytest.mark.parametrize("bad, flag", [
    ({"coherency_median": 0.44, "coherency_noise": 0.54}, "layer b: median director coherency 0.44, below white noise's"),
    ({"coherency_median": 0.1}, "layer b: median director coherency 0.10: hardly any orientation"),
    ({"snr": 2.1}, "layer b: low signal-to-noise ratio 2.1"),
    ({"n_directors": 0}, "layer b: no directors"),
    ({"n_directors": pd.NA}, "layer b: no directors"),
])
def test_alignment_fails_with_a_layer_whose_field_is_noise(tmp_path, bad, flag):
    """The pair fails when either layer's field is noise (its frame row's SNR, director count or
    coherency); the layer's flags that do not concern its field (Σ charge ≠ χ) are not the pair's."""
    write_table(pd.DataFrame({"vertex": range(4), "c": [-1.0, -0.9, -1.0, -0.8]}), tmp_path / "a.parquet")
    record = {"t": 0, "c": 0, "layer_a": "a", "layer_b": "b", "align": tmp_path / "a.parquet"}
    frames = pd.DataFrame([_layer_row("a", charge_sum=1.0, qc_pass=False, qc_flags="Σ charge 1.00 ≠ χ 2"),
                           _layer_row("b"), _layer_row("b", t=1, snr=1.0)])  # another frame's row is not this pair's
    good = alignment_summary([record], frames).iloc[0]
    assert good["qc_pass"] and good["qc_flags"] == ""
    frames.loc[1, list(bad)] = pd.Series(bad)
    row = alignment_summary([record], frames).iloc[0]
    assert not row["qc_pass"] and row["qc_flags"].startswith(flag), row["qc_flags"]
    assert row["c_mean"] == pytest.approx(-0.925)  # the statistics are the same


def test_alignment_fails_when_few_directors_are_compared_and_names_the_object(tmp_path):
    write_table(pd.DataFrame({"vertex": range(4), "c": [-1.0, NAN, NAN, NAN]}), tmp_path / "a.parquet")
    frames = pd.DataFrame([_layer_row("a"), _layer_row("b"), _layer_row("b", object=1, coherency_median=0.05),
                           _layer_row("b", object=2, n_directors=0)])  # a speck without directors: not the pair's
    record = {"t": 0, "c": 0, "layer_a": "a", "layer_b": "b", "align": tmp_path / "a.parquet"}
    row = alignment_summary([record], frames).iloc[0]
    flags = row["qc_flags"].split("; ")
    assert flags[0] == "only 25 % of layer a's directors compared with one of layer b"
    assert flags[1].startswith("layer b object 1: median director coherency 0.05") and len(flags) == 2
    # by area: a speck without directors is left out, a large object without any is the pair's concern
    frames["area"] = [900.0, 900.0, 850.0, 40.0]
    assert alignment_summary([record], frames).iloc[0]["qc_flags"] == row["qc_flags"]
    frames.loc[3, "area"] = 400.0
    flags = alignment_summary([record], frames).iloc[0]["qc_flags"].split("; ")
    assert flags[-1] == "layer b object 2: no directors" and len(flags) == 3


def test_alignment_summary_needs_a_c_column(tmp_path):
    write_table(pd.DataFrame({"vertex": [0]}), tmp_path / "a.parquet")
    with pytest.raises(NemoError, match="lacks column"):
        alignment_summary([{"t": 0, "c": 0, "layer_a": "a", "layer_b": "b", "align": tmp_path / "a.parquet"}])


def test_a_layer_without_directors_keeps_the_peels_flags_and_drops_their_consequences():
    """No directors: the peel's flags (samples outside the image, the texture out of the layer's
    range) are causes and stay; the order, coherency and charge flags follow from it and go."""
    from nemo.summary import quality_flags

    row = {"n_directors": 0, "S_mean": math.nan, "peel_nan_fraction": 1.0, "order_nan_fraction": 1.0,
           "coherency_median": math.nan, "texture": {"peak_depth": 7.0, "outside": True}, "charge_sum": 0.0,
           "n_defects": 0, "euler_characteristic": 2, "directors_skipped": "the layer's intensity is 0"}
    flags = quality_flags(row, {"euler_characteristic": 2})
    assert flags[0] == "no directors: the layer's intensity is 0"
    assert any("no layer intensity" in f for f in flags) and any("texture peaks at depth 7" in f for f in flags)
    assert not any("order value" in f or "Σ charge" in f for f in flags), flags


def test_an_empty_frame_gets_one_flag_that_says_so(frame_files, tmp_path):
    """An empty frame meshes noise specks (an end-to-end review: SNR 0.8–1.2, "109 objects", "turned
    out … a dark object in a bright surround", "1 wall(s) where most time points have 2 … set
    split: centre"): advice that does not apply. Below SNR 1.5 the frame gets one flag saying the
    channel looks empty; the series' flags skip it; a frame at SNR 2 keeps its low-SNR flag."""
    measure = json.loads(frame_files["measure"].read_text())
    records = []
    for t, (snr, walls, loops) in enumerate(((8.0, 2, 0), (8.0, 2, 0), (1.1, 1, 3), (8.0, 2, 0), (2.0, 2, 0))):
        path = tmp_path / f"measure{t}.json"
        path.write_text(json.dumps({**measure, "snr": snr, "walls": walls, "n_boundary_loops": loops,
                                    "n_objects": 109 if snr < 1.5 else 1, "turned_out": int(snr < 1.5)}))
        records.append({**frame_files, "t": t, "measure": path})
    out = frame_summary(records)
    assert out["qc_flags"][2].startswith("the segmented channel looks empty (SNR 1.1 < 1.5)")
    assert ";" not in out["qc_flags"][2] and not out["qc_pass"][2]
    assert "low signal-to-noise ratio 2.0" in out["qc_flags"][4] and "looks empty" not in out["qc_flags"][4]
    assert not out["qc_flags"].str.contains("most time points").any()



def test_curvature_noise_of_a_nearly_flat_surface_is_not_its_own_curvature():
    """On a plane the median largest |k| is the fits' own noise, so their scatter over it reads ~1
    whatever the noise (a review: a plane of 0.02 µm roughness flagged). The typical curvature is at
    least 0.25 / the surface's size √(A/4π); a sphere's own curvature (1 / its size) is above that and
    sets the ratio, however large the sphere (a big vesicle fitted at a small radius keeps its ratio)."""
    from nemo.summary import _curvature_scales

    rng = np.random.default_rng(0)
    k = rng.normal(0.0, 2e-4, (2, 500))
    plane = pd.DataFrame({"k1": k.max(0), "k2": k.min(0)})
    area = 100.0 * 100.0  # a 100 µm square: size 28.2 µm
    noise, reach = _curvature_scales(plane, {"fit_scatter_H": 1.9e-4, "radius": 15.0}, area)
    size = np.sqrt(area / (4 * np.pi))
    assert noise == pytest.approx(1.9e-4 * size / 0.25) and noise < 0.12 and reach == pytest.approx(15.0 * 0.25 / size)
    for radius, fitted in ((10.0, 6.0), (200.0, 12.0)):
        sphere = pd.DataFrame({"k1": np.full(500, 1 / radius), "k2": np.full(500, 1 / radius)})
        noise, reach = _curvature_scales(sphere, {"fit_scatter_H": 0.2 / radius, "radius": fitted},
                                         4 * np.pi * radius**2)
        assert noise == pytest.approx(0.2) and reach == pytest.approx(fitted / radius)


def test_frame_summary_flags_a_deconvolution_unlike_its_series(frame_files, tmp_path):
    """``psf_z`` is the σz the mesh's image was deconvolved by (``psf: auto``: estimated per frame), 0 where it was
    not, NaN where nothing was recorded; a time point deconvolved where most of its series is not, not where most
    is, or by a σz more than 25 % from the deconvolved time points' median, and by 0.75 planes, is flagged; a tie
    flags the deconvolved; a σz of half a plane against none is not (a review's time-lapse flipped there)."""

    def series(sigmas, dz=1.0):
        records = [None if value is None else {"psf": [value, 0.0, 0.0] if value else None, "estimated": True,
                                               "sigma_voxels": [value / dz, 0.0, 0.0] if value else None,
                                               "iterations": 30 if value else 0} for value in sigmas]
        return _series_with(frame_files, tmp_path, "deconvolution", records)

    flag = "psf: auto estimates each frame"
    out = series([2.0, 2.1, 0.0, 1.9])
    assert out["psf_z"].tolist() == [2.0, 2.1, 0.0, 1.9]
    assert out["qc_flags"].str.contains(flag).tolist() == [False, False, True, False] and not out["qc_pass"][2]
    assert "not deconvolved where most of its series is deconvolved by σz 2 (median)" in out["qc_flags"][2]
    out = series([0.0, 0.0, 2.2, None])
    assert out["qc_flags"].str.contains(flag).tolist() == [False, False, True, False] and pd.isna(out["psf_z"][3])
    assert "deconvolved by σz 2.2 where most of its series is not deconvolved" in out["qc_flags"][2]
    assert series([2.0, 2.0, 3.0])["qc_flags"].str.contains(flag).tolist() == [False, False, True]  # +50 %
    assert series([0.0, 2.0])["qc_flags"].str.contains(flag).tolist() == [False, True]  # a tie
    for values in ([2.0, 2.3, 1.8], [0.0, 0.0], [None, None], [1.5]):
        assert not series(values)["qc_flags"].str.contains(flag).any(), values
    assert not series([0.0, 1.04, 1.04, 1.04, 0.0], dz=2.0)["qc_flags"].str.contains(flag).any()  # 0.52 planes
    foreign = _series_with(frame_files, tmp_path, "deconvolution", [{"psf": [2.0, 0.0, 0.0], "iterations": 30}] * 2)
    assert foreign["psf_z"].tolist() == [2.0, 2.0] and not foreign["qc_flags"].str.contains(flag).any()
    assert series([0.0, 2.2, 2.2, 2.2, 0.0], dz=2.5)["qc_flags"].str.contains(flag).tolist() == [
        True, False, False, False, True]  # 0.88 planes
