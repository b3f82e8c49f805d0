"""One frame through the whole chain: image → mesh → peel → directors → order → defects (+ curvature).

:func:`run_frame` is ``nemo run``. Every intermediate result is written into one folder with
fixed names, so any step can be inspected or rerun alone with its own ``nemo`` command:

=====================  ==================================================================
``mesh.ply``           the reconstructed surface (both walls of a shell)
``mesh.inner.ply``     inner wall (``mesh.outer.ply``: outer wall) with outward normals
``layer.parquet``      peeled intensity per vertex of the analysed surface
``directors.parquet``  raw directors (random patch centres)
``order.parquet``      S and averaged director at every vertex
``curvature.parquet``  H, K (k1, k2) at every vertex
``directors.defects.parquet``  extra directors at vertices near each defect (refinement)
``defects.parquet``    defect positions and charges
``summary.json``       parameters, timings, peak memory, counts, Euler check
=====================  ==================================================================

Parameters (:data:`DEFAULTS`) are the paper's for its synthetic vesicle: marching-cubes step
2 µm, layer [0, 5] µm outward from the inner wall, 12 000 director patches of 20 µm, 50 µm
averaging -- with three deliberate changes that act on the *scale* at which the director field
is measured near a defect core:

* the structure-tensor integration scale is 4 micro-image pixels instead of nemo.directors'
  default of half the patch radius, and the micro-image pixel is :data:`PIXEL_PER_EDGE` (¼) of
  the mean edge length instead of ½ (so the σ = 1 px gradient kernel is ≈ ¼ edge and the
  integration ≈ 1 edge);
* after a first pass of :func:`nemo.defects.find_defects`, directors are measured at a random
  half (``defects.refine_directors``) of the vertices within the fit radius (0.75 × the
  averaging radius) of each defect
  (``directors.defects.parquet``) and the defects are found again with the union of both
  director tables. The 12 000 random patches leave only ~ 20 directors within 15 µm of a core,
  and the sub-vertex fit then scatters by ±1 µm with the random draw.

Why the scale matters (measured, benchmarks/bench_defects.py and the report of issue 5): a
gradient structure tensor weights orientations by the local gradient energy, i.e. by fibre
"ink". Around a +½ comet made of streamlines the ink is uneven (streamlines crowd on the head
side: for the ideal field the line density is ∝ |sin(φ/2)|), so the energy-weighted average of
the orientation moves the zero of the measured field towards the tail, by an amount that grows
with the gradient and integration scales (tangent-plane resampling of the image at 0.5 µm:
0.5-1.4 µm at σ = 1/2 µm, 1-3 µm at 1/8 µm, 2.6-3.3 µm at 2/4 µm; with 10 µm fibres whose
ink is nearly uniform, 3 × smaller). On the paper's vesicle the defaults give each defect
within ≈ 1.5 µm (systematic ≈ 1.2 µm towards the tail) instead of 0.5-3 µm. A YAML file may
override any parameter (nested by section, e.g. ``order: {radius: 30}``); unknown keys are an
error naming the key.
"""

from __future__ import annotations

import copy
import json
import os
import resource
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from nemo._log import logger, step
from nemo.errors import NemoError

#: Default parameters of ``nemo run`` (the paper's synthetic-vesicle analysis).
DEFAULTS: dict[str, dict[str, Any]] = {
    "mesh": {
        "sigma": None,          # Gaussian blur (µm); None = half the marching-cubes step
        "threshold": "yen",     # yen | otsu | number
        "step_um": 2.0,         # marching-cubes step (µm), converted to lateral voxels
        "smooth_iter": 10,      # Taubin iterations
        "split": "centre",      # centre | axis | none
        "axis": None,           # reference axis for split: axis
        "surface": "inner",     # analysed surface: inner | outer | whole
    },
    "peel": {
        "range": [0.0, 5.0],    # [d_min, d_max] µm along the (outward) normal
        "n_samples": 11,
        "reduce": "mean",       # mean | max
        "interp": "linear",     # linear | cubic
        "inward": False,
    },
    "directors": {
        "patch_radius": 20.0,   # µm
        "n_patches": 12000,
        "pixel": None,          # micro-image pixel (µm); None = PIXEL_PER_EDGE x mean edge
        "sigma": 4.0,           # structure-tensor scale (micro-image pixels, see module doc)
        "frames": "axis",       # axis | smooth
        "seed": 0,
    },
    "order": {
        "radius": 50.0,         # averaging radius (µm)
    },
    "curvature": {
        "enabled": True,
        "radius": None,         # fit radius (µm); None = 15 x mean edge length (benchmarks: 5x is noisy)
        "fraction": None,       # fraction of vertices fitted; None = morphology default
        "seed": 0,
    },
    "defects": {
        "s_threshold": None,
        "min_distance": None,
        "max_defects": None,
        "contour_radius": None,
        "curvature_correction": True,
        "curvature_source": "angle-defects",  # angle-defects | table (K x area from curvature.parquet)
        "winding_field": "average",            # average | directors
        "refine": "model",                     # model | q | none
        "refine_directors": 0.5,               # fraction of the vertices near each defect given a
                                               # director for the refinement (0 = off; module doc)
    },
}

#: Output file names inside OUTDIR.
FILES = {
    "mesh": "mesh.ply", "inner": "mesh.inner.ply", "outer": "mesh.outer.ply",
    "layer": "layer.parquet", "directors": "directors.parquet", "order": "order.parquet",
    "curvature": "curvature.parquet", "defects": "defects.parquet", "summary": "summary.json",
    "refine_directors": "directors.defects.parquet",
}

#: Default micro-image pixel of ``nemo run`` as a fraction of the mean edge length (module doc).
PIXEL_PER_EDGE = 0.25


def merge_config(overrides: dict | None, base: dict | None = None, where: str = "") -> dict:
    """Deep-merge ``overrides`` into a copy of ``base`` (default :data:`DEFAULTS`).

    Raises
    ------
    NemoError
        An unknown section or key (the message names it and lists the valid ones), or a section
        that is not a mapping.
    """
    base = copy.deepcopy(DEFAULTS if base is None else base)
    if overrides is None:
        return base
    if not isinstance(overrides, dict):
        raise NemoError(f"config{' section ' + where if where else ''} must be a mapping of keys to values, "
                        f"got {type(overrides).__name__}")
    for key, value in overrides.items():
        name = f"{where}.{key}" if where else str(key)
        if key not in base:
            raise NemoError(f"unknown config key {name!r}; valid keys here: {', '.join(base)}")
        if isinstance(base[key], dict):
            base[key] = merge_config(value, base[key], name)
        else:
            base[key] = value
    return base


def load_config(path: str | os.PathLike | None) -> dict:
    """Read a YAML config file and merge it over :data:`DEFAULTS` (validated)."""
    if path is None:
        return merge_config(None)
    import yaml

    path = Path(path)
    if not path.exists():
        raise NemoError(f"config file not found: {path}")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise NemoError(f"{path} is not valid YAML ({str(exc).splitlines()[0]})") from None
    return merge_config(data or {})


def _check(cfg: dict) -> None:
    """Validate values that the stage functions would only reject late."""
    m, p, d, o, dd = cfg["mesh"], cfg["peel"], cfg["directors"], cfg["order"], cfg["defects"]
    if m["surface"] not in ("inner", "outer", "whole"):
        raise NemoError(f"mesh.surface must be inner, outer or whole, got {m['surface']!r}")
    if m["split"] not in ("centre", "center", "axis", "none", None):
        raise NemoError(f"mesh.split must be centre, axis or none, got {m['split']!r}")
    if m["surface"] != "whole" and m["split"] in ("none", None):
        raise NemoError(f"mesh.surface {m['surface']!r} needs mesh.split centre or axis")
    if not (isinstance(m["step_um"], (int, float)) and m["step_um"] > 0):
        raise NemoError(f"mesh.step_um must be a positive length (µm), got {m['step_um']!r}")
    rng = p["range"]
    if not (isinstance(rng, (list, tuple)) and len(rng) == 2 and all(isinstance(v, (int, float)) for v in rng)
            and rng[0] <= rng[1]):
        raise NemoError(f"peel.range must be [d_min, d_max] with d_min <= d_max (µm), got {rng!r}")
    for key, val in (("directors.patch_radius", d["patch_radius"]), ("order.radius", o["radius"])):
        if not (isinstance(val, (int, float)) and val > 0):
            raise NemoError(f"{key} must be a positive length (µm), got {val!r}")
    rf = dd["refine_directors"]
    if isinstance(rf, bool) or not (isinstance(rf, (int, float)) and 0 <= rf <= 1):
        raise NemoError(f"defects.refine_directors must be a fraction in [0, 1] (0 = off), got {rf!r}")
    if d["pixel"] is not None and not (isinstance(d["pixel"], (int, float)) and d["pixel"] > 0):
        raise NemoError(f"directors.pixel must be a positive length (µm) or null, got {d['pixel']!r}")
    if dd["curvature_source"] not in ("angle-defects", "table"):
        raise NemoError(f"defects.curvature_source must be angle-defects or table, got {dd['curvature_source']!r}")
    if dd["curvature_source"] == "table" and not cfg["curvature"]["enabled"]:
        raise NemoError("defects.curvature_source: table needs curvature.enabled: true")


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def run_frame(
    image: str | os.PathLike,
    outdir: str | os.PathLike,
    config: dict | str | os.PathLike | None = None,
    t: int = 0,
    c: int = 0,
    spacing: tuple[float, float, float] | None = None,
) -> dict:
    """Run mesh → peel → directors → order → curvature → defects for one (t, c) of an image.

    Parameters
    ----------
    image : path-like
        TIFF hyperstack or OME-TIFF.
    outdir : path-like
        Output folder (created); file names in :data:`FILES`.
    config : dict or path-like, optional
        Overrides of :data:`DEFAULTS` (a nested dict, or a YAML file).
    t, c : int
        Time point and channel.
    spacing : (dz, dy, dx), optional
        Voxel size overriding the file's calibration.

    Returns
    -------
    dict
        The run summary (also written to ``summary.json``).
    """
    from nemo.defects import find_defects, refine_with_directors
    from nemo.directors import directors
    from nemo.io import read_stack
    from nemo.mesh import mean_edge_length, save_mesh, vertex_normals
    from nemo.order import order
    from nemo.peel import peel
    from nemo.surface import default_sigma, reconstruct, split_mesh
    from nemo.tables import write_table

    cfg = load_config(config) if not isinstance(config, dict) else merge_config(config)
    _check(cfg)
    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    for name in FILES.values():  # a previous run's outputs this run may not rewrite
        (out / name).unlink(missing_ok=True)
    timings: dict[str, float] = {}
    start = time.perf_counter()

    @contextmanager
    def timed(name: str):
        t0 = time.perf_counter()
        with step(name):
            yield
        timings[name] = round(time.perf_counter() - t0, 3)

    with timed("read"):
        volume, info = read_stack(image, t, c, spacing=spacing)
    sp = tuple(float(v) for v in info.spacing)
    unit = info.unit
    prov = {"image": str(image), "t": t, "c": c, "unit": unit, "command": "run"}

    mc = cfg["mesh"]
    step_vox = max(1, int(round(mc["step_um"] / max(sp[1], sp[2]))))
    with timed("mesh"):
        split = mc["split"] not in ("none", None)
        # blur: surface.default_sigma (half the marching-cubes sampling distance) unless given;
        # it merges voxel noise that would otherwise make the wall porous
        sigma = float(mc["sigma"]) if mc["sigma"] is not None else default_sigma(sp, step_vox)
        whole = reconstruct(volume, sp, sigma=sigma, threshold=mc["threshold"], step=step_vox,
                            smooth_iter=mc["smooth_iter"], keep="all" if split else "largest", unit=unit)
        meshes = {"mesh": whole}
        if split:
            by = "centre" if mc["split"] in ("centre", "center") else "axis"
            if by == "axis" and mc["axis"] is None:
                raise NemoError("mesh.split: axis needs mesh.axis: [x, y, z]")
            inner, outer = split_mesh(whole, by=by, axis=mc["axis"], keep="largest")
            meshes.update(inner=inner, outer=outer)
        for name, m in meshes.items():
            save_mesh(m, out / FILES[name])
    mesh = meshes["mesh" if mc["surface"] == "whole" else mc["surface"]]
    n = len(mesh.vertices)
    h = mean_edge_length(mesh)
    logger.info("analysed surface %s: %d vertices, mean edge %.3g %s", mc["surface"], n, h, unit)
    prov.update(mesh=FILES[mc["surface"] if mc["surface"] != "whole" else "mesh"], n_vertices=n)

    pc = cfg["peel"]
    with timed("peel"):
        normals = vertex_normals(mesh)
        intensity = peel(volume, sp, np.asarray(mesh.vertices), -normals if pc["inward"] else normals,
                         float(pc["range"][0]), float(pc["range"][1]), n_samples=int(pc["n_samples"]),
                         reduce=pc["reduce"], interp=pc["interp"])
        write_table(pd.DataFrame({"vertex": np.arange(n, dtype=np.int64), "intensity": intensity}),
                    out / FILES["layer"], **prov, **{f"peel_{k}": v for k, v in pc.items()})
    del volume

    dc = cfg["directors"]
    with timed("directors"):
        # ¼ edge, but micro-images no wider than the directors module allows (~200 px)
        pixel = (float(dc["pixel"]) if dc["pixel"] is not None
                 else max(PIXEL_PER_EDGE * h, float(dc["patch_radius"]) / 97.0))
        dkw = dict(patch_radius=float(dc["patch_radius"]), pixel=pixel, sigma=dc["sigma"],
                   frames=dc["frames"])
        ddf = directors(mesh, intensity, n_patches=None if dc["n_patches"] is None else int(dc["n_patches"]),
                        rng=dc["seed"], **dkw)
        # the parameters actually used (pixel resolved), so `nemo defects --layer` can re-measure alike
        write_table(ddf, out / FILES["directors"], **prov, **{**dc, "pixel": pixel})

    oc = cfg["order"]
    with timed("order"):
        odf = order(mesh, ddf, float(oc["radius"]), targets="all")
        write_table(odf, out / FILES["order"], **prov, radius=float(oc["radius"]), targets="all")

    cc = cfg["curvature"]
    kvals = None
    if cc["enabled"]:
        from nemo.morphology import curvature

        radius = float(cc["radius"]) if cc["radius"] is not None else 15.0 * h
        with timed("curvature"):
            cdf = curvature(mesh, radius, fraction=cc["fraction"], rng=cc["seed"])
            write_table(cdf, out / FILES["curvature"], **prov, radius=radius, fraction=cc["fraction"])
        from nemo.tables import field_on_vertices

        kvals = field_on_vertices(cdf, "K", n, FILES["curvature"], exact=True)

    fc = cfg["defects"]
    dkw_def = dict(
        curvature=kvals if fc["curvature_source"] == "table" else None,
        s_threshold=fc["s_threshold"], min_distance=fc["min_distance"],
        max_defects=fc["max_defects"], contour_radius=fc["contour_radius"],
        curvature_correction=bool(fc["curvature_correction"]), avg_radius=float(oc["radius"]),
        winding_field=fc["winding_field"], refine=fc["refine"],
    )
    with timed("defects"):
        ddefs = find_defects(mesh, odf, ddf, **dkw_def)
    n_refine = 0
    if fc["refine_directors"] > 0 and fc["refine"] == "model" and len(ddefs):
        with timed("refine"):
            frac = float(fc["refine_directors"])
            ddefs, extra = refine_with_directors(mesh, ddefs, odf, ddf, intensity, dkw, fraction=frac,
                                                 seed=dc["seed"], **dkw_def)
            n_refine = len(extra)
            write_table(extra, out / FILES["refine_directors"], **prov, **{**dc, "pixel": pixel},
                        centres=f"{frac:g} of the vertices near each first-pass defect")
    write_table(ddefs, out / FILES["defects"], **prov, euler_check=ddefs.attrs["euler_check"],
                parameters=ddefs.attrs["parameters"])

    total = time.perf_counter() - start
    s = odf["S"].to_numpy()
    summary = {
        "image": str(image), "t": t, "c": c, "spacing": list(sp), "unit": unit,
        "outdir": str(out), "files": {k: v for k, v in FILES.items() if (out / v).exists() or k == "summary"},
        "config": cfg, "marching_cubes_step_voxels": step_vox, "mesh_sigma": sigma,
        "mesh": {"surface": mc["surface"], "vertices": n, "faces": int(len(mesh.faces)),
                 "mean_edge": h, "area": float(mesh.area)},
        "n_directors": int(len(ddf)), "n_refine_directors": int(n_refine), "director_pixel": pixel,
        "S": {"mean": float(np.nanmean(s)), "median": float(np.nanmedian(s))},
        "defects": ddefs[["x", "y", "z", "charge", "charge_rounded", "S"]].to_dict(orient="records"),
        "euler_check": ddefs.attrs["euler_check"],
        "timings_s": timings, "total_s": round(total, 3), "peak_rss_mb": round(_peak_rss_mb(), 1),
    }
    path = out / FILES["summary"]
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    tmp.write_text(json.dumps(summary, indent=2, default=_json_default) + "\n")
    os.replace(tmp, path)
    logger.info("nemo run: %d defects, Σ charge %.3f (χ = %d) in %.1f s, peak memory %.0f MB",
                len(ddefs), summary["euler_check"]["sum_charge"],
                summary["euler_check"]["euler_characteristic"], total, summary["peak_rss_mb"])
    return summary


def _json_default(obj):
    if isinstance(obj, (np.integer, np.floating, np.bool_)):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    return str(obj)
