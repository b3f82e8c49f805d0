"""Aggregation of the validation protocol: scores and Snakemake's per-job benchmark files into
summary tables (Parquet), a markdown report and plots."""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from nemo import atomic
from nemo.errors import NemoError


def read_snakemake_benchmark(path: str | os.PathLike) -> dict:
    """Wall time ``s`` and peak ``max_rss`` (MB) of a Snakemake ``benchmark:`` file (mean over repeats)."""
    df = pd.read_csv(path, sep="\t")
    if "s" not in df:
        raise NemoError(f"{path} is not a Snakemake benchmark file (tab-separated, with a column 's' of wall "
                        f"seconds; it has {', '.join(map(str, df.columns)) or 'no columns'}): give the "
                        "files of the rules' `benchmark:` directives")
    out = {"s": float(df["s"].mean())}
    for col in ("max_rss", "cpu_time", "mean_load"):
        if col in df:
            out[col] = float(pd.to_numeric(df[col], errors="coerce").mean())
    return out


#: Score columns summarised per sweep value (mean over rotations).
SWEEP_COLUMNS = [
    "snr", "detection_rate", "false_positives", "loc_err_mean", "loc_err_median", "loc_err_max",
    "charge_err_mean", "charge_err_max", "charge_correct", "all_found", "angle_err_median", "angle_err_p90",
    "angle_err_ordered_median", "S_ordered_median", "H_relerr_median", "K_relerr_median", "n_vertices", "time_total_s",
    "peak_rss_mb",
]


def _json_object(path: str | os.PathLike, what: str) -> dict:
    """The JSON object in ``path``, or a NemoError naming the file and what it should be."""
    try:
        record = json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise NemoError(f"{path} not found: give {what}") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise NemoError(f"cannot read {path} as JSON ({err}): give {what}") from None
    if not isinstance(record, dict):
        raise NemoError(f"{path} holds a JSON {type(record).__name__}, not an object: give {what}")
    return record


def _case_record(path: str | os.PathLike) -> dict:
    """A case's score record; a score written without ``--case`` (by hand) is its own case,
    named after its path, in the sweep ``"cases"``."""
    record = _json_object(path, "a score of `nemo validate score` (a JSON object)")
    if isinstance(record.get("rows"), list):
        raise NemoError(f"{path} is a shape score (it has 'rows'): give it to --shapes; --scores takes the "
                        "outputs of `nemo validate score`")
    defaults = {"case": str(Path(path).with_suffix("")), "sweep": "cases", "parameter": "", "value_label": "",
                "synth": {}, "run": {}}
    return {**defaults, **record}


def _shape_rows(path: str | os.PathLike) -> list:
    """The rows of a shape score (``{"rows": [...]}`` from `nemo validate score-shape`)."""
    record = _json_object(path, "a shape score of `nemo validate score-shape`")
    if not isinstance(record.get("rows"), list):
        raise NemoError(f"{path} has no list 'rows': give the output of `nemo validate score-shape` "
                        "(defect scores go to --scores)")
    return record["rows"]


def aggregate(
    scores: Sequence[str | os.PathLike],
    shape_scores: Sequence[str | os.PathLike],
    stage_files: Sequence[str | os.PathLike],
    outdir: str | os.PathLike,
) -> dict[str, pd.DataFrame]:
    """Collect per-case scores into ``outdir``: Parquet tables, ``validation.md`` and plots.

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
        s = _case_record(f)
        timings = s.pop("timings_s", {}) or {}
        for stage, sec in timings.items():
            stage_rows.append({"case": s["case"], "sweep": s["sweep"], "stage": stage, "s": sec,
                               "max_rss": np.nan, "source": "workflow"})
        rows.append(s)
    cases = pd.DataFrame(rows)
    case_sweep = dict(zip(cases["case"], cases["sweep"])) if len(cases) else {}
    shapes = pd.DataFrame([r for f in shape_scores for r in _shape_rows(f)])
    for f in stage_files:
        p = Path(f)
        b = read_snakemake_benchmark(p)
        group = p.parent.parent.name
        if group == "benchmarks":  # results/{dataset}/benchmarks/{rule}/{job}.tsv: the workflow's rules
            group = "workflow-" + p.parent.parent.parent.name
        elif p.stem in case_sweep:  # a validation case's job: its sweep
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
        write_table(df, out / f"{name}.parquet", kind=f"validation-{name}")
    atomic.write_text(out / "validation.md", markdown(cases, sweeps, shapes, stages))
    plot(cases, stages, out / "plots", shapes)
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



def stage_record(stage_files: Sequence[str | os.PathLike], defects_path: str | os.PathLike) -> dict:
    """Time per stage (Snakemake benchmark files of the frame's rules) and the surface's topology
    (from the defects table's provenance), for a case's ``score.json``."""
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
    """The validation summary as markdown tables (sweeps, shapes, stage times)."""
    parts = ["# NEMO validation summary", ""]
    if len(sweeps):
        parts += ["## Synthetic vesicles (mean over random rotations)", "",
                  "detection = matched / true defects; FP = false positives per case; loc = "
                  "localisation error (µm, matched defects); |Δq| = charge error; θ = raw director "
                  "angle error vs the analytic field (°, all directors / P90 / ordered region); "
                  "S = median S in the ordered region; H, K = median relative curvature errors; "
                  "time = the frame's per-stage jobs of the workflow, summed (s); RSS = largest job's peak "
                  "memory (MB).", "",
                  _table(sweeps, [("sweep", "sweep", -1), ("value_label", "value", -1), ("n_cases", "n", 0),
                                  ("snr", "SNR", 1),
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
                  _table(shapes, [("shape", "shape", -1), ("dz_dx", "dz/dx", 1), ("blur_z", "σz (µm)", 1),
                                  ("snr", "SNR", 1), ("n_vertices", "vertices", 0),
                                  ("radius_source", "radius", -1), ("radius_edges", "radius (edges)", 1),
                                  ("curvature_radius", "radius (µm)", 1),
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


def _snr_x(v) -> float:
    """Plot position of an SNR: the noise-free case (None/NaN/inf) at 30, drawn as ∞."""
    v = np.nan if v is None else float(v)
    return 30.0 if not np.isfinite(v) else v




def _save(fig, path: Path) -> None:
    """Write a plot atomically (a temporary file beside it, renamed when complete)."""
    with atomic.atomic_path(path, keep_suffix=True) as tmp:
        fig.savefig(tmp, dpi=110)


def _snr_axis(ax, label: str) -> None:
    """A logarithmic SNR axis (noise-free plotted at 30, labelled ∞) with ``label`` on y."""
    ax.set_xscale("log")
    ax.set_xlim(2.5, 40)
    ax.set_xticks([3, 5, 10, 30], ["3", "5", "10", "∞"])
    ax.minorticks_off()
    ax.set_xlabel("SNR")
    ax.set_ylabel(label)
    ax.grid(alpha=0.3)


def _radius_label(shapes: pd.DataFrame) -> pd.Series:
    """``default radius`` for the workflow's own radius, ``N edges`` for a fixed one."""
    fixed = shapes["radius_edges"].map(lambda r: f"{r:g} edges")
    if "radius_source" not in shapes:
        return fixed
    return fixed.where(shapes["radius_source"] != "default", "default radius")


#: Vesicle sweeps drawn against SNR, with their legend.
SNR_SWEEPS = {"snr": "defaults (psf: auto)", "snr_psf": "PSF given (deconvolved)",
              "snr_nopsf": "not deconvolved (psf: none)"}


def _plot_snr(cases: pd.DataFrame, shapes: pd.DataFrame | None, outdir: Path, plt) -> list[Path]:
    """Defects (vesicles of the SNR sweeps) and curvature/thickness (analytic shapes) against SNR."""
    return _plot_snr_vesicles(cases, outdir, plt) + _plot_snr_shapes(shapes, outdir, plt)


def _plot_snr_vesicles(cases: pd.DataFrame, outdir: Path, plt) -> list[Path]:
    """``error_vs_snr.png``: the vesicles of :data:`SNR_SWEEPS`, one colour per sweep."""
    has = len(cases) and "sweep" in cases and "snr" in cases
    sub = cases[cases["sweep"].isin(list(SNR_SWEEPS))].copy() if has else pd.DataFrame()
    if not len(sub):
        return []
    sub["x"] = sub["snr"].map(_snr_x)
    metrics = [("detection_rate", "detection rate", None), ("false_positives", "false positives / case", None),
               ("loc_err_median", "localisation error (µm)", "loc_err_max"),
               ("charge_err_max", "charge error |Δq| (max)", None),
               ("H_relerr_median", "H error, median (sphere)", None)]
    fig, axes = plt.subplots(1, len(metrics), figsize=(3.6 * len(metrics), 3.4))
    for (col, label, col2), ax in zip(metrics, axes):
        for (sweep, what), colour in zip(SNR_SWEEPS.items(), ("C0", "C1", "C2")):
            ss = sub[sub["sweep"] == sweep]
            if col not in ss or not len(ss):
                continue
            g = ss.groupby("x")[col]
            ax.plot(g.mean().index, g.mean().values, "o-", color=colour, label=what if col2 is None else f"{what}: median")
            ax.scatter(ss["x"], ss[col], s=10, alpha=0.4, color=colour)
            if col2 and col2 in ss:
                g2 = ss.groupby("x")[col2]
                ax.plot(g2.max().index, g2.max().values, "s--", color=colour, label=f"{what}: max")
        if col2:
            ax.axhline(3.0, color="grey", lw=0.8, ls=":")  # the bound: every defect within 3 µm
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=6)
        _snr_axis(ax, label)
    fig.suptitle("vesicles R = 80 µm, dz = 2.5 dx (dx = 1 µm), PSF σ 2.5 / 1 / 1 µm", fontsize=9)
    fig.tight_layout()
    _save(fig, outdir / "error_vs_snr.png")
    plt.close(fig)
    return [outdir / "error_vs_snr.png"]


def _plot_snr_shapes(shapes: pd.DataFrame | None, outdir: Path, plt) -> list[Path]:
    """``shapes_vs_snr.png``: the analytic shapes under an anisotropic PSF, solid at the default radius."""
    if shapes is None or not len(shapes) or "snr" not in shapes or "blur_z" not in shapes:
        return []
    sh = shapes[shapes["blur_z"] != shapes["blur_xy"]].copy()
    if not len(sh):
        return []
    sh["x"] = sh["snr"].map(_snr_x)
    sh["family"] = sh["shape"].str.replace(r"_snr\d+$", "", regex=True)
    fig, axes = plt.subplots(1, 3, figsize=(11, 3.2))
    for fam, ss in sh.groupby("family"):
        for r, rr in ss.groupby(_radius_label(ss)):
            rr = rr.sort_values("x")
            if fam.startswith(("ellipsoid_", "torus")):
                style = "o-" if r == "default radius" else "o:"
                axes[0].plot(rr["x"], 100 * rr["H_err_median"], style, label=f"{fam}, {r}")
                axes[1].plot(rr["x"], 100 * rr["K_err_median"], style, label=f"{fam}, {r}")
        if "thickness_err_median" in ss and ss["thickness_err_median"].notna().any():
            t = ss.drop_duplicates("x").sort_values("x")
            axes[2].plot(t["x"], t["thickness_err_median"], "o-", label=fam)
    axes[2].axhline(0.25, color="grey", lw=0.8, ls=":")  # the bound at 1 µm voxels
    for ax, label in zip(axes, ("H error, median (%)", "K error, median (%)", "thickness error, median (µm)")):
        _snr_axis(ax, label)
        if any(np.nan_to_num(np.asarray(ln.get_ydata(), float)).max(initial=0) > 0 for ln in ax.get_lines()):
            ax.set_yscale("log")
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=6)
    fig.suptitle("analytic shapes, PSF σ 2.5 / 1 / 1 µm", fontsize=9)
    fig.tight_layout()
    _save(fig, outdir / "shapes_vs_snr.png")
    plt.close(fig)
    return [outdir / "shapes_vs_snr.png"]


def plot(cases: pd.DataFrame, stages: pd.DataFrame, outdir: str | os.PathLike,
         shapes: pd.DataFrame | None = None) -> list[Path]:
    """Error vs noise, vs SNR, vs anisotropy, vs analysis parameters; analytic shapes vs SNR;
    time per stage (PNG)."""
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
        _save(fig, outdir / fname)
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
    written += _plot_snr(cases, shapes, outdir, plt)
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
        _save(fig, outdir / "time_per_stage.png")
        plt.close(fig)
        written.append(outdir / "time_per_stage.png")
    return written
