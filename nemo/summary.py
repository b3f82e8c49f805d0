"""Aggregation of per-frame results into the summary tables of a time-lapse.

The workflow writes one folder per time point and channel (``results/{dataset}/t{t}/c{c}/``);
these functions collect the per-frame tables into ``results/{dataset}/summary/``:

* :func:`frame_summary` -> ``frames.parquet``: one row per (t, c, layer, object) with the objects found
  and signal-to-noise ratio of the image, the surface's area, volume, Euler characteristic, mean
  H and K, mean thickness, mean layer intensity, director count and coherency, mean S, number of
  defects, their total charge and the frame's quality control (``qc_pass``, ``qc_flags``);
* :func:`collect_defects` -> the defects of all frames with ``t``, ``c``, ``layer`` columns
  (``nemo track`` then adds ``track_id``);
* :func:`alignment_summary` -> ``alignment.parquet``: one row per (t, c, layer pair), with the pair's
  quality control (:func:`alignment_flags`).

Every input is described by a *record*: a dict of the frame's keys (``t``, ``c``, ``layer``...)
and the paths of its files. Nothing here recomputes science; it reads tables and averages.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np
import pandas as pd

from nemo._log import pretty_unit
from nemo.config import reaches_out_of_one_wall
from nemo.errors import NemoError
from nemo.objects import value_for
from nemo.tables import read_provenance, read_table
from nemo.track import link_objects

#: Columns of frames.parquet, in order (documented in docs/workflow.md).
FRAME_COLUMNS = (
    "t", "c", "layer", "object", "object_id", "surface", "n_objects", "walls", "regions", "centre_x", "centre_y",
    "centre_z", "snr", "saturated", "level_correction", "psf_z", "area", "volume", "euler_characteristic", "closed",
    "H_mean", "K_mean",
    "H_fit_mean", "K_fit_mean", "curvature_nan_fraction", "curvature_noise", "thickness_mean", "thickness_median",
    "thickness_valid", "intensity_mean", "peel_nan_fraction", "n_directors", "coherency_mean", "coherency_median",
    "coherency_noise", "S_mean", "S_median", "order_nan_fraction", "n_defects", "charge_sum", "charge_rounded_sum",
    "defects_faint", "defects_misfit", "rejected_zeros", "qc_pass", "qc_flags",
)
#: Largest |Σ charge − χ| of a closed surface's defects that passes quality control: a missed or
#: spurious ±½ defect changes the sum by 0.5, the curvature term's discretisation by ≪ 0.1.
QC_CHARGE_TOLERANCE = 0.25
#: Smallest fraction of vertices with a finite thickness that passes (rays that miss the other
#: surface mean the surfaces do not enclose each other there).
QC_MIN_THICKNESS_VALID = 0.9
#: Lowest Euler characteristic that passes: χ = 2 − 2g, so this allows a sphere, a torus and a
#: double torus; lower values come from porous meshes (holes through a noisy wall).
QC_MIN_EULER = -2
#: Most holes (boundary loops besides the rims where the image border cuts the object) that pass:
#: a few from a small tear; more mean a porous, torn wall.
QC_MAX_HOLES = 2
#: Largest disc a hole may span (its length L: L² / 4π) as a fraction of its surface's area: a wall that
#: faded below the level (with depth in a thick sample) or tore away leaves one wide opening, its area short
#: by more than that disc (an independent review's shells fading with depth: 0.5-0.8, their area −22 to −35 %;
#: a small tear 0.006-0.011, area −2 %).
QC_MAX_HOLE_SPAN = 0.05
#: Largest fraction of vertices without a curvature fit that passes (an open surface has a band
#: along its rim where the fit neighbourhood is cut; most of the surface must still be fitted).
QC_MAX_CURVATURE_NAN = 0.5
#: Largest scatter of the curvature fits about their average (``fit_scatter_H``) over the median largest
#: |principal curvature| that passes: above it H per vertex was off by 11-96 % in a review's 90 analyses of
#: shapes of known curvature (tubes, saddles, oblate rims at SNR 3-10; another review's R 10 µm droplet at 0.13:
#: 7.5 %), below it mostly 2-10 %.
QC_MAX_CURVATURE_NOISE = 0.12
#: Largest fit radius × the median largest |principal curvature| that passes: a fit wider than the surface's
#: typical radius of curvature flattens it (a review's torus of an 8 µm tube read H −24 % at 11.3 µm: 1.07).
QC_MAX_CURVATURE_REACH = 1.0
#: Least typical curvature, times the surface's size √(A/4π), that the curvature's noise is compared with: a
#: sphere reads 1, an open cap of R 60 µm cut to 40 µm across ~0.3; flatter surfaces count as this curved.
CURVATURE_FLAT = 0.25
#: Largest fraction of a layer's vertices without an intensity (samples outside the image or on
#: NaN voxels) or without an order value (no tangent plane, no director in reach) that passes.
QC_MAX_NAN_FRACTION = 0.05
#: Lowest median director coherency that passes: below it the layer's micro-images show
#: hardly any orientation (noise, or no fibres at that depth).
QC_MIN_COHERENCY = 0.2
#: Lowest signal-to-noise ratio of the segmented channel that passes (the issue's realistic
#: range is 3-10; below 3 the surface itself is uncertain).
QC_MIN_SNR = 3.0
#: Below this signal-to-noise ratio the segmented channel looks empty (noise alone reads about 1):
#: the frame gets that one flag, not the mesh's and the series' flags that follow from meshing noise.
QC_EMPTY_SNR = 1.5
#: Largest fraction of the object's core voxels at the detector's full scale that passes
#: (``nemo.surface.saturated_fraction``): above it the plateau reads low and the walls move out
#: (a shell's thickness +0.9 µm at 11 %, measured; bright fibres clipped in a few % of the core,
#: as in NEMO's synthetic vesicles at 6-8 %, leave the wall in place).
QC_MAX_SATURATED = 0.10
#: Lowest ``coherency`` of a defect (its directors' median coherency within the contour over the
#: surface's median, :func:`nemo.defects.find_defects`) that passes. A defect is ordered fibres
#: turning: each patch stays coherent (0.86-1.08 at the 50 defects found within 6 µm of the truth
#: in two generators' z-blurred vesicles, SNR 5-10). Where the fibres fade (across a z-PSF's long
#: axis) a low S says nothing of the field: 8 of 14 defects found 6-34 µm from any truth read
#: 0.69-0.84, and their frames passed, the count and Σ charge being right.
QC_MIN_DEFECT_COHERENCY = 0.85
#: Largest misfit of a defect's model that passes (degrees): its ``fit_residual`` (the RMS of its directors'
#: angles about the fitted defect model, :func:`nemo.defects.find_defects`) beyond their own ``fit_scatter``
#: (between neighbours), √(residual² − scatter²). Where the directors follow a defect what is left is their own
#: noise; a core placed where they do not turn as a defect's, or a texture they do not read, leaves a smooth
#: misfit their scatter does not hold. In 75 frames of five generators (SNR 3 to none, nemo's own directors,
#: whose scatter between neighbours is small, so the misfit is nearly the residual): defects within 3 µm of the
#: truth median 11.7°, more than 6 µm off 32.6°; no frame whose defects all lay within 3 µm read above 17.5°,
#: 18 of the 22 with one more than 6 µm off did or had one no fit placed (docs/validation.md, "Defects whose
#: directors do not follow the model"). Directors with independent noise (imported ones) read their noise as
#: residual and scatter alike: i.i.d. noise of 12-20° with 5 % outliers failed correct frames on the residual alone.
QC_MAX_DEFECT_RESIDUAL_DEG = 20.0
#: Largest ``fit_uncertainty`` of a defect (the fitted core's standard error, with its directors' scatter as
#: their noise) over its ``fit_radius`` that passes: noisy or sparse directors that follow a defect place it
#: only that well. Independent noise on a sphere R 60 µm, fit radius 16.9 µm (4 +½): 4 000 directors with 12 /
#: 20 / 30° read 0.08-0.11 / 0.11-0.18 / 0.15-0.24, frames' worst errors 2.4-2.8 / 3.5-4.8 / 5.5-6.2 µm; 16 000
#: with 20-30° and 5 % outliers 0.07-0.14, errors within 2.1 µm; 1 000 with 15° and outliers 0.33-0.95, errors
#: 3.7-12 µm. nemo's own directors read ~0.01 (their noise is correlated: docs/validation.md, "Noise or a
#: misplaced core").
QC_MAX_DEFECT_UNCERTAINTY = 0.15
#: Columns of defects.parquet before tracking (``nemo track`` appends ``track_id``).
DEFECT_COLUMNS = ("t", "c", "layer", "object", "x", "y", "z", "charge", "charge_rounded", "S", "vertex",
                  "charge_winding", "charge_curvature")
#: Columns of alignment.parquet.
ALIGN_COLUMNS = ("t", "c", "layer_a", "layer_b", "n", "c_mean", "c_median", "c_std",
                 "fraction_parallel", "fraction_orthogonal", "c_avg_mean", "c_avg_median", "qc_pass", "qc_flags")
#: Lowest fraction of layer A's directors compared with a director of B that passes (the others have
#: no valid director or no partner within ``max_distance``): below it the pair's statistics describe
#: a part of the surface only.
QC_MIN_ALIGN_COMPARED = 0.5


def _finite_mean(values) -> float:
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    return float(v.mean()) if v.size else math.nan


def _finite_median(values) -> float:
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    return float(np.median(v)) if v.size else math.nan


def _nan_fraction(values) -> float:
    v = np.asarray(values, dtype=np.float64)
    return float(np.isnan(v).mean()) if v.size else math.nan


def _read_measure(path: str | Path) -> dict:
    try:
        with open(path) as fh:
            data = json.load(fh)
    except FileNotFoundError:
        raise NemoError(f"measure file not found: {path}") from None
    except json.JSONDecodeError as exc:
        raise NemoError(f"{path} is not the JSON of 'nemo measure --json' ({exc})") from None
    return data


def _value(value) -> float:
    """A table cell as a float: NaN for None, NaN and NA."""
    return math.nan if value is None or pd.isna(value) else float(value)


#: Per-frame tables a record may name, with their kind (:mod:`nemo.tables`).
_TABLES = {"curvature": "curvature", "thickness": "thickness", "layer_table": "layer", "directors": "directors",
           "order": "order", "defects": "defects"}


def _read_tables(r: Mapping) -> dict[str, pd.DataFrame]:
    """The tables a record names (an imported layer has no ``layer_table``; morphology has no layer)."""
    return {key: read_table(r[key], kind) for key, kind in _TABLES.items() if r.get(key)}


def _of_object(tables: Mapping[str, pd.DataFrame], label: int) -> dict[str, pd.DataFrame]:
    """The rows of object ``label`` (tables of a single object have no ``object`` column: all rows)."""
    return {key: df[df["object"].to_numpy() == label] if "object" in df.columns else df for key, df in tables.items()}


def _objects(m: Mapping) -> list[tuple[int, Mapping]]:
    """(label, measure record) of each object of a surface's measure record (one: itself)."""
    if m.get("objects"):
        # several objects kept on purpose (mesh.keep: all): not a reason to flag any of them
        return [(int(o["object"]), {**o, "n_objects": None}) for o in m["objects"]]
    return [(0, m)]


def _peel_params(r: Mapping) -> dict:
    """The peel's resolved layer (``nemo.stages.peel``: range, surface, inward, the texture check)."""
    if not r.get("layer_table"):
        return {}
    return read_provenance(r["layer_table"]).get("parameters") or {}


def _step_params(r: Mapping, table: str, label: int) -> dict:
    """The resolved parameters the record's ``table`` (``directors``, ``defects``) was made with, for
    object ``label`` (each object's own on a mesh of several); {} without that table."""
    if not r.get(table):
        return {}
    params = read_provenance(r[table]).get("parameters") or {}
    if params.get("objects"):
        params = next((o for o in params["objects"] if int(o.get("object", -1)) == label), {})
    return params


def _curvature_scales(table: pd.DataFrame, params: Mapping, area: float) -> tuple[float, float]:
    """The curvature fits' scatter about their average (``fit_scatter_H``, :func:`nemo.morphology.curvature`)
    over the surface's typical curvature, and their radius (``radius``) times it; the typical curvature is
    the median largest |principal curvature| of the table, at least :data:`CURVATURE_FLAT` / the surface's
    size √(area / 4π) (a plane's curvatures are the fits' noise: the ratio would read ~1 on any plane;
    a sphere's is 1 / its size); NaN without them."""
    if not {"k1", "k2"} <= set(table.columns):
        return math.nan, math.nan
    k_max = np.fmax(np.abs(table["k1"].to_numpy(dtype=np.float64)), np.abs(table["k2"].to_numpy(dtype=np.float64)))
    typical = float(np.nanmedian(k_max)) if np.isfinite(k_max).any() else math.nan
    if np.isfinite(area) and area > 0:  # a nearly flat surface: its curvature is itself the fits' noise
        flat = CURVATURE_FLAT / math.sqrt(area / (4 * math.pi))
        typical = max(typical, flat) if np.isfinite(typical) else flat
    if not typical > 0:
        return math.nan, math.nan
    return _value(params.get("fit_scatter_H")) / typical, _value(params.get("radius")) * typical


def _beyond_view(table: pd.DataFrame) -> np.ndarray:
    """The table's ``beyond_view`` (NaN because the field of view ends there: :func:`nemo.stages.peel`,
    :func:`nemo.stages.thickness`); all False for a table without it."""
    if "beyond_view" not in table:
        return np.zeros(len(table), dtype=bool)
    return table["beyond_view"].fillna(False).to_numpy(dtype=bool)


def defect_misfit(defects: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    """Per defect, shape (n,): the model's residual beyond the directors' own scatter (degrees,
    √(fit_residual² − fit_scatter²); the residual alone in a table from before ``fit_scatter``) and the
    core's standard error over the fit radius (NaN before ``fit_uncertainty``); NaN where no model placed it."""
    nan = np.full(len(defects), np.nan)
    residual = defects["fit_residual"].to_numpy(np.float64) if "fit_residual" in defects else nan
    scatter = defects["fit_scatter"].to_numpy(np.float64) if "fit_scatter" in defects else np.zeros(len(defects))
    excess = np.sqrt(np.clip(residual**2 - np.nan_to_num(scatter) ** 2, 0.0, None))
    if "fit_uncertainty" not in defects:
        return excess, nan
    radius = defects["fit_radius"].to_numpy(np.float64) if "fit_radius" in defects else nan
    return excess, defects["fit_uncertainty"].to_numpy(np.float64) / np.where(radius > 0, radius, np.nan)


def _unfitted(defects: pd.DataFrame) -> int:
    """Defects the model fit did not place (``refine`` ``q`` or ``vertex`` where ``model`` was asked: no core
    within reach of the lowest S: in 75 frames of five generators each of the 14 such was 11-76 µm from any
    defect; with sparse directors (a few hundred on a sphere) such defects are often right, but those frames
    also miss defects)."""
    return int(defects["refine"].isin(("q", "vertex")).sum()) if "refine" in defects else 0


def _layer_columns(tables: Mapping[str, pd.DataFrame]) -> dict:
    # an imported layer (directors_from) has no peeled intensity
    intensity = tables["layer_table"]["intensity"] if "layer_table" in tables else None
    row = {"intensity_mean": _finite_mean(intensity) if intensity is not None else math.nan,
           "peel_nan_fraction": _nan_fraction(intensity) if intensity is not None else math.nan}
    if intensity is not None:  # the quality control's: the vertices whose samples stay in the image
        row["peel_nan_in_view"] = _nan_fraction(intensity[~_beyond_view(tables["layer_table"])])
    d = tables["directors"]
    row["n_directors"] = len(d)
    row["coherency_mean"] = _finite_mean(d["coherency"])
    row["coherency_median"] = _finite_median(d["coherency"])
    s = tables["order"]["S"]
    row["S_mean"] = _finite_mean(s)
    row["S_median"] = _finite_median(s)
    row["order_nan_fraction"] = _nan_fraction(s)
    df = tables["defects"]
    row["n_defects"] = len(df)
    row["charge_sum"] = float(df["charge"].sum())
    row["charge_rounded_sum"] = float(df["charge_rounded"].sum())
    faint = df["coherency"].to_numpy(np.float64) if "coherency" in df else np.full(len(df), np.nan)
    # a table from before the column (or a defect without directors in reach) was not measured: NA, not 0
    row["defects_faint"] = (int(np.count_nonzero(faint < QC_MIN_DEFECT_COHERENCY))
                            if "coherency" in df or not len(df) else pd.NA)
    row["defect_coherency_min"] = float(np.nanmin(faint)) if np.isfinite(faint).any() else math.nan
    excess, uncertainty = defect_misfit(df)
    row["defects_misfit"] = (int(np.count_nonzero((excess > QC_MAX_DEFECT_RESIDUAL_DEG)
                                                  | (uncertainty > QC_MAX_DEFECT_UNCERTAINTY)))
                             if "fit_residual" in df or not len(df) else pd.NA)  # NA: a table from before the column
    row["defect_residual_max"] = float(np.nanmax(excess)) if np.isfinite(excess).any() else math.nan
    row["defect_uncertainty_max"] = float(np.nanmax(uncertainty)) if (~np.isnan(uncertainty)).any() else math.nan
    return row


def quality_flags(row: Mapping, measure: Mapping) -> list[str]:
    """Reasons to distrust one frame's row of ``frames.parquet`` (empty list: it passes).

    Parameters
    ----------
    row : mapping
        The row's columns so far (``euler_characteristic``, ``charge_sum``, ``n_defects``,
        ``thickness_valid``, ``n_directors``, ``S_mean``, ``peel_nan_fraction``,
        ``order_nan_fraction``, ``coherency_median``, ``coherency_noise`` where computed;
        ``thickness_valid_in_view`` and ``peel_nan_in_view``, the same over the vertices whose ray or
        samples stay in the field of view, and ``thickness_beyond_view``, how many rays left it (on a
        surface cut by the image's border the others have no thickness or intensity because the view
        ends there, not because the wall or image lacks it);
        ``directors_skipped``, why the directors step gave none (a layer without directors gets that
        flag and the peel's, not the order, coherency and charge flags that follow from it);
        ``defects_skipped``, why the defect search did not run (no charge sum to check); ``texture``,
        the peel's check of where the texture peaks, :func:`nemo.peel.texture_profile`).
    measure : mapping
        The surface's ``nemo measure --json`` record (``n_components``,
        ``n_boundary_loops``, ``rim_loops`` (boundary loops on the image's border), ``n_objects``,
        ``saturated``).

    Returns
    -------
    list of str
        Human-readable reasons, e.g. ``"Σ charge 1.50 ≠ χ 2"``. On an open surface the charge
        sum is not checked (the Poincaré–Hopf sum depends on the field at the rim).
    """
    if _looks_empty(row):
        return [f"the segmented channel looks empty (SNR {row['snr']:.1f} < {QC_EMPTY_SNR:g}): no object in view, or "
                "the wrong channel or time point (the frame's numbers are of noise)"]
    flags = []
    chi = row.get("euler_characteristic", math.nan)
    closed = not measure.get("n_boundary_loops")
    if (measure.get("n_objects") or 1) > 1:
        flags.append(f"{measure['n_objects']} objects in the image (see the mesh step's warning)")
    regions = row.get("regions")
    if regions is not None and not pd.isna(regions) and regions > 1 and measure.get("mask_contrast") is not None:
        flags.append(f"the surface holds {regions} large labels of the mask that touch: objects meshed as one, their "
                     "area and volume together (mask_labels selects one; mesh.keep: all keeps every label apart)")
    elif regions is not None and not pd.isna(regions) and regions > 1:
        flags.append(f"the surface holds {regions} separate bright regions of the image: touching objects meshed "
                     "as one, their area and volume together (a mask that labels them apart separates them)")
    snr = row.get("snr", math.nan)
    if np.isfinite(snr) and snr < QC_MIN_SNR:
        flags.append(f"low signal-to-noise ratio {snr:.1f} in the segmented channel")
    if measure.get("turned_out"):
        flags.append(f"{measure['turned_out']} object(s) enclosed by the foreground, turned out (a dark object in a "
                     "bright surround, or a mask's background class: check the channel or mask)")
    flags += _mask_flags(measure)
    saturated = measure.get("saturated")
    if saturated is not None and saturated > QC_MAX_SATURATED:
        flags.append(f"{100 * saturated:.1f} % of the object's core saturated: walls placed outward, "
                     "thickness overestimated (lower the gain or the exposure)")
    check = measure.get("edge_check") or {}  # the mesh step's (nemo.surface._edge_check), with its limit
    offset = check.get("offset")
    left = None if offset is None else abs(offset) * (1.0 - _level_correction(check))  # what the correction leaves
    if left is not None and left > check.get("limit", math.inf):
        flags.append(f"the walls' own profiles put their edges {100 * abs(offset):.0f} % of the contrast "
                     f"{'above' if offset > 0 else 'below'} the half level: walls placed "
                     f"{'outward, thickness overestimated' if offset > 0 else 'inward, thickness underestimated'} "
                     "(thin or z-blurred walls; mesh.edge: profile meshes at the profiles' level, with psf: auto or none)")
    if check.get("thinner_than_blur"):
        cure = ("deconvolving did not thin them" if check.get("image") == "before deconvolution"
                else "psf: deconvolves by a known PSF")
        flags.append(f"the walls are thinner than the image's blur on {100 * check['thinner_than_blur']:.0f} % of "
                     f"their profiles: they come out about as thick as the blur, thickness overestimated (a z-elongated "
                     f"PSF? {cure}; or a bright film by the wall's surface)")
    if (measure.get("n_components") or 1) > 1:
        flags.append(f"surface has {measure['n_components']} pieces")
    if closed and np.isfinite(chi) and chi < QC_MIN_EULER:
        flags.append(f"surface χ = {chi:.0f}: holes or handles (porous mesh?)")
    holes = (measure.get("n_boundary_loops") or 0) - (measure.get("rim_loops") or 0)
    if holes > QC_MAX_HOLES:
        flags.append(f"surface has {holes} holes besides its rim on the image border (a porous or torn wall?)")
    flags += _opening_flags(measure)
    flags += _curvature_flags(row)
    valid, every = _value(row.get("thickness_valid_in_view")), _value(row.get("thickness_valid"))
    cut = np.isfinite(valid) and bool(row.get("thickness_beyond_view"))  # some rays left the view, some stayed
    valid = valid if cut else every  # none left it, or none stayed: every ray counts
    if np.isfinite(valid) and valid < QC_MIN_THICKNESS_VALID and row.get("walls") != 1:  # one wall: no thickness
        flags.append(f"thickness found at {100 * valid:.0f} % of vertices" + (" in view" if cut else ""))
    rim_loops = measure.get("rim_loops")  # None: not recorded (an imported surface, an older record)
    cut_by_border = bool(rim_loops) if rim_loops is not None else not closed
    return flags + (_layer_flags(row, closed, chi, cut_by_border) if "n_directors" in row else [])


def _opening_flags(measure: Mapping) -> list[str]:
    """A hole (a boundary loop off the image border) wider than :data:`QC_MAX_HOLE_SPAN` of the surface's area."""
    hole, area = _value(measure.get("largest_hole")), _value(measure.get("area"))
    if not (np.isfinite(hole) and np.isfinite(area) and area > 0):
        return []
    span = hole * hole / (4.0 * math.pi) / area
    if span <= QC_MAX_HOLE_SPAN:
        return []
    unit = pretty_unit(measure.get("unit"))
    return [f"surface has an opening {hole / math.pi:.3g} {unit} across besides its rim on the image border (the disc "
            f"it spans is {100 * span:.0f} % of the surface's area): a wall that faded below the level (with depth, or "
            "uneven light) or tore away, its area short and no volume, or an object open there (a cup)"]


def _curvature_flags(row: Mapping) -> list[str]:
    """Curvature missing at many vertices, fitted over more than the surface's radius of curvature, or
    dominated by the fits' noise."""
    flags = []
    missing = row.get("curvature_nan_fraction", math.nan)
    if np.isfinite(missing) and missing > QC_MAX_CURVATURE_NAN:
        flags.append(f"no curvature at {100 * missing:.0f} % of vertices (the fit radius reaches the rim)")
    reach = _value(row.get("curvature_reach"))
    if np.isfinite(reach) and reach > QC_MAX_CURVATURE_REACH:
        flags.append(f"curvature fitted over a radius {reach:.2g} × the surface's typical radius of curvature: H and K "
                     "are flattened (a tube or a neck narrower than the fit; a curvature.radius below the radius of "
                     "curvature fits it)")
    noise = _value(row.get("curvature_noise"))
    if np.isfinite(noise) and noise > QC_MAX_CURVATURE_NOISE:
        flags.append(f"curvature dominated by noise: the fits scatter by {100 * noise:.0f} % of the surface's typical "
                     "curvature, so H and K per vertex are noisy (median errors of 8 % or more in tests; a noisy wall, "
                     "or a surface curved on the scale of a few mesh edges)")
    return flags


def _mask_flags(measure: Mapping) -> list[str]:
    """A mask that does not follow the segmented channel (:func:`nemo.surface.mask_edge_offset`)."""
    contrast, offset, limit = (measure.get(k) for k in ("mask_contrast", "mask_offset", "mask_offset_limit"))
    if contrast is not None and contrast < 0:
        return ["the mask holds the darker side of the segmented channel (a background or cavity class? check "
                "mask_channel)"]
    if offset is not None and limit is not None and offset > limit:
        return [f"the mask lies {offset:.2g} (median) from the segmented channel's edges, more than {limit:.2g} (a mask "
                "of another time point, channel or class?)"]
    return []


def _looks_empty(row: Mapping) -> bool:
    """The row's segmented channel reads an SNR below :data:`QC_EMPTY_SNR`."""
    snr = row.get("snr", math.nan)
    return bool(np.isfinite(snr) and snr < QC_EMPTY_SNR)


def _layer_flags(row: Mapping, closed: bool, chi: float, cut_by_border: bool) -> list[str]:
    """The layer's part of :func:`quality_flags` (peel, directors, order, defects). A layer without
    directors keeps the peel's flags (causes) and drops the order and charge flags (consequences);
    a surface cut by the image's border (``cut_by_border``) counts only the samples in view."""
    flags = []
    if not row["n_directors"] or not np.isfinite(row["S_mean"]):
        flags.append(f"no directors: {row['directors_skipped']}" if row.get("directors_skipped") else "no directors")
    directed = not flags
    for key, what in (("peel_nan_fraction", "no layer intensity (samples outside the image?)"),
                      ("order_nan_fraction", "no order value (no tangent plane or director in reach)")):
        value = row.get(key, math.nan)
        if key == "peel_nan_fraction" and cut_by_border:  # samples beyond the border are the view's
            value, what = row.get("peel_nan_in_view", value), "no layer intensity within the field of view (NaN voxels?)"
        if np.isfinite(value) and value > QC_MAX_NAN_FRACTION and (directed or key == "peel_nan_fraction"):
            flags.append(f"{100 * value:.0f} % of vertices have {what}")
    if row.get("reaches_out") and row.get("walls") == 1:
        flags.append("the object has one wall, so the layer's range from its outline reaches outside it: its "
                     "directors are the background's or the edge's (peel inward: layers.NAME.inward true; for a "
                     "shell, mesh.split: centre)")
    texture = row.get("texture") or {}
    if texture.get("outside"):
        flags.append(f"the image's texture peaks at depth {texture['peak_depth']:.3g}, outside the layer's range "
                     "(set layers.NAME.range to include it)")
    if not directed:  # no order and no defects follow from it
        return flags
    flags += _coherency_flags(row)
    faint = row.get("defects_faint")
    if faint is not None and not pd.isna(faint) and faint > 0:
        lowest = row.get("defect_coherency_min", math.nan)
        flags.append(f"{faint} defect(s) where the fibres are faint (coherency "
                     f"{f'{lowest:.2f} ' if np.isfinite(lowest) else ''}below {QC_MIN_DEFECT_COHERENCY:g} of the "
                     "surface's): a low S there says little, the position is uncertain (fibres across a z-elongated "
                     "PSF fade; where the frame was not deconvolved (psf: none, or auto found no z blur), the measured "
                     "PSF as datasets.NAME.psf helps)")
    misfit = row.get("defects_misfit")
    if misfit is not None and not pd.isna(misfit) and misfit > 0:
        largest = row.get("defect_residual_max", math.nan)
        widest = row.get("defect_uncertainty_max", math.nan)
        residual = (f"up to {largest:.0f}° (limit {QC_MAX_DEFECT_RESIDUAL_DEG:g}°)" if np.isfinite(largest)
                    else f"above {QC_MAX_DEFECT_RESIDUAL_DEG:g}°")
        spread = (f"above {QC_MAX_DEFECT_UNCERTAINTY:g}" if np.isnan(widest) else
                  f"{'unbounded' if np.isinf(widest) else f'up to {widest:.2f}'} (limit {QC_MAX_DEFECT_UNCERTAINTY:g})")
        flags.append(f"{misfit} defect(s) the directors do not place (their fit residual beyond their own scatter "
                     f"{residual}, the core's standard error {spread} of the fit radius, or no core within reach): the "
                     "position is uncertain (placed off the core, a texture the directors do not read, or directors too "
                     "noisy or sparse; the defects table's fit_residual, fit_scatter, fit_uncertainty and refine)")
    zeros = row.get("rejected_zeros")
    if zeros is not None and not pd.isna(zeros) and zeros > 0:
        flags.append(f"{zeros} zero(s) of the averaged order rejected (a disordered contour or an unresolved winding, "
                     "or a zero charge round them): defects closer together than the contour radius may be missed "
                     "there (a missed ± pair keeps Σ charge = χ)")
    charge = row["charge_sum"]
    searched = not row.get("defects_skipped")  # a skipped search has its own flag; no sum to check
    if searched and closed and np.isfinite(chi) and abs(charge - chi) > QC_CHARGE_TOLERANCE:
        flags.append(f"Σ charge {charge:.2f} ≠ χ {chi:.0f} ({row['n_defects']} defects)")
    return flags


def _coherency_flags(row: Mapping) -> list[str]:
    """A layer whose directors show hardly any orientation, or less than white noise does."""
    coherency, floor = _value(row.get("coherency_median")), _value(row.get("coherency_noise"))
    if np.isfinite(coherency) and coherency < QC_MIN_COHERENCY:
        return [f"median director coherency {coherency:.2f}: hardly any orientation"]
    if np.isfinite(coherency) and np.isfinite(floor) and coherency < floor:
        return [f"median director coherency {coherency:.2f}, below white noise's {floor:.2f} with these "
                "patches: no texture to orient (noise, or no fibres at that depth)"]
    return []


def frame_summary(records: Iterable[Mapping]) -> pd.DataFrame:
    """One row per (t, c, layer, object) from the per-frame files.

    Parameters
    ----------
    records : iterable of mapping
        Each with keys ``t``, ``c``, ``layer``, ``surface`` and the paths ``measure`` (JSON of
        ``nemo measure``), ``layer_table``, ``directors``, ``order``, ``defects`` and optionally
        ``curvature`` and ``thickness`` (None when not computed). A layer imported with
        ``directors_from`` has no ``layer_table`` (``intensity_mean`` NaN).

    Returns
    -------
    DataFrame, shape (n_records, len(FRAME_COLUMNS))
        Sorted by t, c, layer, object. ``object`` is 0 for a frame of one object; with
        ``mesh.keep: all`` every object has its row (:mod:`nemo.objects`), with its centre
        (``centre_x/y/z``, the area-weighted centroid of its surface). Means ignore NaN (e.g. thickness rays that hit nothing);
        ``thickness_valid`` is the fraction of vertices with a finite thickness;
        ``qc_pass`` and ``qc_flags`` are the frame's quality control (:func:`quality_flags`).
    """
    rows = []
    for r in records:
        m = _read_measure(r["measure"])
        tables = _read_tables(r)
        skipped = _skipped_searches(r)
        for label, mo in _objects(m):  # a loop over objects (one row each)
            row = _frame_row(r, m, mo, _of_object(tables, label), skipped.get(label), label)
            row["object"] = label
            rows.append(row)
    out = pd.DataFrame(rows, columns=list(FRAME_COLUMNS))
    out = out.astype({"t": "int64", "c": "int64", "object": "int64", "walls": "Int64", "regions": "Int64", "n_directors": "Int64",
                      "n_defects": "Int64", "defects_faint": "Int64", "defects_misfit": "Int64", "rejected_zeros": "Int64",
                      "qc_pass": "bool",
                      "qc_flags": "str", "closed": "bool"})
    _flag_changed_walls(out)
    _flag_changed_level(out)
    _flag_changed_psf(out, pd.Series([row.get("psf_z_planes", math.nan) for row in rows], dtype="float64"))
    _flag_cut_objects(out)
    out["object_id"] = link_objects(out)
    _flag_switched_object(out)
    return out.sort_values(["t", "c", "layer", "object"], kind="stable").reset_index(drop=True)


def _flag_changed_walls(out: pd.DataFrame) -> None:
    """Flag (in place) the rows whose object has other walls than in most frames of its series.

    With ``mesh.split: auto`` the walls are counted frame by frame: a shell whose cavity closes
    (or a droplet that opens one) changes what its inner surface is between time points. With
    several objects the labels are area ranks, so a shell and a droplet of similar size may swap
    labels between frames: a frame whose objects have the series' usual walls among them (the
    same counts, in another order) is not flagged.
    """
    known = out[out["walls"].notna() & ~(out["snr"] < QC_EMPTY_SNR)]  # an empty frame has its own flag
    if known.empty:
        return
    series, frame = ["c", "layer", "surface"], ["t", "c", "layer", "surface"]
    usual = known.groupby([*series, "object"], dropna=False)["walls"].agg(lambda w: w.mode().max())  # ties: 2
    expected = known.join(usual.rename("usual"), on=[*series, "object"])["usual"]
    counts = known.groupby(frame, dropna=False)["walls"].agg(lambda w: tuple(sorted(w))).rename("counts")
    usual_counts = counts.groupby(series, dropna=False).agg(lambda c: c.mode().iloc[-1]).rename("usual_counts")
    mix = known.join(counts, on=frame).join(usual_counts, on=series)
    swapped = (mix["counts"] == mix["usual_counts"]).to_numpy()
    odd = expected.index[(known["walls"] != expected).to_numpy() & ~swapped]
    for i in odd:  # a loop over the few flagged rows
        _add_flag(out, i, f"{out.at[i, 'walls']} wall(s) where most time points have {expected.at[i]} (mesh.split: "
                          "auto counts them per frame; set split: centre or none to fix them)")


def _flag_changed_level(out: pd.DataFrame) -> None:
    """Flag (in place) the time points whose share of the way the half level was moved towards the walls' profiles'
    level (``level_correction``, :func:`nemo.surface._edge_check`) differs by more than 0.5 from the series' median
    time point's, either way.

    The correction's soft limits keep frames near a limit close together; a time point flagged here moved its
    walls, and stepped their thickness, against the rest of its series (the walls' profiles changed: brightness,
    noise). The level is the frame's (one mesh step for all its objects), so each time point counts once,
    whatever its number of objects (a review: two-object time points outvoted the rest).
    """
    known = out[out["level_correction"].notna() & ~(out["snr"] < QC_EMPTY_SNR)]  # an empty frame has its own flag
    for _, rows in known.groupby(["c", "layer", "surface"], dropna=False):  # a loop over the few series
        per_t = rows.groupby("t")["level_correction"].median()
        usual = float(per_t.median())
        for t in per_t.index[(per_t - usual).abs().to_numpy() > 0.5]:  # the few flagged time points
            share = float(per_t[t])
            for i in rows.index[(rows["t"] == t).to_numpy()]:
                _add_flag(out, i, f"the half level moved {100 * share:.0f} % of the way to the walls' profiles' level, "
                                  f"the series' median {100 * usual:.0f} %: its walls step "
                                  f"{'thinner' if share > usual else 'thicker'} than the series' (edge_check in the mesh "
                                  "step's parameters; mesh.edge: profile meshes every frame at its walls' own level)")


#: Largest difference of a time point's ``psf_z`` from its series' that passes: this fraction of the series'
#: median σz (``psf: auto`` estimates each frame's z blur, within ~10 % on vesicles from SNR 3 up), and at least
#: :data:`QC_MIN_PSF_Z_CHANGE_PLANES` planes (a σz of half a plane, the least ``auto`` deconvolves, against
#: none changes little: a review's time-lapse flipped there with the same thickness).
QC_MAX_PSF_Z_CHANGE = 0.25
QC_MIN_PSF_Z_CHANGE_PLANES = 0.75


def _psf_z(record: Mapping | None, planes: bool = False) -> float:
    """σz the mesh's image was deconvolved by (``psf: auto``: the z blur estimated; ``planes``: in planes), 0
    where it was not, NaN where the mesh step recorded nothing (a surface from elsewhere, an older NEMO)."""
    if not record:
        return math.nan
    if not (record.get("psf") and record.get("iterations")):
        return 0.0
    if planes:  # a record from elsewhere may lack it
        return float(record["sigma_voxels"][0]) if record.get("sigma_voxels") else math.nan
    return float(record["psf"][0])


def _flag_changed_psf(out: pd.DataFrame, planes: pd.Series) -> None:
    """Flag (in place) the time points whose σz (``planes``: in planes, per row of ``out``) differs from their
    series' by more than :data:`QC_MAX_PSF_Z_CHANGE` of it and :data:`QC_MIN_PSF_Z_CHANGE_PLANES` planes: the
    series' σz is the median of its deconvolved time points where most are deconvolved (a tie: not), else 0.
    ``psf: auto`` decides per frame, so a frame near one of its limits can step its walls and directors against
    the rest of its series."""
    known = out[planes.notna().to_numpy() & ~(out["snr"] < QC_EMPTY_SNR).to_numpy()]
    for _, rows in known.groupby(["c", "layer", "surface"], dropna=False):  # a loop over the few series
        per_t = planes[rows.index].groupby(rows["t"]).median()
        microns = rows.groupby("t")["psf_z"].median()
        most = bool((per_t > 0).mean() > 0.5)
        usual, usual_um = (float(per_t[per_t > 0].median()), float(microns[per_t > 0].median())) if most else (0.0, 0.0)
        limit = max(QC_MAX_PSF_Z_CHANGE * usual, QC_MIN_PSF_Z_CHANGE_PLANES)
        for t in per_t.index[(per_t - usual).abs().to_numpy() > limit]:  # the few flagged time points
            value = float(microns[t])
            said = f"deconvolved by σz {value:.3g}" if value > 0 else "not deconvolved"
            usual_said = f"deconvolved by σz {usual_um:.3g} (median)" if most else "not deconvolved"
            for i in rows.index[(rows["t"] == t).to_numpy()]:
                _add_flag(out, i, f"{said} where most of its series is {usual_said} (psf: auto estimates each frame; "
                                  "the deconvolution record in the mesh step's parameters says why; give "
                                  "datasets.NAME.psf, or none, to treat every frame alike)")


def _level_correction(check: Mapping | None) -> float:
    """The share of the way from the half level to the walls' profiles' level the mesh step moved the surface
    (:func:`nemo.surface._edge_check`; an older record's ``corrected`` counts whole); NaN without a check."""
    if not check:
        return math.nan
    return _value(check.get("correction", 1.0 if check.get("corrected") else 0.0))


#: What ``qc_flags`` joins its reasons with; a reason's own "; " becomes ", " (:func:`join_flags`).
FLAG_SEPARATOR = "; "


def join_flags(flags: Iterable[str]) -> str:
    """The reasons as one ``qc_flags`` string that splits back on :data:`FLAG_SEPARATOR` into as many (a
    reason's own separators read as commas: a frame's 6 reasons split into 9 parts)."""
    return FLAG_SEPARATOR.join(flag.replace(FLAG_SEPARATOR, ", ") for flag in flags)


def _add_flag(out: pd.DataFrame, i, flag: str) -> None:
    """Fail row ``i`` of ``out`` (in place) with one more reason, after its own."""
    own, reason = out.at[i, "qc_flags"], join_flags([flag])  # its own reasons already joined
    out.at[i, "qc_flags"] = f"{own}{FLAG_SEPARATOR}{reason}" if own else reason
    out.at[i, "qc_pass"] = False


def _flag_cut_objects(out: pd.DataFrame) -> None:
    """Flag (in place) the rows whose surface is open where most time points of its series are
    closed: an object that drifted partly out of the field of view (or a torn wall). Its area,
    volume and centre are of the part in view, and its defects cannot be checked against χ, so a
    frame of wrong numbers passed (an independent review: area −17 %, 2 of 3 defects in view)."""
    series, frame = ["c", "layer", "surface"], ["t", "c", "layer", "surface"]
    usual = out.groupby([*series, "object"], dropna=False)["closed"].transform(lambda c: c.mode().max())  # ties: closed
    # several objects (keep: all): labels are area ranks, so an object always cut by the border may take
    # the label of one mostly closed; flag only frames with more open objects than the series' usual
    n_open = (~out["closed"]).groupby([out[k] for k in frame], dropna=False).transform("sum")
    usual_open = n_open.groupby([out[k] for k in series], dropna=False).transform(lambda n: n.mode().min())
    more = (n_open > usual_open).to_numpy(bool)
    empty = (out["snr"] < QC_EMPTY_SNR).to_numpy(bool)  # its own flag
    for i in out.index[usual.to_numpy(bool) & ~out["closed"].to_numpy(bool) & more & ~empty]:  # the few flagged rows
        _add_flag(out, i, "surface open where most time points are closed (the object partly out of the field of "
                          "view, or a torn wall): area, volume, centre and defects are not comparable with the other "
                          "frames")


def _flag_switched_object(out: pd.DataFrame) -> None:
    """Flag (in place) the rows where ``keep: largest`` analysed another object than at the time
    point before: with several objects in view, the largest may change (an independent review:
    one shell shrinking and another growing made t0–2 one shell and t3–5 the other, one series
    whose area and volume fell and rose again, and only "3 objects in the image" flagged). Another
    object is another ``object_id`` (:func:`nemo.track.link_objects`: its centre moved by more
    than its radius); one object in view at both time points has only moved."""
    several = out.groupby(["t", "c", "layer", "surface"], dropna=False)["object"].transform("nunique") > 1
    rows = out[~several & out["object_id"].notna()]
    for _, g in rows.groupby(["c", "layer", "surface"], dropna=False):  # a loop over the few series
        g = g.sort_values("t")
        ids = g["object_id"].to_numpy(np.int64)
        crowded = g["n_objects"].fillna(1).to_numpy(np.float64) > 1
        for k in np.flatnonzero((ids[1:] != ids[:-1]) & (crowded[:-1] | crowded[1:])):  # the few switches
            _add_flag(out, g.index[k + 1], f"another object than at t = {g['t'].iloc[k]} (object_id {ids[k]} → "
                                           f"{ids[k + 1]}): with several objects in view the largest changed; set "
                                           "mesh.keep: all, or give a mask of the object")


def _skipped_searches(r: Mapping) -> dict[int, str]:
    """Objects whose defect search could not run (``nemo.stages``), with the reason."""
    if not r.get("defects"):
        return {}
    check = read_provenance(r["defects"]).get("euler_check") or {}
    if check.get("skipped"):  # a frame of one object
        return {0: check["skipped"]}
    return {int(o["object"]): o["skipped"] for o in check.get("objects") or [] if o.get("skipped")}


def _frame_row(r: Mapping, m: Mapping, mo: Mapping, tables: Mapping[str, pd.DataFrame],
               skipped: str | None = None, label: int = 0) -> dict:
    """One row of ``frames.parquet``: the record ``r``, the surface's measure ``m``, the object's ``mo``."""
    centre = mo.get("centre") or [math.nan] * 3
    row = {"t": int(r["t"]), "c": int(r["c"]), "layer": str(r["layer"]),
           "surface": str(r["surface"]), "area": _value(mo.get("area")),
           "volume": _value(mo.get("volume")),
           "euler_characteristic": _value(mo.get("euler_characteristic")),
           "closed": not mo.get("n_boundary_loops"),
           "n_objects": m.get("n_objects"), "walls": value_for(m.get("walls"), label),
           "regions": value_for(m.get("regions"), label), "snr": _value(m.get("snr")),
           "saturated": _value(m.get("saturated")),
           "level_correction": _level_correction(m.get("edge_check")),
           "psf_z": _psf_z(m.get("deconvolution")), "psf_z_planes": _psf_z(m.get("deconvolution"), planes=True),
           "centre_x": _value(centre[0]), "centre_y": _value(centre[1]), "centre_z": _value(centre[2]),
           "H_mean": _value(mo.get("mean_H")), "K_mean": _value(mo.get("mean_K"))}
    if "curvature" in tables:
        cur = tables["curvature"]
        row["H_fit_mean"] = _finite_mean(cur["H"])
        row["K_fit_mean"] = _finite_mean(cur["K"])
        row["curvature_nan_fraction"] = _nan_fraction(cur["H"])
        row["curvature_noise"], row["curvature_reach"] = _curvature_scales(cur, _step_params(r, "curvature", label),
                                                                           row["area"])
    if "thickness" in tables:
        th = tables["thickness"]["thickness"].to_numpy(dtype=np.float64)
        row["thickness_mean"] = _finite_mean(th)
        row["thickness_median"] = _finite_median(th)
        row["thickness_valid"] = float(np.isfinite(th).mean()) if th.size else math.nan
        in_view = th[~_beyond_view(tables["thickness"])]  # the quality control's: rays that stay in view
        row["thickness_valid_in_view"] = float(np.isfinite(in_view).mean()) if in_view.size else math.nan
        row["thickness_beyond_view"] = int(th.size - in_view.size)
    if "directors" in tables:  # a morphology-only record has no layer tables
        row.update(_layer_columns(tables))
        directors = _step_params(r, "directors", label)
        row["coherency_noise"] = _value(directors.get("coherency_noise"))  # NaN: imported directors, older tables
        row["directors_skipped"] = directors.get("skipped")
        peel = _peel_params(r)
        row["texture"] = peel.get("texture") or {}
        # the record's surface: the workflow's `nemo peel` is given a mesh file, not its name (an
        # independent review: the workflow never raised this flag where `nemo run` did)
        row["reaches_out"] = bool(peel) and reaches_out_of_one_wall({**peel, "surface": r["surface"]})
        defect_params = _step_params(r, "defects", label)
        zeros = defect_params.get("rejected_zeros")  # None: a table from before the count
        row["rejected_zeros"] = pd.NA if zeros is None else int(zeros)
        if defect_params.get("refine") == "model" and not pd.isna(row.get("defects_misfit", pd.NA)):
            row["defects_misfit"] += _unfitted(tables["defects"])
    no_directors = "directors" in tables and not row["n_directors"]  # its own flag says why
    row["defects_skipped"] = skipped
    if "directors" in tables and (skipped or no_directors):  # not searched: no count, not "none found"
        row.update(n_defects=pd.NA, charge_sum=math.nan, charge_rounded_sum=math.nan, defects_faint=pd.NA,
                   defects_misfit=pd.NA, rejected_zeros=pd.NA)
    extra = skipped and not no_directors and not _looks_empty(row)
    flags = quality_flags(row, mo) + ([f"no defect search: {skipped}"] if extra else [])
    row["qc_pass"] = not flags
    row["qc_flags"] = join_flags(flags)
    return row


def collect_defects(records: Iterable[Mapping], frames: pd.DataFrame | None = None) -> pd.DataFrame:
    """The defects of all frames in one table with ``t``, ``c``, ``layer`` first.

    Parameters
    ----------
    records : iterable of mapping
        Each with keys ``t``, ``c``, ``layer`` and ``defects`` (path of a defects table).
    frames : DataFrame, optional
        :func:`frame_summary` of the same frames: each defect then gets its frame's (object's)
        ``qc_pass`` and ``qc_flags``, so a defect of a frame that failed the quality control
        can be told apart (a layer without texture, a missed defect).

    Returns
    -------
    DataFrame
        Columns :data:`DEFECT_COLUMNS` (then any further columns of the inputs, then ``qc_pass``
        and ``qc_flags`` with ``frames``), sorted by t, c, layer, then the input order.
    """
    parts = []
    from nemo.tables import read_provenance

    for r in records:
        df = read_table(r["defects"], "defects")
        params = read_provenance(r["defects"]).get("parameters") or {}
        df["min_distance"] = float(params.get("min_distance") or math.nan)  # tracking's default
        per_object = {int(o["object"]): o.get("min_distance") for o in params.get("objects") or [] if "object" in o}
        if per_object and "object" in df.columns:  # several objects: each its own suppression radius
            radii = pd.Series({k: float(v) if v else math.nan for k, v in per_object.items()})
            df["min_distance"] = df["object"].astype(int).map(radii).astype(float)
        if "object" not in df.columns:  # one object: 0
            df.insert(0, "object", np.zeros(len(df), dtype=np.int64))
        df.insert(0, "layer", str(r["layer"]))
        df.insert(0, "c", int(r["c"]))
        df.insert(0, "t", int(r["t"]))
        parts.append(df)
    if not parts:
        return _no_defects(frames)
    found = [p for p in parts if not p.empty]
    out = pd.concat(found or parts, ignore_index=True)  # none found: the empty tables' columns
    if not found:
        out = out.astype({k: "int64" for k in ("t", "c", "object", "vertex") if k in out})
    extra = [c for c in out.columns if c not in DEFECT_COLUMNS]
    out = out[list(DEFECT_COLUMNS) + extra]
    out = out.sort_values(["t", "c", "layer"], kind="stable").reset_index(drop=True)
    return out if frames is None else _with_frame_qc(out, frames)


def _no_defects(frames: pd.DataFrame | None) -> pd.DataFrame:
    """The defects table of no frame: :data:`DEFECT_COLUMNS`, ``min_distance`` (and with ``frames``
    the frame's ``object_id``, ``qc_pass``, ``qc_flags``)."""
    empty = pd.DataFrame({c: pd.Series(dtype="object" if c == "layer" else "float64")
                          for c in (*DEFECT_COLUMNS, "min_distance")}).astype({"t": "int64", "c": "int64",
                                                                              "object": "int64", "vertex": "int64"})
    return empty if frames is None else _with_frame_qc(empty, frames)


def _with_frame_qc(defects: pd.DataFrame, frames: pd.DataFrame) -> pd.DataFrame:
    """``defects`` with the ``object_id``, ``qc_pass`` and ``qc_flags`` of their frame's row (t, c, layer,
    object)."""
    keys = ["t", "c", "layer", "object"]
    qc = frames[[*keys, *(["object_id"] if "object_id" in frames else []), "qc_pass", "qc_flags"]].drop_duplicates(keys)
    out = defects.astype({"object": "int64"}).merge(qc.astype({"object": "int64"}), on=keys, how="left",
                                                     validate="many_to_one")
    out["qc_pass"] = out["qc_pass"].fillna(False).astype(bool)  # a defect of no summarised frame: not vouched for
    out["qc_flags"] = out["qc_flags"].fillna("no frame summary").astype(str)
    return out


def c_avg_means(table: pd.DataFrame) -> dict:
    """``c_avg_mean`` (weighted by ``weight``) and ``c_avg_median`` of an alignment table (NaN without them)."""
    if "c_avg" not in table or "weight" not in table:  # a table written before the averaged alignment
        return {"c_avg_mean": math.nan, "c_avg_median": math.nan}
    c, w = table["c_avg"].to_numpy(np.float64), table["weight"].to_numpy(np.float64)
    ok = np.isfinite(c) & np.isfinite(w) & (w > 0)
    return {"c_avg_mean": float(np.sum(w[ok] * c[ok]) / np.sum(w[ok])) if ok.any() else math.nan,
            "c_avg_median": float(np.median(c[ok])) if ok.any() else math.nan}


def alignment_summary(records: Iterable[Mapping], frames: pd.DataFrame | None = None) -> pd.DataFrame:
    """One row per (t, c, layer pair) from the ``nemo align`` tables.

    Parameters
    ----------
    records : iterable of mapping
        Each with keys ``t``, ``c``, ``layer_a``, ``layer_b`` and ``align`` (path).
    frames : DataFrame, optional
        ``frames.parquet`` (:func:`frame_summary`) of the same frames, for the two layers' part of
        the pair's quality control (:func:`alignment_flags`); without it only the pair's own part.

    Returns
    -------
    DataFrame
        Columns :data:`ALIGN_COLUMNS`: ``n`` directors of A with a partner, mean / median /
        standard deviation of c = cos 2(θ_B − θ_A), and the fractions with c > 0.5 (close to
        parallel, within 30°) and c < −0.5 (close to orthogonal); ``c_avg_mean`` (weighted by S_A ·
        S_B) and ``c_avg_median`` of the averaged directors' alignment (:func:`nemo.order.alignment`:
        noise pulls the mean of c towards 0, not c_avg), NaN for a table without it; ``qc_pass``
        and ``qc_flags``.
    """
    by_layer = {} if frames is None else {key: group.to_dict("records")
                                          for key, group in frames.groupby(["t", "c", "layer"], sort=False)}
    rows = []
    for r in records:
        table = read_table(r["align"], "align")
        c = table["c"].to_numpy(dtype=np.float64)
        c = c[np.isfinite(c)]
        t, ch, a, b = int(r["t"]), int(r["c"]), str(r["layer_a"]), str(r["layer_b"])
        row = {**c_avg_means(table), "t": t, "c": ch, "layer_a": a, "layer_b": b, "n": int(c.size),
               "c_mean": float(c.mean()) if c.size else math.nan,
               "c_median": float(np.median(c)) if c.size else math.nan,
               "c_std": float(c.std()) if c.size else math.nan,
               "fraction_parallel": float((c > 0.5).mean()) if c.size else math.nan,
               "fraction_orthogonal": float((c < -0.5).mean()) if c.size else math.nan}
        flags = alignment_flags({**row, "compared": c.size / max(len(table), 1)},
                                {name: by_layer.get((t, ch, name), []) for name in (a, b)})
        rows.append({**row, "qc_pass": not flags, "qc_flags": join_flags(flags)})
    out = pd.DataFrame(rows, columns=list(ALIGN_COLUMNS))
    out = out.astype({"t": "int64", "c": "int64", "n": "int64", "qc_pass": "bool", "qc_flags": "str"})
    return out.sort_values(["t", "c", "layer_a", "layer_b"], kind="stable").reset_index(drop=True)


def alignment_flags(pair: Mapping, layer_rows: Mapping[str, list[Mapping]]) -> list[str]:
    """Reasons to distrust one row of ``alignment.parquet`` (empty list: it passes).

    The pair is as good as the two fields it compares: a layer whose segmented channel is empty or
    below :data:`QC_MIN_SNR`, or whose directors show no more orientation than white noise, makes
    both c and c_avg noise (a review's Hydra layers at 90°, SNR 4: c_avg −0.27). A layer's other
    flags (its Σ charge, faint defects, thickness) say nothing of the alignment and are left out.

    Parameters
    ----------
    pair : mapping
        The pair's row so far (``layer_a``, ``layer_b``, ``n``) and ``compared``, the fraction of
        A's directors compared with one of B.
    layer_rows : mapping
        Each layer's rows of ``frames.parquet`` at the pair's (t, c), one per object; a layer
        without rows is not checked.

    Returns
    -------
    list of str
        Human-readable reasons, e.g. ``"layer endo: median director coherency 0.44, below white
        noise's 0.54 …"``.
    """
    if not pair["n"]:
        return ["no director of A was compared with one of B (a layer without directors?)"]
    flags = []
    if pair["compared"] < QC_MIN_ALIGN_COMPARED:
        flags.append(f"only {100 * pair['compared']:.0f} % of layer {pair['layer_a']}'s directors compared with "
                     f"one of layer {pair['layer_b']}")
    for name in dict.fromkeys((pair["layer_a"], pair["layer_b"])):
        rows = layer_rows.get(name) or []
        for row in _pair_objects(rows):
            where = f"layer {name}" + (f" object {row['object']}" if len(rows) > 1 else "")
            flags += [f"{where}: {flag}" for flag in _field_flags(row)]
    return flags


def _pair_objects(rows: list[Mapping]) -> list[Mapping]:
    """A layer's object rows whose field the pair depends on: an object without directors is left
    out when others have them and its area is below :data:`nemo.surface.OBJECT_MIN_AREA` of the
    largest of theirs (a speck adds nothing to the pair; a large object without any does)."""
    from nemo.surface import OBJECT_MIN_AREA

    directed = [row for row in rows if not pd.isna(row.get("n_directors")) and row.get("n_directors")]
    if not directed:
        return rows
    largest = max((_value(row.get("area")) for row in directed), default=math.nan)
    return [row for row in rows if any(row is d for d in directed)
            or _value(row.get("area")) >= OBJECT_MIN_AREA * largest]  # an area unknown (NaN): as a speck


def _field_flags(row: Mapping) -> list[str]:
    """The flags of a frame's row (:func:`quality_flags`) that make its director field noise."""
    snr = _value(row.get("snr"))
    if np.isfinite(snr) and snr < QC_MIN_SNR:
        return [f"low signal-to-noise ratio {snr:.1f} in the segmented channel"]
    n = row.get("n_directors")
    if n is None or pd.isna(n) or not n:
        return ["no directors"]
    return _coherency_flags(row)
