"""Per-stage wall time, CPU time and peak memory, on the paper-scale vesicle and a ≥ 1M-vertex
mesh; plus the director step as the paper describes it (a Python loop over patches: scipy
``griddata`` onto a micro-image, then OrientationPy) against NEMO's batched implementation.

Every stage runs in its own forked child process that loads its inputs from the work folder,
so the peak RSS reported for a stage is that stage's (inputs included), not the maximum of a
whole script. Prints a markdown table (also written to WORKDIR/stages.md and stages.json).

    python benchmarks/bench_stages.py                       # paper vesicle + 1M mesh + loop (~6 min)
    python benchmarks/bench_stages.py --skip-big --n-loop 200
    python benchmarks/bench_stages.py --workdir /tmp/stages # keep (and reuse) the data

Stages (library calls, the parameters of ``nemo run``/config/paper.yaml): synth (``vesicle``),
mesh (``reconstruct`` step 2 µm + ``split_mesh``; step 1 µm for the big mesh), curvature
(20 000 quadric samples, radius 20 µm, + interpolation), thickness (inner → outer, Embree),
peel ([0, 5] µm × 11), directors (20 µm patches; 12 000 on the paper vesicle, the default
density on the big mesh), order (50 µm, every vertex), defects (``find_defects``), and
``nemo run`` end to end (a subprocess; peak from ``wait4``).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import resource
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np


def _rss_mb() -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def _child(fn_name, args, conn):
    warnings.simplefilter("ignore")
    try:
        fn = globals()[fn_name]
        setup = fn(*args, phase="load")
        base = _rss_mb()
        t0, c0 = time.perf_counter(), time.process_time()
        info = fn(*args, phase="run", data=setup) or {}
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
        conn.send({"wall_s": wall, "cpu_s": cpu, "rss_inputs_mb": base, "peak_rss_mb": peak, **info})
    except Exception as exc:  # noqa: BLE001 - report, do not hang the parent
        conn.send({"error": f"{type(exc).__name__}: {exc}"})
    conn.close()


def run_stage(label, fn_name, *args):
    ctx = mp.get_context("fork")
    a, b = ctx.Pipe(duplex=False)
    p = ctx.Process(target=_child, args=(fn_name, args, b))
    p.start()
    res = a.recv()
    p.join()
    res["stage"] = label
    if "error" in res:
        print(f"{label:<34s} FAILED {res['error']}", flush=True)
    else:
        extra = "  ".join(f"{k}={v}" for k, v in res.items() if k not in
                          ("wall_s", "cpu_s", "rss_inputs_mb", "peak_rss_mb", "stage"))
        print(f"{label:<34s} wall {res['wall_s']:7.2f} s  cpu {res['cpu_s']:7.2f} s  peak {res['peak_rss_mb']:7.0f} MB"
              f"  (inputs {res['rss_inputs_mb']:.0f} MB)  {extra}", flush=True)
    return res


# ----------------------------------------------------------------------------- stages
# Each stage: phase="load" returns its inputs (read from `wd`), phase="run" computes and saves.
def st_synth(wd, radius, phase, data=None):
    from nemo.synthetic import vesicle

    if phase == "load":
        return None
    vol, truth = vesicle(radius=radius, seed=0)
    np.save(wd / "volume.npy", np.ascontiguousarray(vol[0, :, 0]))
    (wd / "truth.json").write_text(json.dumps(truth))
    return {"shape": "x".join(map(str, vol.shape[1::2] + vol.shape[4:]))}


def st_mesh(wd, step, phase, data=None):
    from nemo.mesh import save_mesh
    from nemo.surface import default_sigma, reconstruct, split_mesh

    if phase == "load":
        return np.load(wd / "volume.npy")
    whole = reconstruct(data, (1.0, 1.0, 1.0), sigma=default_sigma((1.0, 1.0, 1.0), step), step=step, keep="all")
    inner, outer = split_mesh(whole, by="centre", keep="largest")
    save_mesh(inner, wd / "inner.ply")
    save_mesh(outer, wd / "outer.ply")
    return {"vertices_inner": len(inner.vertices)}


def st_curvature(wd, phase, data=None):
    from nemo.mesh import load_mesh
    from nemo.morphology import curvature

    if phase == "load":
        return load_mesh(wd / "inner.ply")
    df = curvature(data, 20.0, n_samples=20000, rng=0)
    radius = json.loads((wd / "truth.json").read_text())["radius"]
    return {"median_H_times_R": round(float(np.nanmedian(df["H"])) * radius, 3)}


def st_thickness(wd, phase, data=None):
    from nemo.mesh import load_mesh
    from nemo.morphology import thickness

    if phase == "load":
        return load_mesh(wd / "inner.ply"), load_mesh(wd / "outer.ply")
    d = thickness(data[0], data[1])
    return {"median_um": round(float(np.nanmedian(d)), 2)}


def st_peel(wd, phase, data=None):
    from nemo.mesh import load_mesh, vertex_normals
    from nemo.peel import peel

    if phase == "load":
        return np.load(wd / "volume.npy"), load_mesh(wd / "inner.ply")
    vol, mesh = data
    inten = peel(vol, (1.0, 1.0, 1.0), np.asarray(mesh.vertices), vertex_normals(mesh), 0.0, 5.0, 11)
    np.save(wd / "intensity.npy", inten)
    return {}


def _mesh_and_intensity(wd):
    """The inner mesh (normals cached outside the timed part) and its peeled layer."""
    from nemo.mesh import load_mesh

    mesh = load_mesh(wd / "inner.ply")
    mesh.vertex_normals  # noqa: B018 -- computed now, not inside the timed stage
    return mesh, np.load(wd / "intensity.npy")


def st_directors(wd, n_patches, phase, data=None):
    from nemo.directors import directors
    from nemo.synthetic import truth_directors
    from nemo.validation import director_errors

    if phase == "load":
        return _mesh_and_intensity(wd)
    mesh, inten = data
    df = directors(mesh, inten, patch_radius=20.0, n_patches=n_patches, rng=0)
    df.to_parquet(wd / "directors.parquet")
    truth = json.loads((wd / "truth.json").read_text())
    p = df[["x", "y", "z"]].to_numpy()
    err = director_errors(df[["nx", "ny", "nz"]].to_numpy(), truth_directors(truth, p))
    return {"n": len(df), "err_median_deg": round(float(np.median(err)), 2)}


def st_order(wd, phase, data=None):
    import pandas as pd

    from nemo.mesh import load_mesh
    from nemo.order import order

    if phase == "load":
        return load_mesh(wd / "inner.ply"), pd.read_parquet(wd / "directors.parquet")
    df = order(data[0], data[1], 50.0)
    df.to_parquet(wd / "order.parquet")
    return {"S_median": round(float(df["S"].median()), 3)}


def st_defects(wd, phase, data=None):
    import pandas as pd

    from nemo.defects import find_defects
    from nemo.mesh import load_mesh

    if phase == "load":
        return (load_mesh(wd / "inner.ply"), pd.read_parquet(wd / "order.parquet"),
                pd.read_parquet(wd / "directors.parquet"))
    df = find_defects(data[0], data[1], data[2], avg_radius=50.0)
    return {"n_defects": len(df), "charges": "/".join(f"{q:+.2f}" for q in df["charge"])}


# ----------------------------------------------------------------------------- the paper's loop
def director_loop(mesh, intensity, centres, patch_radius, pixel, sigma, half):
    """The director step as the paper describes it: one patch at a time, scipy ``griddata``
    onto a micro-image, OrientationPy's structure tensor, angle at the centre pixel.
    (A deliberate Python loop over patches: this is the baseline NEMO's batched code replaces.)"""
    import orientationpy
    from scipy.interpolate import griddata
    from scipy.spatial import cKDTree

    from nemo.geometry import tangent_frames

    v = np.asarray(mesh.vertices)
    tree = cKDTree(v)
    t1, t2 = tangent_frames(mesh, "axis", vertices=centres)
    g = (np.arange(2 * half + 1) - half) * pixel
    gu, gw = np.meshgrid(g, g)  # rows = t2, columns = t1
    out = np.empty((len(centres), 3))
    for k, c in enumerate(centres):
        idx = tree.query_ball_point(v[c], patch_radius + 3 * pixel)
        d = v[idx] - v[c]
        u, w = d @ t1[k], d @ t2[k]
        img = griddata((u, w), intensity[idx], (gu, gw), method="linear")
        img = np.where(np.isfinite(img), img, np.nanmean(intensity[idx]))
        grad = orientationpy.computeGradient(img, mode="gaussian")
        st = orientationpy.computeStructureTensor(grad, sigma=sigma)
        theta = -np.deg2rad(orientationpy.computeOrientation(st)["theta"][half, half])
        out[k] = np.cos(theta) * t1[k] + np.sin(theta) * t2[k]
    return out


def st_loop_vs_vectorised(wd, n_loop, phase, data=None):
    from nemo.directors import _MARGIN_PX, SIGMA_PX, default_pixel, directors
    from nemo.mesh import mean_edge_length
    from nemo.synthetic import truth_directors
    from nemo.validation import director_errors

    if phase == "load":
        return _mesh_and_intensity(wd)
    mesh, inten = data
    r = 20.0
    centres = np.sort(np.random.default_rng(0).choice(len(mesh.vertices), 12000, replace=False))
    pixel = default_pixel(mean_edge_length(mesh), r)  # directors' default
    half = int(np.ceil(r / pixel)) + _MARGIN_PX
    sigma = SIGMA_PX
    t0 = time.perf_counter()
    vec = directors(mesh, inten, patch_radius=r, centres=centres, pixel=pixel, sigma=sigma)
    t_vec = time.perf_counter() - t0
    sub = np.random.default_rng(1).choice(12000, n_loop, replace=False)
    t0 = time.perf_counter()
    loop = director_loop(mesh, inten, centres[sub], r, pixel, sigma, half)
    t_loop = time.perf_counter() - t0
    truth = json.loads((wd / "truth.json").read_text())
    vsub = vec.set_index("vertex").loc[centres[sub], ["nx", "ny", "nz"]].to_numpy()
    p = mesh.vertices[centres[sub]]
    tn = truth_directors(truth, p)
    per_loop, per_vec = t_loop / n_loop, t_vec / 12000
    return {"vectorised_12000_s": round(t_vec, 2), "loop_per_patch_ms": round(1e3 * per_loop, 2),
            "loop_12000_extrapolated_s": round(per_loop * 12000, 1),
            "ratio": round(per_loop / per_vec, 1),
            "agreement_median_deg": round(float(np.median(director_errors(loop, vsub))), 2),
            "err_loop_median_deg": round(float(np.median(director_errors(loop, tn))), 2),
            "err_vec_median_deg": round(float(np.median(director_errors(vsub, tn))), 2),
            "micro_image_px": 2 * half + 1}


def nemo_run(wd, image):
    """``nemo run`` end to end in a subprocess: wall time and its peak RSS (``os.wait4``)."""
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "nemo", "run", str(image), "-o", str(wd / "run")],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    _, status, ru = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    summary = json.loads((wd / "run" / "summary.json").read_text()) if status == 0 else {}
    res = {"stage": "nemo run (CLI, whole frame)", "wall_s": wall, "cpu_s": ru.ru_utime + ru.ru_stime,
           "peak_rss_mb": ru.ru_maxrss / 1024.0, "rss_inputs_mb": float("nan"),
           "n_defects": len(summary.get("defects", []))}
    print(f"{res['stage']:<34s} wall {wall:7.2f} s  cpu {res['cpu_s']:7.2f} s  peak {res['peak_rss_mb']:7.0f} MB"
          f"  timings {summary.get('timings_s')}", flush=True)
    return res


def suite(wd: Path, radius: float, step: int, n_patches, label: str, with_run: bool) -> list[dict]:
    wd.mkdir(parents=True, exist_ok=True)
    print(f"\n== {label}: R = {radius} µm, 1 µm voxels, marching-cubes step {step} ({wd})", flush=True)
    rows = []
    if not (wd / "volume.npy").exists():
        rows.append(run_stage("synth", "st_synth", wd, radius))
    rows.append(run_stage("mesh", "st_mesh", wd, step))
    rows.append(run_stage("curvature (20k samples, 20 µm)", "st_curvature", wd))
    rows.append(run_stage("thickness (inner -> outer)", "st_thickness", wd))
    rows.append(run_stage("peel ([0, 5] µm x 11)", "st_peel", wd))
    rows.append(run_stage("directors (20 µm)", "st_directors", wd, n_patches))
    rows.append(run_stage("order (50 µm, all vertices)", "st_order", wd))
    rows.append(run_stage("defects", "st_defects", wd))
    if with_run:
        from nemo.io import write_hyperstack

        image = wd / "vesicle.tif"
        if not image.exists():
            write_hyperstack(image, np.load(wd / "volume.npy"), (1.0, 1.0, 1.0), axes="ZYX")
        rows.append(nemo_run(wd, image))
    for r in rows:
        r["case"] = label
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--workdir", help="keep data here (default: a temporary folder)")
    ap.add_argument("--skip-big", action="store_true", help="skip the ≥ 1M-vertex mesh")
    ap.add_argument("--big-radius", type=float, default=240.0,
                    help="radius of the big vesicle (µm; 240 gives ≈ 1.1M inner vertices at step 1)")
    ap.add_argument("--n-loop", type=int, default=400, help="patches timed with the per-patch loop")
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    tmp = None
    if args.workdir:
        root = Path(args.workdir)
    else:
        tmp = tempfile.TemporaryDirectory()
        root = Path(tmp.name)
    rows = suite(root / "paper", 200.0, 2, 12000, "paper (R 200, step 2 µm)", with_run=True)
    print("\n== director step: per-patch loop (griddata + OrientationPy) vs vectorised", flush=True)
    lv = run_stage("directors loop vs vectorised", "st_loop_vs_vectorised", root / "paper", args.n_loop)
    lv["case"] = "paper (R 200, step 2 µm)"
    if not args.skip_big:
        rows += suite(root / "big", args.big_radius, 1, None, f"big (R {args.big_radius:g}, step 1 µm)",
                      with_run=False)
    lines = ["| case | stage | wall (s) | CPU (s) | peak RSS (MB) | RSS of inputs (MB) | notes |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        notes = ", ".join(f"{k} {v}" for k, v in r.items() if k not in
                          ("wall_s", "cpu_s", "rss_inputs_mb", "peak_rss_mb", "stage", "case", "error"))
        if "error" in r:
            notes = r["error"]
        lines.append(f"| {r['case']} | {r['stage']} | {r.get('wall_s', float('nan')):.2f} | "
                     f"{r.get('cpu_s', float('nan')):.2f} | {r.get('peak_rss_mb', float('nan')):.0f} | "
                     f"{r.get('rss_inputs_mb', float('nan')):.0f} | {notes} |")
    table = "\n".join(lines)
    print("\n" + table)
    if "error" not in lv:
        print(f"\ndirector step: vectorised 12 000 patches {lv['vectorised_12000_s']} s; per-patch loop "
              f"{lv['loop_per_patch_ms']} ms/patch ({args.n_loop} timed) -> {lv['loop_12000_extrapolated_s']} s "
              f"for 12 000; ratio {lv['ratio']}x; loop vs vectorised directors agree to "
              f"{lv['agreement_median_deg']}° (median); error vs analytic field: loop "
              f"{lv['err_loop_median_deg']}°, vectorised {lv['err_vec_median_deg']}° (median)")
    (root / "stages.md").write_text(table + "\n")
    (root / "stages.json").write_text(json.dumps({"stages": rows, "loop_vs_vectorised": lv}, indent=1, default=str))
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
