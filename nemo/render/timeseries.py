"""Matplotlib figures of a time-lapse, from a dataset's summary tables.

* :func:`tracks_figure` -- one layer's defect tracks in (azimuth, polar) and the distance each
  track travelled;
* :func:`defect_map_figure` -- every frame's defects and the tracks on an equal-area
  (Mollweide) map;
* :func:`frames_figure` -- the per-frame summary (S, defects, Σ charge vs χ, thickness, H,
  area, volume versus t) with the per-frame quality control of :func:`frame_qc`.

Inputs are ``summary/defects.parquet`` and ``summary/frames.parquet`` (see docs/workflow.md).
matplotlib is imported inside the functions.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from nemo.render.charts import spherical_angles
from nemo.render.figures import _figure, _map_axes
from nemo.render.style import (
    LAYER_COLOURS,
    LAYER_MARKERS,
    SURFACE_COLOURS,
    charge_text,
    field_label,
    unit_text,
)
from nemo.summary import QC_CHARGE_TOLERANCE, QC_EMPTY_SNR

# --------------------------------------------------------------------------------------------
# defect tracks and the defect map


def _defect_centres(df: pd.DataFrame, centres: dict | None) -> np.ndarray:
    """Per-row origin of the spherical coordinates: the frame's surface centroid from
    ``centres[(t, c)]``, else the mean position of that frame's defects; with several objects
    (an ``object`` column), each object's centroid ``centres[(t, c, object)]``, else the mean
    position of its defects in the frame. Shape (M, 3)."""
    xyz = df[["x", "y", "z"]].to_numpy(float)
    cs = df["c"].astype(int) if "c" in df.columns else pd.Series(0, index=df.index)
    keys = list(zip(df["t"].astype(int), cs))
    labelled = any(len(k) == 3 for k in (centres or {}))  # several objects: their centroids are known
    if "object" in df.columns and (labelled or (df["object"] != 0).any()):  # not the frame's (between objects)
        keys = list(zip(df["t"].astype(int), cs, df["object"].astype(int)))
        centres = {k: v for k, v in (centres or {}).items() if len(k) == 3}
    frame_mean = pd.DataFrame(xyz, columns=["x", "y", "z"]).assign(_k=keys).groupby("_k").mean()
    centres = centres or {}
    return np.array([centres[k] if k in centres else frame_mean.loc[[k]].to_numpy()[0]
                     for k in keys]).reshape(-1, 3)


def _layer_rows(defects: pd.DataFrame, layer: str | None) -> pd.DataFrame:
    df = defects
    if layer is not None and "layer" in df.columns:
        df = df[df["layer"].astype(str) == str(layer)]
    return df.sort_values(["track_id", "t"]) if len(df) and "track_id" in df.columns else df


def tracks_figure(defects: pd.DataFrame, layer: str | None = None,
                  centres: dict[tuple[int, int], np.ndarray] | None = None):
    """Defect tracks over time for one layer.

    Parameters
    ----------
    defects : DataFrame
        ``summary/defects.parquet``: ``t, c, layer, x, y, z, charge, track_id`` (rows of other
        layers are ignored when ``layer`` is given).
    layer : str, optional
    centres : dict (t, c) -> (3,), optional
        Surface centroid per frame; default the mean defect position of each frame.

    Returns
    -------
    matplotlib.figure.Figure
        Left: tracks in (azimuth, polar) with one colour per track; right: distance from the
        track's first position along the sphere of the mean radius, versus t.
    """
    import matplotlib
    from matplotlib.ticker import MaxNLocator

    df = _layer_rows(defects, layer)
    fig, (ax_m, ax_d) = _figure(2, 6.0, 3.8)
    fig.set_size_inches(13, 4.0)
    _map_axes(ax_m)
    ax_d.set_xlabel(field_label("t"))
    ax_d.set_ylabel("distance from first position [µm]")
    ax_d.xaxis.set_major_locator(MaxNLocator(integer=True))
    if not len(df):
        ax_m.set_title("no defects", fontsize=10)
        return fig
    rel = df[["x", "y", "z"]].to_numpy(float) - _defect_centres(df, centres)
    r = np.linalg.norm(rel, axis=1)
    az, pol = spherical_angles(rel, np.zeros(3))
    cmap = matplotlib.colormaps["tab10"]
    ids = df["track_id"].to_numpy()
    t = df["t"].to_numpy(float)
    for i, tid in enumerate(pd.unique(ids)):
        sel = ids == tid
        colour = cmap(i % 10)
        a, p_ = az[sel], pol[sel]
        for seg in _seam_segments(a):  # do not draw across the ±180° seam
            ax_m.plot(a[seg], p_[seg], "-", color=colour, lw=1.5)
        ax_m.scatter(a, p_, color=colour, s=18, zorder=4)
        q = float(np.nanmedian(df["charge"].to_numpy(float)[sel]))
        ax_m.annotate(f"{tid} ({charge_text(q)})", (a[-1], p_[-1]), xytext=(5, 5),
                      textcoords="offset points", fontsize=8, color=colour, zorder=6,
                      bbox={"boxstyle": "round,pad=0.1", "fc": "white", "alpha": 0.75, "lw": 0})
        u = rel[sel] / np.maximum(r[sel, None], 1e-12)
        ang = np.arccos(np.clip(u @ u[0], -1, 1))
        ax_d.plot(t[sel], ang * r[sel].mean(), "-o", color=colour, ms=3, label=f"{tid} ({charge_text(q)})")
    ax_m.set_title(f"defect tracks{'' if layer is None else f' (layer {layer})'}: "
                   f"{len(pd.unique(ids))} tracks over {len(np.unique(t))} frames", fontsize=10)
    if len(pd.unique(ids)) <= 12:
        ax_d.legend(fontsize=7, title="track (charge)", title_fontsize=7)
    return fig


def _seam_segments(lon_deg: np.ndarray) -> list[np.ndarray]:
    """Index runs of a track that do not jump across the ±180° longitude seam."""
    jumps = np.flatnonzero(np.abs(np.diff(lon_deg)) > 180) + 1
    return np.split(np.arange(len(lon_deg)), jumps)


def defect_lonlat(defects: pd.DataFrame, centres: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Longitude and latitude of defects around their frame's surface centroid, in degrees.

    Longitude is the azimuth φ = atan2(y, x) in (−180, 180]; latitude is 90° − θ (θ the polar
    angle from +z), so +z is the north pole. Origins as in :func:`tracks_figure`.
    """
    if not len(defects):
        return np.zeros(0), np.zeros(0)
    az, pol = spherical_angles(defects[["x", "y", "z"]].to_numpy(float) - _defect_centres(defects, centres),
                               np.zeros(3))
    return az, 90.0 - pol


#: Marker of a defect by the sign of its charge: ``+`` comet-like circle, ``−`` trefoil-like triangle.
_CHARGE_MARKERS = {1: ("o", "m > 0 (e.g. +½)"), -1: ("^", "m < 0 (e.g. −½)"), 0: ("s", "m ≈ 0")}


def _defect_map_points(ax, df: pd.DataFrame, lon: np.ndarray, lat: np.ndarray):
    """Scatter the defects of every frame on a Mollweide axis; returns the last collection."""
    from matplotlib.colors import TwoSlopeNorm

    q = df["charge"].to_numpy(float)
    t = df["t"].to_numpy(float)
    span = max(float(np.ptp(t)), 1.0) if len(t) else 1.0
    alpha = 0.35 + 0.65 * (t - (t.min() if len(t) else 0)) / span  # earlier frames fainter
    sign = np.where(q > 0.1, 1, np.where(q < -0.1, -1, 0))
    norm = TwoSlopeNorm(vcenter=0.0, vmin=-1.0, vmax=1.0)
    sc = None
    for s, (marker, _) in _CHARGE_MARKERS.items():
        sel = sign == s
        if not sel.any():
            continue
        last = t[sel] == t.max()
        sc = ax.scatter(np.radians(lon[sel]), np.radians(lat[sel]), c=q[sel], cmap="RdBu_r", norm=norm,
                        marker=marker, s=np.where(last, 70, 40), alpha=alpha[sel], edgecolors="k",
                        linewidths=np.where(last, 1.2, 0.5), zorder=5)
        sc.set_gid("defects")
    return sc, norm


def defect_map_figure(defects: pd.DataFrame, layer: str | None = None,
                      centres: dict[tuple[int, int], np.ndarray] | None = None):
    """Every frame's defects and the tracks of one layer on an equal-area world map.

    Parameters
    ----------
    defects : DataFrame
        ``summary/defects.parquet``: ``t, x, y, z, charge`` (+ ``c``, ``layer``, ``track_id``).
    layer : str, optional
        Only this layer's rows.
    centres : dict (t, c) -> (3,), optional
        Surface centroid per frame (default: each frame's mean defect position).

    Returns
    -------
    matplotlib.figure.Figure
        One Mollweide (equal-area) panel: longitude = azimuth φ about the centroid, latitude =
        90° − θ (north = +z); equal areas on the surface stay equal, so the poles are not
        stretched as in the (φ, θ) maps. Defects are coloured by charge m on a diverging map
        centred on 0 (red positive, blue negative) and shaped by sign (circle +, triangle −);
        earlier frames are fainter, the last frame has bold edges; grey lines join the
        positions of each track (``track_id``), never across the ±180° seam. Scatter
        collections have gid ``"defects"``; offsets are radians (lon, lat).
    """
    import matplotlib
    from matplotlib.cm import ScalarMappable
    from matplotlib.figure import Figure as MplFigure
    from matplotlib.lines import Line2D

    df = _layer_rows(defects, layer)
    fig = MplFigure(figsize=(11, 6.4), layout="constrained")
    ax = fig.add_subplot(projection="mollweide")
    ax.grid(True, color="0.75", lw=0.5)
    ax.tick_params(labelsize=8, colors="0.3")
    ax.set_xlabel("longitude φ (azimuth from +x towards +y) [°]")
    ax.set_ylabel("latitude 90° − θ (north = +z) [°]")
    name = "" if layer is None else f"layer {layer}: "
    lon, lat = defect_lonlat(df, centres)
    if "track_id" in df.columns:
        for tid in pd.unique(df["track_id"]):
            sel = (df["track_id"] == tid).to_numpy()
            for seg in _seam_segments(lon[sel]):
                ax.plot(np.radians(lon[sel][seg]), np.radians(lat[sel][seg]), "-", color="0.35",
                        lw=1.3, zorder=3)
    sc, norm = _defect_map_points(ax, df, lon, lat)
    cb = fig.colorbar(sc if sc is not None else ScalarMappable(norm, "RdBu_r"), ax=ax,
                      orientation="horizontal", shrink=0.45, pad=0.02, aspect=30)
    cb.set_label(field_label("charge") + " (0 = white)")
    cb.set_ticks([-1, -0.5, 0, 0.5, 1], labels=["−1", "−½", "0", "+½", "+1"])
    cmap = matplotlib.colormaps["RdBu_r"]
    handles = [Line2D([], [], ls="", marker=m, mfc=cmap(norm(0.5 * s)), mec="k", ms=8, label=lab)
               for s, (m, lab) in _CHARGE_MARKERS.items()
               if s != 0 or (len(df) and (np.abs(df["charge"].to_numpy(float)) <= 0.1).any())]
    handles.append(Line2D([], [], color="0.35", lw=1.3, label="track (same track_id)"))
    t = df["t"].to_numpy(int) if len(df) else np.zeros(0, int)
    if len(t):
        handles.append(Line2D([], [], ls="", marker="o", mfc="0.6", mec="k", mew=1.2, ms=8,
                              label=f"bold edge: last frame t = {t.max()}; fainter = earlier"))
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(0.0, -0.08), ncols=2, fontsize=8,
              frameon=False)
    n_tr = df["track_id"].nunique() if "track_id" in df.columns else 0
    ax.set_title(f"{name}{len(df)} defects in {len(np.unique(t))} frames"
                 f"{f' (t = {t.min()}–{t.max()})' if len(t) else ''}, {n_tr} tracks\n"
                 + ("equal-area map, each object's defects around its own centroid"
                    if "object" in df.columns and df["object"].nunique() > 1
                    else "equal-area map around the surface centroid"), fontsize=11, pad=24)
    return fig


# --------------------------------------------------------------------------------------------
# per-frame summary with quality control

#: Panels of :func:`frames_figure`: key, title, columns (column, line label), per ``layer`` or
#: per ``surface``, y label (``{u}`` the length unit) and the y-limits policy.
FRAME_PANELS: tuple[tuple, ...] = (
    ("S", "nematic order S", (("S_mean", "mean"), ("S_median", "median")), "layer", "S", "unit"),
    ("n_defects", "number of defects", (("n_defects", None),), "layer", "defects", "count"),
    ("charge", "Σ charge vs Euler characteristic χ", (("charge_sum", None),), "layer",
     "Σ charge m", "charge"),
    ("thickness", "wall thickness", (("thickness_mean", "mean"), ("thickness_median", "median")),
     "surface", "thickness [{u}]", "relative"),
    ("H", "mean curvature H", (("H_mean", "mesh mean"), ("H_fit_mean", "fit mean")), "surface",
     "H [1/{u}]", "relative"),
    ("area", "surface area", (("area", None),), "surface", "area [{u}²]", "relative"),
    ("volume", "enclosed volume", (("volume", None),), "surface", "volume [{u}³]", "relative"),
)
#: Smallest half-span of a ``relative`` panel, as a fraction of the mean.
RELATIVE_SPAN = 0.05
_STYLES = ("-", "--")


def frame_qc(frames: pd.DataFrame) -> pd.DataFrame:
    """``qc_pass`` (bool) and ``qc_flags`` (str, '; '-joined reasons) of each row.

    The table's own columns when present (:func:`nemo.summary.quality_flags`); otherwise a row
    with a layer fails when |charge_sum − euler_characteristic| > :data:`QC_CHARGE_TOLERANCE`
    or it has no defects.
    """
    out = pd.DataFrame(index=frames.index)
    if "qc_pass" in frames.columns:
        out["qc_pass"] = frames["qc_pass"].fillna(True).astype(bool)
        flags = frames["qc_flags"] if "qc_flags" in frames.columns else pd.Series("", index=frames.index)
        flags = flags.fillna("").astype(str)
        out["qc_flags"] = flags.where(out["qc_pass"] | (flags != ""), "failed quality control")
        return out
    reasons = []
    for _, row in frames.iterrows():
        r = []
        q, chi = row.get("charge_sum", np.nan), row.get("euler_characteristic", np.nan)
        if pd.notna(q) and pd.notna(chi) and abs(float(q) - float(chi)) > QC_CHARGE_TOLERANCE:
            r.append(f"Σ charge {round(float(q), 2) + 0.0:.2f} ≠ χ {float(chi):.0f}")
        has_layer = pd.notna(row.get("layer")) and str(row.get("layer", "")) != ""
        if has_layer and "n_defects" in row and pd.notna(row["n_defects"]) and int(row["n_defects"]) == 0:
            r.append("no defects")
        reasons.append("; ".join(r))
    out["qc_flags"] = reasons
    out["qc_pass"] = out["qc_flags"] == ""
    return out


def _frame_groups(frames: pd.DataFrame) -> tuple[dict, dict]:
    """(layer groups, surface groups): label -> rows sorted by t (surface rows deduplicated)."""
    multi_c = "c" in frames.columns and frames["c"].nunique() > 1

    def label(c, name, what):
        return f"{'c' + str(c) + ' ' if multi_c else ''}{what}{name}"

    cs = frames["c"] if "c" in frames.columns else pd.Series(0, index=frames.index)
    lay = frames["layer"].astype(str) if "layer" in frames.columns else pd.Series("", index=frames.index)
    # several objects (mesh.keep: all): a line per object, followed over time by its object_id (labels
    # are area ranks, which swap when two objects' areas cross)
    obj = frames["object"] if "object" in frames.columns else pd.Series(0, index=frames.index)
    if "object_id" in frames.columns and frames["object_id"].notna().any():
        obj = frames["object_id"].astype("Int64").fillna(-1)
    several = obj.nunique() > 1

    def tag(o) -> str:
        return f" object {o}" if several else ""

    layers = {label(c, L, "layer " if L else "all") + tag(o): g.sort_values("t")
              for (c, L, o), g in frames.groupby([cs, lay, obj], sort=True)}
    if "surface" not in frames.columns:
        return layers, layers
    surf = frames["surface"].astype(str)
    surfaces = {label(c, f"{S} surface", "") + tag(o): g.sort_values("t").drop_duplicates("t")
                for (c, S, o), g in frames.groupby([cs, surf, obj], sort=True)}
    return layers, surfaces


def _scale(values: np.ndarray) -> tuple[float, str]:
    """A factor 10^-3k that brings values ≥ 10⁴ to plain numbers, and its label prefix."""
    v = np.abs(values[np.isfinite(values)])
    if not v.size or v.max() < 1e4:
        return 1.0, ""
    k = int(np.floor(np.log10(v.max()) / 3) * 3)
    return 10.0 ** -k, f"10$^{{{k}}}$ "


def _panel_limits(policy: str, values: np.ndarray, chi: np.ndarray) -> tuple[float, float]:
    """y limits: ``unit`` [0, 1]; ``count`` [0, max + 1]; ``charge`` the charges and χ with at
    least ±1 about χ; ``relative`` the data range, at least ±:data:`RELATIVE_SPAN` × mean."""
    v = values[np.isfinite(values)]
    if policy == "unit":
        return 0.0, 1.0
    if policy == "count":
        return 0.0, float(v.max()) + 1 if v.size else 1.0
    if policy == "charge":
        ref = np.concatenate([v, chi[np.isfinite(chi)]])
        c = chi[np.isfinite(chi)]
        lo = min(ref.min(), c.min() - 1) if c.size else (ref.min() - 1 if ref.size else -1)
        hi = max(ref.max(), c.max() + 1) if c.size else (ref.max() + 1 if ref.size else 1)
        return float(lo) - 0.25, float(hi) + 0.25
    if not v.size:
        return 0.0, 1.0
    lo, hi = float(v.min()), float(v.max())
    half = max(RELATIVE_SPAN * abs(float(v.mean())), 0.6 * (hi - lo)) or 1.0
    mid = 0.5 * (lo + hi)
    return mid - half, mid + half


def _plot_panel(ax, spec: tuple, groups: dict, styles: dict, unit: str, qc: pd.DataFrame) -> bool:
    """Draw one :data:`FRAME_PANELS` entry; False when the table has none of its columns."""
    key, title, cols, _, ylabel, policy = spec
    cols = [(c, lab) for c, lab in cols if any(c in g.columns for g in groups.values())]
    ax.set_title(title, fontsize=10)
    if not cols:
        ax.text(0.5, 0.5, "not in frames.parquet", ha="center", va="center", color="0.5",
                transform=ax.transAxes)
        ax.set_yticks([])
        return False
    groups = {name: _without_empty_frames(g) for name, g in groups.items()}
    allv = np.concatenate([g[c].to_numpy(float) for g in groups.values() for c, _ in cols if c in g])
    factor, prefix = _scale(allv)
    chi = np.concatenate([np.zeros(0)] + [g["euler_characteristic"].to_numpy(float) for g in groups.values()
                                          if "euler_characteristic" in g and key == "charge"])
    for i, (name, g) in enumerate(groups.items()):
        # layers side by side (±0.04 in t) so that equal values stay visible
        t = g["t"].to_numpy(float) + 0.04 * (i - (len(groups) - 1) / 2) * (spec[3] == "layer")
        for (c, _), ls in zip(cols, _STYLES):
            if c in g:
                ax.plot(t, g[c].to_numpy(float) * factor, ls, marker=styles[name][1], ms=4.5,
                        color=styles[name][0])
        first = g[cols[0][0]].to_numpy(float) if cols[0][0] in g else np.full(len(g), np.nan)
        bad = ~qc.loc[g.index, "qc_pass"].to_numpy(bool) & np.isfinite(first)
        if spec[3] == "layer" and bad.any():  # a surface's row carries its layers' flags, not its own
            ax.plot(t[bad], first[bad] * factor, "x", color="red", ms=8, mew=1.8, zorder=6)
    if key == "charge" and chi.size:
        _chi_reference(ax, groups)
    lo, hi = _panel_limits(policy, allv * factor, chi)
    ax.set_ylim(lo, hi)
    ax.set_ylabel(ylabel.replace("[", f"[{prefix}" if prefix else "[").replace("{u}", unit))
    if policy == "count":
        from matplotlib.ticker import MaxNLocator

        ax.yaxis.set_major_locator(MaxNLocator(integer=True))
    if len(cols) > 1:
        from matplotlib.lines import Line2D

        ax.legend(handles=[Line2D([], [], color="0.3", ls=ls, label=lab) for (_, lab), ls in zip(cols, _STYLES)],
                  fontsize=7, loc="lower right", framealpha=0.7)
    return True


def _without_empty_frames(rows: pd.DataFrame) -> pd.DataFrame:
    """``rows`` with the values of frames whose segmented channel looks empty (``snr`` below
    :data:`nemo.summary.QC_EMPTY_SNR`) set to NaN: a noise speck's area or H is not the object's,
    and would set the panel's scale (the frame keeps its row, its flag and its red shading)."""
    if "snr" not in rows.columns:
        return rows
    empty = (rows["snr"] < QC_EMPTY_SNR).to_numpy(bool)
    if not empty.any():
        return rows
    rows = rows.copy()
    keys = ("t", "c", "object", "object_id", "snr")
    for c in rows.columns:  # a loop over the table's columns: floats get NaN, nullable integers NA
        if c in keys or pd.api.types.is_bool_dtype(rows[c]):
            continue
        if pd.api.types.is_float_dtype(rows[c]):
            rows.loc[empty, c] = np.nan
        elif isinstance(rows[c].dtype, pd.Int64Dtype):
            rows.loc[empty, c] = pd.NA
    return rows


def _chi_reference(ax, groups: dict) -> None:
    """χ per frame as a black dashed line with the ±tolerance band of quality control."""
    rows = pd.concat([g[["t", "euler_characteristic"]] for g in groups.values()
                      if "euler_characteristic" in g]).drop_duplicates().sort_values("t")
    t, chi = rows["t"].to_numpy(float), rows["euler_characteristic"].to_numpy(float)
    ax.fill_between(t, chi - QC_CHARGE_TOLERANCE, chi + QC_CHARGE_TOLERANCE, color="0.88", zorder=0,
                    step="mid" if len(t) > 1 else None)
    ax.plot(t, chi, "k--", marker="_", ms=14, lw=1.2, zorder=4)


def _qc_strip(ax, groups: dict, styles: dict, qc: pd.DataFrame) -> list[str]:
    """One row of pass (green ●) / fail (red ✕) markers per layer; returns the reasons."""
    reasons = []
    names = list(groups)
    for i, name in enumerate(names):
        g = groups[name]
        ok = qc.loc[g.index, "qc_pass"].to_numpy(bool)
        t = g["t"].to_numpy(float)
        ax.plot(t[ok], np.full(ok.sum(), i), "o", color="tab:green", ms=9)
        ax.plot(t[~ok], np.full((~ok).sum(), i), "X", color="red", ms=11)
        for tt, why in zip(t[~ok], qc.loc[g.index, "qc_flags"].to_numpy(str)[~ok]):
            reasons.append((tt, i, f"t = {tt:.0f}, {name}: {why}"))
    ax.set_yticks(range(len(names)), names, fontsize=9)
    for lab, name in zip(ax.get_yticklabels(), names):
        lab.set_color(styles[name][0])
    ax.set_ylim(len(names) - 0.5, -0.5)
    ax.set_title("quality control per frame (green ● pass, red ✕ flagged; flagged frames shaded "
                 "red in every panel)", fontsize=10)
    return [text for *_, text in sorted(reasons)]


def _frames_legend(ax, styles: dict, has_chi: bool) -> None:
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    ax.axis("off")
    h = [Line2D([], [], color=c, marker=m, ms=5, label=n) for n, (c, m) in styles.items()]
    if has_chi:
        h.append(Line2D([], [], color="k", ls="--", marker="_", ms=12, label="χ (Euler characteristic)"))
        h.append(Patch(color="0.88", label=f"χ ± {QC_CHARGE_TOLERANCE} (QC tolerance)"))
    h.append(Line2D([], [], ls="", marker="x", color="red", ms=10, mew=2, label="flagged frame (layer)"))
    h.append(Patch(color="red", alpha=0.15, label="t with a QC flag"))
    ax.legend(handles=h, loc="center", fontsize=9, frameon=False)


def frames_figure(frames: pd.DataFrame, unit: str = "um", title: str = ""):
    """Per-frame summary of a time-lapse for a biophysicist, with quality control.

    Parameters
    ----------
    frames : DataFrame
        ``summary/frames.parquet`` (:data:`nemo.summary.FRAME_COLUMNS`; missing columns give
        an empty panel). ``mean_S`` is read as ``S_mean``.
    unit : str
        Length unit of the table (its provenance ``unit``; ``"um"`` shown as µm).
    title : str
        Figure title (e.g. the dataset).

    Returns
    -------
    matplotlib.figure.Figure or None
        None without a ``t`` column. Panels (:data:`FRAME_PANELS`) versus integer t: S
        (mean solid, median dashed; 0–1), number of defects (from 0), Σ charge with χ as a
        dashed reference and the ±0.25 QC band, per layer (one colour per channel and layer);
        thickness, mean curvature H, area and volume per surface (deduplicated over layers).
        Y limits never use an offset or scientific notation: values ≥ 10⁴ are scaled by 10³ᵏ
        stated in the label, and each morphology panel spans at least ±5 % of its mean
        (:data:`RELATIVE_SPAN`), so numerical noise of 0.01 % looks flat while a real change
        of a few percent shows. A bottom strip marks each layer's frames as passing or
        flagged (:func:`frame_qc`) and lists the reasons; flagged t are shaded red everywhere
        and the layers' values crossed in red. A frame whose segmented channel looks empty keeps its
        flag but none of its values is drawn (a noise speck's area is not the object's).
    """
    from matplotlib.figure import Figure as MplFigure
    from matplotlib.ticker import MaxNLocator

    if "t" not in frames.columns or not len(frames):
        return None
    if "S_mean" not in frames.columns and "mean_S" in frames.columns:
        frames = frames.rename(columns={"mean_S": "S_mean"})
    frames = frames.reset_index(drop=True)
    qc = frame_qc(frames)
    layers, surfaces = _frame_groups(frames)
    styles = {n: (LAYER_COLOURS[i % len(LAYER_COLOURS)], LAYER_MARKERS[i % len(LAYER_MARKERS)])
              for i, n in enumerate(layers)}
    styles.update({n: (SURFACE_COLOURS[i % len(SURFACE_COLOURS)], "o")
                   for i, n in enumerate(s for s in surfaces if s not in layers)})
    bad_t = sorted(set(frames.loc[~qc["qc_pass"], "t"].astype(int)))
    n_lines = max(1, len(bad_t) and int((~qc["qc_pass"]).sum()))
    fig = MplFigure(figsize=(16, 8.6 + 0.3 * len(layers) + 0.2 * min(n_lines, 12)), layout="constrained")
    gs = fig.add_gridspec(4, 4, height_ratios=[3, 3, 0.5 + 0.35 * len(layers), 0.3 + 0.22 * min(n_lines, 13)])
    axes = [fig.add_subplot(gs[i // 4, i % 4]) for i in (0, 1, 2, 4, 5, 6, 7)]
    t_all = np.unique(frames["t"].to_numpy(int))
    for ax, spec in zip(axes, FRAME_PANELS):
        _plot_panel(ax, spec, layers if spec[3] == "layer" else surfaces, styles, unit_text(unit), qc)
    ax_qc = fig.add_subplot(gs[2, :], sharex=axes[0])
    reasons = _qc_strip(ax_qc, layers, styles, qc)
    for ax in [*axes, ax_qc]:
        for t in bad_t:
            ax.axvspan(t - 0.5, t + 0.5, color="red", alpha=0.12, lw=0, zorder=0)
        ax.xaxis.set_major_locator(MaxNLocator(integer=True, min_n_ticks=1))  # one time point: one tick
        ax.set_xlim(t_all.min() - 0.5, t_all.max() + 0.5)
        ax.ticklabel_format(axis="y", style="plain", useOffset=False) if ax is not ax_qc else None
        ax.grid(True, axis="y", color="0.9", lw=0.6)
        ax.set_xlabel(field_label("t"))
    _frames_legend(fig.add_subplot(gs[0, 3]), styles, "euler_characteristic" in frames)
    _reasons_text(fig.add_subplot(gs[3, :]), reasons)
    fig.suptitle(title or "per-frame summary", fontsize=13)
    return fig


#: Characters of a QC reason line in frames.png (the full text is in frames.parquet's qc_flags).
REASON_WIDTH = 190


def _reasons_text(ax, reasons: list[str], max_lines: int = 12) -> None:
    ax.axis("off")
    if not reasons:
        ax.text(0, 1, "All frames pass quality control.", va="top", fontsize=10, color="tab:green",
                transform=ax.transAxes)
        return
    import textwrap

    lines = reasons[:max_lines] + ([f"… and {len(reasons) - max_lines} more (frames.parquet qc_flags)"]
                                   if len(reasons) > max_lines else [])
    lines = [textwrap.shorten(line, REASON_WIDTH, placeholder=" … (frames.parquet qc_flags)") for line in lines]
    ax.text(0, 1, "Flagged frames:\n" + "\n".join(lines), va="top", fontsize=9, color="darkred",
            transform=ax.transAxes, linespacing=1.3)
