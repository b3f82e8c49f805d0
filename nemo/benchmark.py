"""Benchmark and validation protocol (issue 8): case generation, analytic shapes, scoring.

The protocol runs through the Snakemake workflow (``workflow/rules/benchmark.smk``, enabled by
a ``benchmark:`` config section, e.g. ``config/benchmark.yaml``); this module holds everything
the rules compute and nothing about Snakemake:

* :func:`expand_cases` turns the ``benchmark:`` section (a base case, sweeps over dotted keys,
  random rotations) into cases; each case is ``nemo synth`` options (the volume) plus
  per-dataset overrides of the workflow's analysis sections. Cases with the same volume share it.
* :func:`shape_volume` generates analytic shapes (ellipsoid, torus, concentric shells of
  spheres/ellipsoids) as blurred solids from their signed distance, so that ``nemo mesh``
  reconstructs them exactly like a microscopy stack; :func:`score_shape` scores curvature and
  thickness on the reconstructed mesh against the analytic values.
* :func:`match_defects`, :func:`score_defects`, :func:`director_errors`, :func:`score_vesicle`
  score one analysed vesicle against its ground truth (``nemo.synthetic.read_truth``).
* :func:`aggregate` collects the scores and Snakemake's per-job benchmark files into
  ``summary/*.parquet``, a markdown table and plots.

Command line (used by the rules): ``python -m nemo.benchmark {shape,score,score-shape,aggregate}``.
"""

from __future__ import annotations

import argparse
import copy
import hashlib
import json
import os
import sys
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import pandas as pd
from scipy.optimize import linear_sum_assignment
from scipy.special import erf

from nemo import atomic
from nemo.errors import NemoError

#: Default matching radius for defects as a fraction of the vesicle radius.
MATCH_FRACTION = 0.15


# --------------------------------------------------------------------------------------------
# cases
# --------------------------------------------------------------------------------------------
def _set_dotted(d: dict, key: str, value: Any) -> None:
    parts = key.split(".")
    if parts[0] not in ("synth", "run") or len(parts) < 2:
        raise NemoError(f"benchmark sweep key {key!r} must start with 'synth.' or 'run.' "
                        "(e.g. synth.noise, run.order.radius)")
    cur = d
    for p in parts[:-1]:
        cur = cur.setdefault(p, {})
        if not isinstance(cur, dict):
            raise NemoError(f"benchmark sweep key {key!r}: {p!r} is not a section")
    cur[parts[-1]] = copy.deepcopy(value)


def _slug(value: Any) -> str:
    if isinstance(value, (list, tuple)):
        return "x".join(_slug(v) for v in value)
    if isinstance(value, float) and value.is_integer():
        value = int(value)
    return str(value).replace(".", "p").replace("-", "m") if isinstance(value, (int, float)) else str(value)


def volume_id(synth: dict) -> str:
    """Stable short id of a volume from its ``nemo synth`` options."""
    text = json.dumps(synth, sort_keys=True)
    return "v" + hashlib.sha1(text.encode()).hexdigest()[:10]


def expand_cases(bench: dict) -> dict[str, dict]:
    """Expand a ``benchmark:`` config section into cases.

    Parameters
    ----------
    bench : dict
        ``base`` (``synth``: ``nemo synth`` options, ``run``: overrides of the analysis sections),
        ``rotations`` (seeds of random rotations of the defect set; also the fibre/noise seed),
        ``sweeps`` (name -> ``{key: "synth.noise", values: [...], set: {dotted: value}}``) and
        ``cases`` (name -> ``{synth: ..., run: ..., rotations: [...]}`` or
        ``{dataset: NAME, run: ...}`` to analyse a workflow dataset's image as one point).

    Returns
    -------
    dict
        ``case id -> {case, sweep, parameter, value, rotation, synth, run, volume, dataset}``;
        ``volume`` is :func:`volume_id` of ``synth`` (None for dataset cases).
    """
    base = bench.get("base") or {}
    base = {"synth": dict(base.get("synth") or {}), "run": copy.deepcopy(base.get("run") or {})}
    rotations = list(bench.get("rotations") or [0])
    cases: dict[str, dict] = {}

    def add(cid, sweep, key, value, rot, spec, dataset=None):
        synth = dict(spec["synth"])
        if dataset is None:
            synth.setdefault("seed", int(rot))
            if rot is not None:
                synth["rotate_random"] = int(rot)
        if cid in cases:
            raise NemoError(f"benchmark: two cases are called {cid!r}; rename a sweep or case")
        cases[cid] = {
            "case": cid, "sweep": sweep, "parameter": key, "value": value,
            "value_label": _slug(value) if value is not None else "", "rotation": rot,
            "synth": synth, "run": spec["run"], "dataset": dataset,
            "volume": None if dataset is not None else volume_id(synth),
        }

    for name, sw in (bench.get("sweeps") or {}).items():
        if "key" not in sw or not sw.get("values"):
            raise NemoError(f"benchmark.sweeps.{name} needs 'key' (e.g. synth.noise) and 'values'")
        for value in sw["values"]:
            for rot in sw.get("rotations", rotations):
                spec = copy.deepcopy(base)
                for k, v in (sw.get("set") or {}).items():
                    _set_dotted(spec, k, v)
                _set_dotted(spec, sw["key"], value)
                add(f"{name}-{_slug(value)}-r{rot}", name, sw["key"], value, rot, spec)
    for name, c in (bench.get("cases") or {}).items():
        spec = copy.deepcopy(base)
        if c.get("dataset"):
            spec = {"synth": {}, "run": copy.deepcopy(c.get("run") or {})}
            add(name, name, None, None, None, spec, dataset=c["dataset"])
            continue
        spec["synth"].update(c.get("synth") or {})
        for k, v in (c.get("run") or {}).items():
            spec["run"].setdefault(k, {}).update(v)
        for rot in c.get("rotations", rotations):
            add(f"{name}-r{rot}", name, None, None, rot, spec)
    if not cases:
        raise NemoError("benchmark: no cases (give 'sweeps' and/or 'cases')")
    return cases


def expand_shapes(bench: dict) -> dict[str, dict]:
    """``benchmark.shapes`` (name -> :func:`shape_volume` spec) with defaults filled in."""
    out = {}
    for name, spec in (bench.get("shapes") or {}).items():
        s = dict(spec)
        if s.get("kind") not in SHAPES:
            raise NemoError(f"benchmark.shapes.{name}.kind must be one of {', '.join(SHAPES)}")
        s.setdefault("spacing", [1.0, 1.0, 1.0])
        s.setdefault("radius_edges", [5.0])
        s.setdefault("mesh", {})
        out[name] = s
    return out


# --------------------------------------------------------------------------------------------
# analytic shapes
# --------------------------------------------------------------------------------------------
SHAPES = ("ellipsoid", "torus", "shells")


def _ellipsoid_sdf(p: np.ndarray, axes: Sequence[float]) -> np.ndarray:
    """First-order signed distance to an ellipsoid (exact zero set; ≈ distance nearby)."""
    a = np.asarray(axes, float)
    q = np.sqrt(((p / a) ** 2).sum(-1))
    grad = np.linalg.norm(p / a**2, axis=-1) / np.maximum(q, 1e-12)
    return (q - 1.0) / np.maximum(grad, 1e-12)


def _torus_sdf(p: np.ndarray, major: float, minor: float) -> np.ndarray:
    rho = np.hypot(p[..., 0], p[..., 1])
    return np.hypot(rho - major, p[..., 2]) - minor


def _extent(spec: dict) -> np.ndarray:
    k = spec["kind"]
    if k == "ellipsoid":
        return np.asarray(spec["axes"], float)
    if k == "torus":
        R, r = spec["major"], spec["minor"]
        return np.array([R + r, R + r, r], float)
    return np.asarray(spec["outer"], float)


def shape_sdf(spec: dict, p: np.ndarray) -> np.ndarray:
    """Signed distance (negative inside the solid) of a shape centred at the origin."""
    k = spec["kind"]
    if k == "ellipsoid":
        return _ellipsoid_sdf(p, spec["axes"])
    if k == "torus":
        return _torus_sdf(p, spec["major"], spec["minor"])
    if k == "shells":
        return np.maximum(_ellipsoid_sdf(p, spec["outer"]), -_ellipsoid_sdf(p, spec["inner"]))
    raise NemoError(f"unknown shape kind {k!r}; choose one of {', '.join(SHAPES)}")


def shape_volume(spec: dict, rng: np.random.Generator | int | None = None) -> tuple[np.ndarray, dict]:
    """A blurred solid shape as a uint8 (Z, Y, X) volume and its analytic description.

    Parameters
    ----------
    spec : dict
        ``kind``: ``ellipsoid`` (``axes`` [a, b, c] µm along x, y, z), ``torus`` (``major``,
        ``minor`` µm, axis z) or ``shells`` (solid between the ellipsoids ``inner`` and ``outer``,
        [a, b, c] each; equal axes = concentric spheres); ``spacing`` [dz, dy, dx] µm; optional
        ``blur`` (µm, default one lateral voxel: an error-function edge), ``margin`` (µm),
        ``noise`` (std, 0-255 scale), ``foreground``/``background`` intensities.
    rng : Generator or int, optional
        For the noise.

    Returns
    -------
    volume : ndarray of uint8, shape (Z, Y, X)
    truth : dict
        The spec plus ``centre`` (physical x, y, z) and ``threshold`` (mid intensity).
    """
    need = {"ellipsoid": ("axes",), "torus": ("major", "minor"), "shells": ("inner", "outer")}
    if spec.get("kind") not in need:
        raise NemoError(f"unknown shape kind {spec.get('kind')!r}; choose one of {', '.join(SHAPES)}")
    missing = [k for k in need[spec["kind"]] if k not in spec]
    if missing:
        raise NemoError(f"shape '{spec['kind']}' needs {', '.join(missing)} (µm)")
    sp = np.asarray(spec.get("spacing", [1.0, 1.0, 1.0]), float)
    if sp.shape != (3,) or np.any(sp <= 0):
        raise NemoError(f"shape spacing must be [dz, dy, dx] > 0, got {spec.get('spacing')}")
    blur = float(spec.get("blur", sp[2]))
    fg, bg = float(spec.get("foreground", 200)), float(spec.get("background", 20))
    ext = _extent(spec)
    margin = float(spec.get("margin", 4 * blur + 3 * sp.max()))
    half = ext + margin  # x, y, z
    n = (2 * np.ceil(half / sp[::-1]) + 1).astype(int)  # voxels along x, y, z
    centre = (n - 1) / 2 * sp[::-1]
    z = np.arange(n[2]) * sp[0] - centre[2]
    y = np.arange(n[1]) * sp[1] - centre[1]
    x = np.arange(n[0]) * sp[2] - centre[0]
    vol = np.empty((n[2], n[1], n[0]), np.float32)
    for i, zi in enumerate(z):  # plane by plane: bounded memory (not a hot path)
        p = np.stack(np.broadcast_arrays(x[None, :], y[:, None], np.full((1, 1), zi)), -1)
        d = shape_sdf(spec, p)
        vol[i] = bg + (fg - bg) * 0.5 * (1 - erf(d / (np.sqrt(2) * blur)))
    if spec.get("noise"):
        gen = np.random.default_rng(rng)
        vol += gen.normal(0, float(spec["noise"]), vol.shape).astype(np.float32)
    vol = np.clip(np.rint(vol), 0, 255).astype(np.uint8)
    truth = dict(spec)
    truth.update(centre=centre.tolist(), threshold=(fg + bg) / 2, spacing=sp.tolist())
    return vol, truth


def _project_ellipsoid(p: np.ndarray, axes) -> tuple[np.ndarray, np.ndarray]:
    """Radial projection onto the ellipsoid and its outward unit normal there."""
    a = np.asarray(axes, float)
    q = np.sqrt(((p / a) ** 2).sum(-1, keepdims=True))
    s = p / q
    n = s / a**2
    return s, n / np.linalg.norm(n, axis=-1, keepdims=True)


def ellipsoid_curvature(p: np.ndarray, axes) -> tuple[np.ndarray, np.ndarray]:
    """Analytic mean and Gaussian curvature (outward normal: sphere H = +1/R) at points ``p``
    (N, 3), projected radially onto the ellipsoid x²/a² + y²/b² + z²/c² = 1."""
    a2 = np.asarray(axes, float) ** 2
    s, _ = _project_ellipsoid(p, axes)
    w = (s**2 / a2**2).sum(-1)
    prod = a2.prod()
    K = 1.0 / (prod * w**2)
    H = (a2.sum() - (s**2).sum(-1)) / (2.0 * prod * w**1.5)
    return H, K


def torus_curvature(p: np.ndarray, major: float, minor: float) -> tuple[np.ndarray, np.ndarray]:
    """Analytic H (outward normal) and K of a torus (axis z) at the nearest surface points."""
    rho = np.hypot(p[:, 0], p[:, 1])
    cosv = (rho - major) / np.maximum(np.hypot(rho - major, p[:, 2]), 1e-12)
    den = minor * (major + minor * cosv)
    return (major + 2 * minor * cosv) / (2 * den), cosv / den


def shell_thickness(p: np.ndarray, inner, outer) -> np.ndarray:
    """Exact distance along the inner ellipsoid's outward normal (at the radial projection of
    ``p``) to the outer ellipsoid."""
    s, n = _project_ellipsoid(p, inner)
    A2 = np.asarray(outer, float) ** 2
    qa = (n**2 / A2).sum(-1)
    qb = 2 * (s * n / A2).sum(-1)
    qc = (s**2 / A2).sum(-1) - 1
    return (-qb + np.sqrt(qb**2 - 4 * qa * qc)) / (2 * qa)


def _norm_err(est: np.ndarray, exact: np.ndarray) -> np.ndarray:
    """|est − exact| / RMS(exact) (= relative error for constant fields)."""
    return np.abs(est - exact) / np.sqrt(np.mean(exact**2))


def score_shape(mesh_path: str | os.PathLike, truth: dict) -> list[dict]:
    """Curvature and thickness of a reconstructed analytic shape against the exact values.

    Curvature (``nemo.morphology.curvature``) is fitted at every ``radius_edges`` × mean edge
    length; errors are |est − exact| / RMS(exact) over the vertices (the relative error for a
    sphere). Shells are split into inner/outer walls (``nemo.surface.split_mesh``) and the
    thickness from the inner wall along its normals is compared with the exact normal-ray
    distance (µm and in voxels of the largest spacing).

    Returns
    -------
    list of dict
        One row per curvature radius.
    """
    from nemo.mesh import load_mesh, mean_edge_length
    from nemo.morphology import curvature, measure, thickness
    from nemo.surface import split_mesh

    mesh = load_mesh(mesh_path)
    c = np.asarray(truth["centre"], float)
    kind = truth["kind"]
    rows = []
    base = {"shape": truth.get("name", kind), "kind": kind,
            "dz_dx": truth["spacing"][0] / truth["spacing"][2], "dx": truth["spacing"][2]}
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
        d = thickness(surf, outer, direction="outward")
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
    for fac in truth.get("radius_edges", [5.0]):
        radius = float(fac) * edge
        t0 = time.perf_counter()
        cdf = curvature(surf, radius, rng=0)
        t_curv = time.perf_counter() - t0
        H, K = cdf["H"].to_numpy(), cdf["K"].to_numpy()
        ok = np.isfinite(H) & np.isfinite(K)
        eh, ek = _norm_err(H[ok], H0[ok]), _norm_err(K[ok], K0[ok])
        strong = np.abs(K0) > 0.2 * np.abs(K0).max()
        rows.append({
            **base, "n_vertices": len(surf.vertices), "mean_edge": edge,
            "radius_edges": float(fac), "curvature_radius": radius,
            "H_err_median": float(np.median(eh)), "H_err_p90": float(np.percentile(eh, 90)),
            "K_err_median": float(np.median(ek)), "K_err_p90": float(np.percentile(ek, 90)),
            "K_sign_agreement": float(np.mean(np.sign(K[ok & strong]) == np.sign(K0[ok & strong]))),
            "gauss_bonnet_ratio": float(m.get("gauss_bonnet_ratio", np.nan) or np.nan),
            "integral_K": float(m.get("integral_K", np.nan)),
            "euler_characteristic": int(m.get("euler_characteristic", 0)),
            "curvature_valid": float(ok.mean()), "time_curvature_s": t_curv, **thick,
        })
    return rows


# --------------------------------------------------------------------------------------------
# vesicle scores
# --------------------------------------------------------------------------------------------
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
        :func:`score_defects` plus ``angle_err_median/p90`` (raw directors, all),
        ``angle_err_ordered_median/p90`` (raw directors in the ordered region),
        ``avg_angle_err_ordered_median`` (averaged field), ``S_ordered_median/p10``,
        ``H_relerr_median/p90``, ``K_relerr_median/p90`` (sphere of radius R).
    """
    from nemo.synthetic import truth_directors

    R = float(truth["radius"])
    tdf = truth_defects(truth, t, layer)
    out = score_defects(defects, tdf, match_radius or MATCH_FRACTION * R)
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


# --------------------------------------------------------------------------------------------
# aggregation
# --------------------------------------------------------------------------------------------
def read_snakemake_benchmark(path: str | os.PathLike) -> dict:
    """Wall time ``s`` and peak ``max_rss`` (MB) of a Snakemake ``benchmark:`` file (mean over repeats)."""
    df = pd.read_csv(path, sep="\t")
    out = {"s": float(df["s"].mean())}
    for col in ("max_rss", "cpu_time", "mean_load"):
        if col in df:
            out[col] = float(pd.to_numeric(df[col], errors="coerce").mean())
    return out


#: Score columns summarised per sweep value (mean over rotations).
SWEEP_COLUMNS = [
    "detection_rate", "false_positives", "loc_err_mean", "loc_err_max", "charge_err_mean",
    "charge_correct", "all_found", "angle_err_median", "angle_err_p90", "angle_err_ordered_median",
    "S_ordered_median", "H_relerr_median", "K_relerr_median", "n_vertices", "time_total_s",
    "peak_rss_mb",
]


def aggregate(
    scores: Sequence[str | os.PathLike],
    shape_scores: Sequence[str | os.PathLike],
    stage_files: Sequence[str | os.PathLike],
    outdir: str | os.PathLike,
) -> dict[str, pd.DataFrame]:
    """Collect per-case scores into ``outdir``: Parquet tables, ``benchmark.md`` and plots.

    Parameters
    ----------
    scores : paths of per-case ``score.json`` (case metadata + scores + ``timings_s``).
    shape_scores : paths of per-shape ``score.json`` (``{"rows": [...]}``).
    stage_files : Snakemake benchmark files, named ``.../<group>/<stage>/<job>.tsv``.
    outdir : summary folder.

    Returns
    -------
    dict of DataFrame
        ``cases``, ``sweeps``, ``shapes``, ``stages`` (also written as Parquet).
    """
    from nemo.tables import write_table

    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    rows, stage_rows = [], []
    for f in scores:
        s = json.loads(Path(f).read_text())
        timings = s.pop("timings_s", {}) or {}
        for stage, sec in timings.items():
            stage_rows.append({"case": s["case"], "sweep": s["sweep"], "stage": stage, "s": sec,
                               "max_rss": np.nan, "source": "workflow"})
        rows.append(s)
    cases = pd.DataFrame(rows)
    case_sweep = dict(zip(cases["case"], cases["sweep"])) if len(cases) else {}
    shapes = pd.DataFrame([r for f in shape_scores for r in json.loads(Path(f).read_text())["rows"]])
    for f in stage_files:
        p = Path(f)
        b = read_snakemake_benchmark(p)
        group = p.parent.parent.name
        if group == "benchmarks":  # results/{dataset}/benchmarks/{rule}/{job}.tsv: the workflow's rules
            group = "workflow-" + p.parent.parent.parent.name
        elif p.stem in case_sweep:  # a benchmark case's job: its sweep
            group = case_sweep[p.stem]
        stage_rows.append({"case": p.stem, "sweep": group, "stage": p.parent.name,
                           "s": b["s"], "max_rss": b.get("max_rss", np.nan), "source": "snakemake"})
    stages = pd.DataFrame(stage_rows, columns=["case", "sweep", "stage", "s", "max_rss", "source"])
    if len(cases):
        cases["value_label"] = cases["value_label"].astype(str)
        cols = [c for c in SWEEP_COLUMNS if c in cases]
        num = cases[cols].astype(float)
        grp = pd.concat([cases[["sweep", "parameter", "value_label"]], num], axis=1)
        g = grp.groupby(["sweep", "parameter", "value_label"], sort=False, dropna=False)
        sweeps = g.mean()
        sweeps["n_cases"] = g.size()
        sweeps = sweeps.reset_index()
        sweeps["parameter"] = sweeps["parameter"].fillna("")
    else:
        sweeps = pd.DataFrame()
    # Parquet needs one type per column: sweep values are kept as labels
    cases_out = cases.drop(columns=[c for c in ("value", "synth", "run") if c in cases])
    if len(cases):
        cases_out["synth"] = cases["synth"].map(lambda d: json.dumps(d, sort_keys=True))
        cases_out["run"] = cases["run"].map(lambda d: json.dumps(d, sort_keys=True))
    for name, df in (("cases", cases_out), ("sweeps", sweeps), ("shapes", shapes), ("stages", stages)):
        write_table(df, out / f"{name}.parquet", kind=f"benchmark-{name}")
    (out / "benchmark.md").write_text(markdown(cases, sweeps, shapes, stages))
    plot(cases, stages, out / "plots")
    return {"cases": cases, "sweeps": sweeps, "shapes": shapes, "stages": stages}


def _fmt(v, nd=2):
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "–"
    if isinstance(v, (bool, np.bool_)):
        return "yes" if v else "no"
    if isinstance(v, (int, np.integer)):
        return str(v)
    return f"{v:.{nd}f}"


def _table(df: pd.DataFrame, cols: list[tuple[str, str, int]]) -> str:
    cols = [c for c in cols if c[0] in df]
    lines = ["| " + " | ".join(h for _, h, _ in cols) + " |", "|" + "---|" * len(cols)]
    for _, r in df.iterrows():
        lines.append("| " + " | ".join(_fmt(r[c], nd) if nd >= 0 else str(r[c]) for c, _, nd in cols) + " |")
    return "\n".join(lines)


def _stage_record(stage_files: list[str], defects_path: str) -> dict:
    """Time per stage (Snakemake benchmark files of the frame's rules) and the surface's topology."""
    from nemo.tables import read_provenance

    timings: dict[str, float] = {}
    rss = 0.0
    for f in stage_files:
        row = pd.read_csv(f, sep="\t").iloc[0]
        stage = Path(f).parent.name
        timings[stage] = round(timings.get(stage, 0.0) + float(row["s"]), 3)
        rss = max(rss, float(pd.to_numeric(row.get("max_rss"), errors="coerce") or 0.0))
    prov = read_provenance(defects_path)
    check = prov.get("euler_check") or {}
    return {"timings_s": timings, "time_total_s": round(sum(timings.values()), 3), "peak_rss_mb": rss or None,
            "n_vertices": prov.get("n_vertices"), "closed": check.get("closed"),
            "euler_characteristic": check.get("euler_characteristic")}


def markdown(cases: pd.DataFrame, sweeps: pd.DataFrame, shapes: pd.DataFrame, stages: pd.DataFrame) -> str:
    """The benchmark summary as markdown tables (sweeps, shapes, stage times)."""
    parts = ["# NEMO benchmark summary", ""]
    if len(sweeps):
        parts += ["## Synthetic vesicles (mean over random rotations)", "",
                  "detection = matched / true defects; FP = false positives per case; loc = "
                  "localisation error (µm, matched defects); |Δq| = charge error; θ = raw director "
                  "angle error vs the analytic field (°, all directors / P90 / ordered region); "
                  "S = median S in the ordered region; H, K = median relative curvature errors; "
                  "time = the frame's per-stage jobs of the workflow, summed (s); RSS = largest job's peak "
                  "memory (MB).", "",
                  _table(sweeps, [("sweep", "sweep", -1), ("value_label", "value", -1), ("n_cases", "n", 0),
                                  ("detection_rate", "detection", 2), ("false_positives", "FP", 2),
                                  ("loc_err_mean", "loc (µm)", 2), ("loc_err_max", "loc max", 2),
                                  ("charge_err_mean", "|Δq|", 3), ("charge_correct", "q right", 2),
                                  ("angle_err_median", "θ med", 2), ("angle_err_p90", "θ P90", 2),
                                  ("angle_err_ordered_median", "θ ordered", 2),
                                  ("S_ordered_median", "S ordered", 3), ("H_relerr_median", "H err", 4),
                                  ("K_relerr_median", "K err", 4), ("n_vertices", "vertices", 0),
                                  ("time_total_s", "time (s)", 1), ("peak_rss_mb", "RSS (MB)", 0)]), ""]
    if len(shapes):
        parts += ["## Analytic shapes: curvature and thickness", "",
                  "errors |est − exact| / RMS(exact) over the vertices (relative error for a "
                  "sphere); thickness error in µm along the inner wall's normals.", "",
                  _table(shapes, [("shape", "shape", -1), ("dz_dx", "dz/dx", 0), ("n_vertices", "vertices", 0),
                                  ("radius_edges", "radius (edges)", 1), ("curvature_radius", "radius (µm)", 1),
                                  ("H_err_median", "H med", 4), ("H_err_p90", "H P90", 4),
                                  ("K_err_median", "K med", 4), ("K_err_p90", "K P90", 4),
                                  ("K_sign_agreement", "K sign", 3), ("gauss_bonnet_ratio", "∫K/2πχ", 4),
                                  ("thickness_err_median", "thick. med (µm)", 3),
                                  ("thickness_err_p90", "thick. P90 (µm)", 3),
                                  ("thickness_err_median_vox", "thick. med (vox)", 3)]), ""]
    if len(stages):
        st = (stages.groupby(["source", "sweep", "stage"], sort=False)
              .agg(n=("s", "size"), s_median=("s", "median"), s_max=("s", "max"),
                   max_rss_median=("max_rss", "median")).reset_index())
        parts += ["## Time per stage", "",
                  "`workflow`: the benchmark files of the cases' per-stage jobs (median over the cases "
                  "of a sweep); `snakemake`: other jobs (volumes, shapes); max_rss MB.", "",
                  _table(st, [("source", "source", -1), ("sweep", "group", -1), ("stage", "stage", -1),
                              ("n", "jobs", 0), ("s_median", "s (median)", 2), ("s_max", "s (max)", 2),
                              ("max_rss_median", "max_rss (MB)", 0)]), ""]
    return "\n".join(parts) + "\n"


def plot(cases: pd.DataFrame, stages: pd.DataFrame, outdir: str | os.PathLike) -> list[Path]:
    """Error vs noise, error vs anisotropy, errors vs analysis parameters, time per stage (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    written = []
    metrics = [("detection_rate", "detection rate"), ("false_positives", "false positives / case"),
               ("loc_err_mean", "localisation error (µm)"), ("angle_err_median", "director error, median (°)")]

    def sweep_plot(mask, xlabel, fname, xfun=float):
        sub = cases[mask].copy()
        if not len(sub):
            return
        sub["x"] = sub["value"].map(xfun)
        fig, axes = plt.subplots(1, len(metrics), figsize=(4 * len(metrics), 3.2))
        for (col, label), ax in zip(metrics, axes):
            if col not in sub:
                continue
            for sweep, ss in sub.groupby("sweep"):
                g = ss.groupby("x")[col]
                m, sd = g.mean(), g.std().fillna(0)
                ax.errorbar(m.index, m.values, yerr=sd.values, marker="o", capsize=3, label=sweep)
                ax.scatter(ss["x"], ss[col], s=8, alpha=0.4)
            ax.set_xlabel(xlabel)
            ax.set_ylabel(label)
            ax.grid(alpha=0.3)
        axes[0].legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(outdir / fname, dpi=110)
        plt.close(fig)
        written.append(outdir / fname)

    if len(cases) and "parameter" in cases:
        par = cases["parameter"].fillna("")
        sweep_plot(par == "synth.noise", "noise std (0-255 scale)", "error_vs_noise.png")
        sweep_plot(par == "synth.spacing", "voxel anisotropy dz/dx", "error_vs_anisotropy.png",
                   lambda v: float(v[0]) / float(v[2]))
        for key, label, fname in (("run.mesh.step", "marching-cubes step (voxels)", "error_vs_mc_step.png"),
                                  ("run.directors.patch_radius", "director patch radius (µm)",
                                   "error_vs_patch_radius.png"),
                                  ("run.order.radius", "averaging radius (µm)", "error_vs_averaging_radius.png")):
            sweep_plot(par == key, label, fname)
    if len(stages):
        run = stages[stages["source"] == "workflow"]
        smk = stages[stages["source"] == "snakemake"]
        fig, axes = plt.subplots(1, 2, figsize=(11, 3.8))
        if len(run):
            order = list(dict.fromkeys(run["stage"]))
            data = [run.loc[run["stage"] == s, "s"].to_numpy() for s in order]
            axes[0].boxplot(data)
            axes[0].set_xticks(range(1, len(order) + 1), order)
            axes[0].set_ylabel("wall time (s)")
            axes[0].set_title("workflow stages, all sweep cases")
            axes[0].tick_params(axis="x", rotation=30)
        if len(smk):
            g = smk.groupby("stage").agg(s=("s", "median"), rss=("max_rss", "median")).sort_values("s")
            axes[1].barh(g.index, g["s"], color="tab:blue")
            axes[1].set_xlabel("wall time per job, median (s)")
            axes[1].set_title("Snakemake rules (benchmark files)")
            for i, (sv, rss) in enumerate(zip(g["s"], g["rss"])):
                if np.isfinite(rss):
                    axes[1].text(sv, i, f" {rss:.0f} MB", va="center", fontsize=7)
        fig.tight_layout()
        fig.savefig(outdir / "time_per_stage.png", dpi=110)
        plt.close(fig)
        written.append(outdir / "time_per_stage.png")
    return written


# --------------------------------------------------------------------------------------------
# command line (used by workflow/rules/benchmark.smk)
# --------------------------------------------------------------------------------------------
def _read(path, kind=None):
    return pd.read_parquet(path) if path else None


def _atomic_json(obj: dict, path: str | os.PathLike) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic.write_json(path, obj, indent=1)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m nemo.benchmark`` sub-commands: shape, score, score-shape, aggregate."""
    ap = argparse.ArgumentParser(prog="python -m nemo.benchmark", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    a = sub.add_parser("shape", help="write an analytic shape as a hyperstack + truth JSON")
    a.add_argument("spec", help="JSON spec (see shape_volume)")
    a.add_argument("-o", "--output", required=True)
    a.add_argument("--truth", required=True)
    a = sub.add_parser("score-shape", help="score curvature/thickness of a reconstructed shape")
    a.add_argument("mesh")
    a.add_argument("truth")
    a.add_argument("-o", "--output", required=True)
    a = sub.add_parser("score", help="score one analysed vesicle against its truth")
    a.add_argument("--truth", required=True)
    a.add_argument("--defects", required=True)
    a.add_argument("--directors")
    a.add_argument("--order")
    a.add_argument("--curvature")
    a.add_argument("--stage-files", nargs="*", default=[],
                   help="Snakemake benchmark files (.tsv) of the frame's per-stage rules (time, memory)")
    a.add_argument("--case", default="{}", help="case metadata (JSON)")
    a.add_argument("--match-radius", type=float)
    a.add_argument("--ordered-distance", type=float)
    a.add_argument("-o", "--output", required=True)
    a = sub.add_parser("aggregate", help="collect scores into summary tables and plots")
    a.add_argument("--scores", nargs="*", default=[])
    a.add_argument("--shapes", nargs="*", default=[])
    a.add_argument("--stages", nargs="*", default=[])
    a.add_argument("-o", "--output", required=True)
    args = ap.parse_args(argv)
    try:
        if args.cmd == "shape":
            from nemo.io import write_hyperstack

            spec = json.loads(args.spec)
            vol, truth = shape_volume(spec, rng=spec.get("seed", 0))
            write_hyperstack(args.output, vol, truth["spacing"], unit="um", axes="ZYX")
            _atomic_json(truth, args.truth)
        elif args.cmd == "score-shape":
            truth = json.loads(Path(args.truth).read_text())
            _atomic_json({"rows": score_shape(args.mesh, truth)}, args.output)
        elif args.cmd == "score":
            from nemo.synthetic import read_truth

            truth = read_truth(args.truth)
            case = json.loads(args.case)
            sc = score_vesicle(truth, _read(args.defects), _read(args.directors), _read(args.order),
                               _read(args.curvature), ordered_distance=args.ordered_distance,
                               match_radius=args.match_radius)
            sc.update(_stage_record(args.stage_files, args.defects))
            sc.update(radius=truth["radius"], dz_dx=truth["spacing"][0] / truth["spacing"][2],
                      noise=truth.get("parameters", {}).get("noise"))
            _atomic_json({**case, **sc}, args.output)
        elif args.cmd == "aggregate":
            aggregate(args.scores, args.shapes, args.stages, args.output)
    except NemoError as exc:
        print(f"nemo benchmark: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
