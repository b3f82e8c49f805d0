"""Scores of the validation protocol: results of the analysis against the ground truth.

* :func:`score_shape`: curvature and thickness of a reconstructed analytic shape against the
  closed-form values (:mod:`nemo.validation.shapes`).
* :func:`match_defects`, :func:`score_defects`, :func:`director_errors`, :func:`score_vesicle`:
  one analysed synthetic vesicle against its truth (``nemo.synthetic.read_truth``).
"""

from __future__ import annotations

import os
import time

import numpy as np
import pandas as pd
from scipy.optimize import linear_sum_assignment

from nemo.validation.shapes import ellipsoid_curvature, shell_thickness, torus_curvature

#: Default matching radius for defects as a fraction of the vesicle radius.
MATCH_FRACTION = 0.15


def _norm_err(est: np.ndarray, exact: np.ndarray) -> np.ndarray:
    """|est − exact| / RMS(exact) (= relative error for constant fields)."""
    return np.abs(est - exact) / np.sqrt(np.mean(exact**2))


def _pct(a: np.ndarray, q: float) -> float:
    """Percentile ``q`` of ``a``; NaN when empty (no finite estimate: a shredded noisy surface)."""
    return float(np.percentile(a, q)) if len(a) else np.nan


def score_shape(mesh_path: str | os.PathLike, truth: dict) -> list[dict]:
    """Curvature and thickness of a reconstructed analytic shape against the exact values.

    Curvature (``nemo.morphology.curvature``) is fitted at every ``radius_edges`` × mean edge
    length (``radius_source`` ``fixed``) and at the workflow's default radius and averaging
    (:func:`nemo.stages.curvature`, ``radius_source`` ``default``); errors are
    |est − exact| / RMS(exact) over the vertices (the relative error for a sphere). Shells are
    split into inner/outer walls (``nemo.surface.split_mesh``) and the thickness from the inner
    wall along its normals, as the workflow's thickness step gives it at its defaults
    (:func:`nemo.stages.thickness`: averaged over ``thickness.smooth`` mean edges), is compared
    with the exact normal-ray distance (µm and in voxels of the largest spacing).

    Returns
    -------
    list of dict
        One row per curvature radius (the fixed ones, then the default).
    """
    from nemo import stages
    from nemo.mesh import load_mesh, mean_edge_length
    from nemo.morphology import curvature, measure
    from nemo.surface import split_mesh

    mesh = load_mesh(mesh_path)
    c = np.asarray(truth["centre"], float)
    kind = truth["kind"]
    rows = []
    blur = truth.get("blur_zyx") or [truth.get("blur", truth["spacing"][2])] * 3
    base = {"shape": truth.get("name", kind), "kind": kind,
            "dz_dx": truth["spacing"][0] / truth["spacing"][2], "dx": truth["spacing"][2],
            "blur_z": float(blur[0]), "blur_xy": float(blur[2]),
            "snr": np.nan if truth.get("snr") is None else float(truth["snr"])}
    outer = None
    if kind == "shells":
        surf, outer = split_mesh(mesh, by="centre", centre=c)
    else:
        surf = mesh
    p = np.asarray(surf.vertices) - c
    if kind == "torus":
        H0, K0 = torus_curvature(p, truth["major"], truth["minor"])
    else:
        H0, K0 = ellipsoid_curvature(p, truth["inner"] if kind == "shells" else truth["axes"])
    edge = mean_edge_length(surf)
    m = measure(surf)
    thick = {}
    if outer is not None:
        t0 = time.perf_counter()
        d = stages.thickness(surf, outer, {})[0]["thickness"].to_numpy()  # the thickness rule at its defaults
        t_thick = time.perf_counter() - t0
        d0 = shell_thickness(p, truth["inner"], truth["outer"])
        err = np.abs(d - d0)
        ok = np.isfinite(d)
        vox = max(truth["spacing"])
        thick = {
            "thickness_exact_mean": float(np.mean(d0)),
            "thickness_err_median": float(np.median(err[ok])) if ok.any() else np.nan,
            "thickness_err_p90": float(np.percentile(err[ok], 90)) if ok.any() else np.nan,
            "thickness_err_median_vox": float(np.median(err[ok]) / vox) if ok.any() else np.nan,
            "thickness_bias": float(np.median((d - d0)[ok])) if ok.any() else np.nan,
            "thickness_valid": float(ok.mean()), "time_thickness_s": t_thick,
        }
    fixed = [("fixed", float(fac) * edge) for fac in truth.get("radius_edges", [5.0])]
    for source, radius in [*fixed, ("default", None)]:
        t0 = time.perf_counter()
        if radius is None:  # what the workflow's curvature rule gives: the radius from the surface
            cdf, resolved = stages.curvature(surf)
            radius = float(resolved["radius"])
        else:
            cdf = curvature(surf, radius, rng=0)
        t_curv = time.perf_counter() - t0
        H, K = cdf["H"].to_numpy(), cdf["K"].to_numpy()
        ok = np.isfinite(H) & np.isfinite(K)
        eh, ek = _norm_err(H[ok], H0[ok]), _norm_err(K[ok], K0[ok])
        strong = np.abs(K0) > 0.2 * np.abs(K0).max()
        rows.append({
            **base, "n_vertices": len(surf.vertices), "mean_edge": edge,
            "radius_source": source, "radius_edges": radius / edge, "curvature_radius": radius,
            "H_err_median": _pct(eh, 50), "H_err_p90": _pct(eh, 90),
            "K_err_median": _pct(ek, 50), "K_err_p90": _pct(ek, 90),
            "K_sign_agreement": (float(np.mean(np.sign(K[ok & strong]) == np.sign(K0[ok & strong])))
                                 if (ok & strong).any() else np.nan),
            "gauss_bonnet_ratio": float(m.get("gauss_bonnet_ratio", np.nan) or np.nan),
            "integral_K": float(m.get("integral_K", np.nan)),
            "euler_characteristic": int(m.get("euler_characteristic", 0)),
            "curvature_valid": float(ok.mean()), "time_curvature_s": t_curv, **thick,
        })
    return rows


def match_defects(
    found: np.ndarray, truth: np.ndarray, max_distance: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One-to-one matching of found to true defects (Hungarian, Euclidean distance).

    Parameters
    ----------
    found : ndarray, shape (F, 3)
    truth : ndarray, shape (T, 3)
        Physical x, y, z (µm).
    max_distance : float
        Pairs farther apart are never matched (µm).

    Returns
    -------
    i_found, i_truth : ndarray of int, shape (M,)
        Matched indices.
    distance : ndarray, shape (M,)
        Their distances (µm).
    """
    found = np.asarray(found, float).reshape(-1, 3)
    truth = np.asarray(truth, float).reshape(-1, 3)
    if not len(found) or not len(truth):
        e = np.zeros(0, int)
        return e, e, np.zeros(0)
    d = np.linalg.norm(found[:, None] - truth[None], axis=-1)
    cost = np.where(d <= max_distance, d, 1e9)
    i, j = linear_sum_assignment(cost)
    keep = d[i, j] <= max_distance
    return i[keep], j[keep], d[i[keep], j[keep]]


def score_defects(found: pd.DataFrame, truth: pd.DataFrame, max_distance: float) -> dict:
    """Detection rate, false positives, localisation and charge errors.

    Parameters
    ----------
    found : DataFrame
        Columns ``x``, ``y``, ``z``, ``charge`` (+ ``charge_rounded``), e.g. a defects table.
    truth : DataFrame
        Columns ``x``, ``y``, ``z``, ``charge`` of the true defects.
    max_distance : float
        Matching radius (µm).

    Returns
    -------
    dict
        ``n_true``, ``n_found``, ``n_matched``, ``detection_rate`` (matched / true),
        ``false_positives`` (found − matched), ``loc_err_mean/median/max`` (µm, matched),
        ``charge_err_mean/max`` (|charge − true|, matched), ``charge_correct`` (fraction of the
        matched with the right rounded charge), ``all_found`` (every defect matched, no false
        positive, every charge right).
    """
    xyz = ["x", "y", "z"]
    i, j, dist = match_defects(found[xyz].to_numpy(), truth[xyz].to_numpy(), max_distance)
    n_true, n_found = len(truth), len(found)
    out = {"n_true": n_true, "n_found": n_found, "n_matched": len(i),
           "detection_rate": len(i) / n_true if n_true else np.nan,
           "false_positives": n_found - len(i), "match_radius": float(max_distance)}
    if len(i):
        q = found["charge"].to_numpy()[i]
        q0 = truth["charge"].to_numpy()[j]
        qr = found["charge_rounded"].to_numpy()[i] if "charge_rounded" in found else np.round(2 * q) / 2
        cerr = np.abs(q - q0)
        out.update(loc_err_mean=float(dist.mean()), loc_err_median=float(np.median(dist)),
                   loc_err_max=float(dist.max()), charge_err_mean=float(cerr.mean()),
                   charge_err_max=float(cerr.max()), charge_correct=float(np.mean(np.isclose(qr, q0))))
    else:
        out.update(loc_err_mean=np.nan, loc_err_median=np.nan, loc_err_max=np.nan,
                   charge_err_mean=np.nan, charge_err_max=np.nan, charge_correct=np.nan)
    out["all_found"] = bool(out["n_matched"] == n_true and out["false_positives"] == 0
                            and (n_true == 0 or out["charge_correct"] == 1.0))
    return out


def director_errors(n: np.ndarray, n_true: np.ndarray) -> np.ndarray:
    """Head–tail-symmetric angle (degrees, [0, 90]) between directors ``n`` and ``n_true`` (N, 3)."""
    n = np.asarray(n, float)
    m = np.asarray(n_true, float)
    c = np.abs(np.einsum("ij,ij->i", n, m)) / np.maximum(
        np.linalg.norm(n, axis=1) * np.linalg.norm(m, axis=1), 1e-300)
    return np.rad2deg(np.arccos(np.clip(c, 0.0, 1.0)))


def _far_from(xyz: np.ndarray, points: np.ndarray, distance: float) -> np.ndarray:
    from scipy.spatial import cKDTree

    if not len(points):
        return np.ones(len(xyz), bool)
    d, _ = cKDTree(points).query(xyz)
    return d > distance


def truth_defects(truth: dict, t: int = 0, layer: int = 0) -> pd.DataFrame:
    """True defects of a frame and layer (inner-surface positions x, y, z and charges)."""
    return pd.DataFrame([d for d in truth["defects"] if d["t"] == t and d["layer"] == layer])


def score_vesicle(
    truth: dict,
    defects: pd.DataFrame,
    directors: pd.DataFrame | None = None,
    order: pd.DataFrame | None = None,
    curvature: pd.DataFrame | None = None,
    ordered_distance: float | None = None,
    match_radius: float | None = None,
    t: int = 0,
    layer: int = 0,
) -> dict:
    """All accuracy scores of one analysed synthetic vesicle.

    Parameters
    ----------
    truth : dict
        :func:`nemo.synthetic.read_truth`.
    defects, directors, order, curvature : DataFrame
        The tables of the analysed frame (``order`` needs ``x``, ``y``, ``z``).
    ordered_distance : float, optional
        Vertices/directors farther than this from every true defect form the *ordered region*
        (default: 0.25 R).
    match_radius : float, optional
        Defect matching radius (default :data:`MATCH_FRACTION` × R).

    Returns
    -------
    dict
        :func:`score_defects` (against the defects in the field of view when the truth marks
        ``in_view``: an open vesicle cut by the stack; ``n_out_of_view`` the others) plus
        ``angle_err_median/p90`` (raw directors, all),
        ``angle_err_ordered_median/p90`` (raw directors in the ordered region),
        ``avg_angle_err_ordered_median`` (averaged field), ``S_ordered_median/p10``,
        ``H_relerr_median/p90``, ``K_relerr_median/p90`` (sphere of radius R).
    """
    from nemo.synthetic import truth_directors

    R = float(truth["radius"])
    tdf = truth_defects(truth, t, layer)
    hidden = 0
    if "in_view" in tdf:  # an open (cut) vesicle: defects above the field of view cannot be found
        hidden = int((~tdf["in_view"].astype(bool)).sum())
        tdf = tdf[tdf["in_view"].astype(bool)].reset_index(drop=True)
    out = score_defects(defects, tdf, match_radius or MATCH_FRACTION * R)
    out["n_out_of_view"] = hidden
    out["charge_sum"] = float(defects["charge"].sum()) if len(defects) else 0.0
    dist = ordered_distance or 0.25 * R
    tx = tdf[["x", "y", "z"]].to_numpy() if len(tdf) else np.zeros((0, 3))
    out["ordered_distance"] = float(dist)
    if directors is not None and len(directors):
        p = directors[["x", "y", "z"]].to_numpy()
        err = director_errors(directors[["nx", "ny", "nz"]].to_numpy(), truth_directors(truth, p, t, layer))
        far = _far_from(p, tx, dist)
        out.update(angle_err_median=float(np.median(err)), angle_err_p90=float(np.percentile(err, 90)),
                   angle_err_ordered_median=float(np.median(err[far])) if far.any() else np.nan,
                   angle_err_ordered_p90=float(np.percentile(err[far], 90)) if far.any() else np.nan,
                   n_directors=int(len(directors)))
    if order is not None and len(order):
        p = order[["x", "y", "z"]].to_numpy()
        far = _far_from(p, tx, dist) & np.isfinite(order["S"].to_numpy())
        s = order["S"].to_numpy()[far]
        err = director_errors(order[["nx", "ny", "nz"]].to_numpy()[far], truth_directors(truth, p[far], t, layer))
        out.update(S_ordered_median=float(np.median(s)) if len(s) else np.nan,
                   S_ordered_p10=float(np.percentile(s, 10)) if len(s) else np.nan,
                   avg_angle_err_ordered_median=float(np.median(err)) if len(err) else np.nan,
                   avg_angle_err_ordered_p90=float(np.percentile(err, 90)) if len(err) else np.nan)
    if curvature is not None and len(curvature):
        H, K = curvature["H"].to_numpy(), curvature["K"].to_numpy()
        eh = np.abs(H * R - 1.0)
        ek = np.abs(K * R**2 - 1.0)
        out.update(H_relerr_median=float(np.nanmedian(eh)), H_relerr_p90=float(np.nanpercentile(eh, 90)),
                   K_relerr_median=float(np.nanmedian(ek)), K_relerr_p90=float(np.nanpercentile(ek, 90)))
    return out
