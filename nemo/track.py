"""Defect tracking over time: link the defects of consecutive frames into tracks.

Linking is done by `laptrack <https://github.com/yfukai/laptrack>`_ (linear-assignment
tracking, Jaqaman et al. 2008) with a maximum displacement per frame and gap closing over
missed detections. Only defects of the **same rounded charge** are linked: tracking runs
independently for every group of (channel, layer, ``charge_rounded``), so a +½ and a −½ that
pass close to each other can never swap identities.

Frames are the ranks of the analysed time points (``frames``), not the raw ``t`` values, so
analysing ``t = 0, 2, 4`` links 0 → 2 → 4 as consecutive frames; a frame in which a defect
was missed is bridged when ``gap_frames >= 1``. Distances are Euclidean in physical units
(µm); on a surface this is the chord, a lower bound of the geodesic step, which is what a
maximum-displacement cut-off needs.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pandas as pd

from nemo.errors import NemoError

#: Columns a defect table must have to be tracked.
REQUIRED = ("t", "x", "y", "z", "charge_rounded")
#: Columns that split tracking into independent groups when present.
GROUP_COLUMNS = ("c", "layer")


def _check(defects: pd.DataFrame, max_distance: float, gap_frames: int) -> None:
    missing = [c for c in REQUIRED if c not in defects.columns]
    if missing:
        raise NemoError(
            f"defect table lacks column(s) {', '.join(missing)} needed for tracking "
            f"(it has: {', '.join(map(str, defects.columns))}); it must hold the defects of all "
            "frames with a 't' column, as written by the workflow's aggregation"
        )
    if not (np.isfinite(max_distance) and max_distance > 0):
        raise NemoError(f"max_distance must be a positive length in µm, got {max_distance!r}")
    if int(gap_frames) != gap_frames or gap_frames < 0:
        raise NemoError(f"gap_frames must be a whole number >= 0, got {gap_frames!r}")
    xyz = defects[["x", "y", "z"]].to_numpy(dtype=float)
    if not np.isfinite(xyz).all():
        raise NemoError("defect table has non-finite x, y, z positions; cannot track them")
    _check_time_points(defects["t"], "defect table has t values")


def _check_time_points(t, what: str) -> None:
    """Refuse time points that are not whole numbers (0.5, NaN, text, True): ``t`` is an index."""
    values = pd.Series(t)
    numeric = pd.api.types.is_numeric_dtype(values) and not pd.api.types.is_bool_dtype(values)
    t = pd.to_numeric(values, errors="coerce").to_numpy(dtype=float) if numeric else np.full(len(values), np.nan)
    whole = np.isfinite(t) & (t == np.round(t))
    if not whole.all():
        bad = values[~whole].unique()[:5].tolist()
        raise NemoError(f"{what} that are not whole time-point indices ({bad}): t is the 0-based index of the "
                        "time point in the hyperstack, not a time in minutes")


def _cutoff(distance: float) -> float:
    """laptrack's squared cut-off for links of at most ``distance`` (its cut-off is exclusive)."""
    return float(distance) ** 2 * (1.0 + 1e-9)


def _split_long_steps(track: np.ndarray, frame: np.ndarray, xyz: np.ndarray, cutoff: float) -> np.ndarray:
    """Split the tracks (ids ``track``, one per detection) at every step between consecutive frames
    longer than ``sqrt(cutoff)``: laptrack's gap closing also joins segments of adjacent frames,
    up to the gap's cut-off (it has no smallest gap). Returns new ids (0, 1, ...)."""
    order = np.lexsort((frame, track))
    tid, f, p = track[order], frame[order], xyz[order]
    step = np.r_[np.inf, ((p[1:] - p[:-1]) ** 2).sum(axis=1)]
    same = np.r_[False, tid[1:] == tid[:-1]]
    cut = same & (np.r_[0, np.diff(f)] == 1) & (step > cutoff)
    out = np.empty_like(track)
    out[order] = np.cumsum(~same | cut) - 1
    return out


def link_defects(
    defects: pd.DataFrame,
    max_distance: float,
    gap_frames: int = 1,
    gap_max_distance: float | None = None,
    frames: Sequence[int] | None = None,
) -> pd.DataFrame:
    """Give every defect a ``track_id`` by linking same-charge defects frame to frame.

    Parameters
    ----------
    defects : DataFrame, shape (M, ...)
        One row per defect and frame with columns ``t``, ``x``, ``y``, ``z`` (µm) and
        ``charge_rounded``; optional ``c`` and ``layer`` columns separate independent series.
    max_distance : float
        Largest displacement (µm) between consecutive analysed frames for a link.
    gap_frames : int
        Largest number of consecutive frames a defect may be missed and still be linked
        (0 = no gap closing).
    gap_max_distance : float, optional
        Largest displacement (µm) across a gap; default ``max_distance``. A link between
        consecutive frames is never longer than ``max_distance`` (laptrack's gap closing also
        joins segments of adjacent frames; such links are split again).
    frames : sequence of int, optional
        All analysed time points (also those without defects), so a frame with no detection
        counts as a gap. Default: the sorted unique ``t`` of ``defects``.

    Returns
    -------
    DataFrame, shape (M, ...)
        ``defects`` (same row order) with an integer column ``track_id`` (0, 1, ...; unique
        across groups, numbered by group, then first frame, then position).
    """
    from laptrack import LapTrack  # imported here: optional cost at import of nemo

    _check(defects, max_distance, gap_frames)
    # rows are selected by position: labels may repeat (per-frame tables concatenated without
    # ignore_index), and .loc on a repeated label selects every row that has it
    out = defects.reset_index(drop=True)
    out["track_id"] = np.full(len(out), -1, dtype=np.int64)
    if out.empty:
        return out.set_axis(defects.index)
    if frames is not None:
        _check_time_points(list(frames), "frames has values")
    t_all = np.unique(np.asarray(frames if frames is not None else out["t"], dtype=np.int64))
    unknown = np.setdiff1d(out["t"].to_numpy(dtype=np.int64), t_all)
    if unknown.size:
        raise NemoError(f"defects at t = {unknown.tolist()} are not among the analysed frames {t_all.tolist()}")
    rank = pd.Series(np.arange(t_all.size), index=t_all)
    gap_max = float(gap_max_distance) if gap_max_distance is not None else float(max_distance)
    group_cols = [c for c in GROUP_COLUMNS if c in out.columns] + ["charge_rounded"]
    # round the charge key so float noise (0.4999999) never splits a group
    key = out[group_cols].copy()
    key["charge_rounded"] = np.round(key["charge_rounded"].to_numpy(dtype=float) * 2) / 2
    next_id = 0
    for index in key.groupby(group_cols, sort=True, dropna=False).indices.values():
        sub = out.loc[index, ["x", "y", "z"]].astype(float).reset_index(drop=True)
        sub["frame"] = rank.loc[out.loc[index, "t"].to_numpy(dtype=np.int64)].to_numpy()
        sub["row_"] = np.arange(len(sub))
        lt = LapTrack(
            metric="sqeuclidean",
            cutoff=_cutoff(max_distance),
            gap_closing_metric="sqeuclidean",
            gap_closing_cutoff=_cutoff(gap_max) if gap_frames > 0 else False,
            gap_closing_max_frame_count=int(gap_frames) + 1,
            splitting_cutoff=False,
            merging_cutoff=False,
        )
        track_df, _, _ = lt.predict_dataframe(sub, coordinate_cols=["x", "y", "z"], frame_col="frame")
        local = np.empty(len(sub), dtype=np.int64)
        local[track_df["row_"].to_numpy(dtype=np.int64)] = track_df["track_id"].to_numpy()
        local = _split_long_steps(local, sub["frame"].to_numpy(), sub[["x", "y", "z"]].to_numpy(), _cutoff(max_distance))
        # renumber deterministically: by first frame, then x, y, z of the first detection
        first = (
            pd.DataFrame({"tid": local, "frame": sub["frame"].to_numpy(), "x": sub["x"].to_numpy(),
                          "y": sub["y"].to_numpy(), "z": sub["z"].to_numpy()})
            .sort_values(["frame", "x", "y", "z"]).drop_duplicates("tid")
        )
        new = {tid: next_id + i for i, tid in enumerate(first["tid"])}
        out.loc[index, "track_id"] = np.array([new[v] for v in local], dtype=np.int64)
        next_id += len(new)
    return out.set_axis(defects.index)


#: Time points (ranks) an object may be missing, or its frame empty, and keep its id when it returns.
OBJECT_GAP = 2


def link_objects(frames: pd.DataFrame, gap: int = OBJECT_GAP) -> pd.Series:
    """A persistent identity (``object_id``) for each object of ``frames.parquet`` across time points.

    With ``mesh.keep: all`` the ``object`` label of a frame is an area rank, so two objects whose
    areas cross swap labels (an independent review: a shrinking shell and a growing one 1.5 µm
    apart swapped at t = 3, and each label's series fell and rose again). The objects of each time
    point are matched to the ids seen in the last ``gap`` + 1 time points (at their last centre)
    by the linear assignment of the distances between centres (scipy); a match only within the
    larger of the two objects' radii (of the sphere of the same area). An object without a match
    gets a new id (it entered the field, or its centre jumped). Ids count from 0 in order of first
    appearance, then of label. One object's rows (its layers, surfaces and the channels peeled from
    the one segmentation) share its id: each (t, object) is linked once, by the centre and area of
    its ``whole`` surface's row (else its first row).

    Parameters
    ----------
    frames : DataFrame
        Rows with ``t``, ``object``, ``centre_x``, ``centre_y``, ``centre_z`` and ``area`` (and
        ``surface``); with ``snr``, rows of a frame that looks empty
        (:data:`nemo.summary.QC_EMPTY_SNR`) get no id and do not break the others' links.
    gap : int
        Time points an id may go unseen and still be matched.

    Returns
    -------
    Series of Int64, aligned with ``frames``
        The id; NA for a row without a finite centre and area, or of an empty frame.
    """
    from nemo.summary import QC_EMPTY_SNR

    centre = ["centre_x", "centre_y", "centre_z"]
    usable = frames[centre + ["area"]].apply(pd.to_numeric, errors="coerce").notna().all(axis=1)
    if "snr" in frames.columns:
        usable &= ~(pd.to_numeric(frames["snr"], errors="coerce") < QC_EMPTY_SNR)
    whole_first = frames["surface"].astype(str).ne("whole") if "surface" in frames.columns else False
    objs = frames[usable].assign(_rank=whole_first).sort_values(["t", "object", "_rank"], kind="stable")
    objs = objs.drop_duplicates(["t", "object"])
    xyz = objs[centre].to_numpy(np.float64)
    radius = np.sqrt(objs["area"].to_numpy(np.float64) / (4 * np.pi))
    times = objs["t"].to_numpy()
    ids = np.full(len(objs), -1, dtype=np.int64)
    last_seen: dict[int, tuple[int, int]] = {}  # id -> (rank of its last time point, its row there)
    for rank, t in enumerate(np.unique(times)):  # a loop over time points, not objects
        now = np.flatnonzero(times == t)
        known = [(i, row) for i, (r, row) in last_seen.items() if rank - r <= gap + 1]
        if known:
            before = np.array([row for _, row in known])
            ids[now] = _assign(xyz[before], radius[before], xyz[now], radius[now], np.array([i for i, _ in known]))
        new = now[ids[now] < 0]
        ids[new] = len(last_seen) + np.arange(len(new))
        last_seen.update({int(ids[j]): (rank, int(j)) for j in now})
    by_key = dict(zip(zip(objs["t"], objs["object"]), ids))
    found = [by_key.get(k, -1) for k in zip(frames["t"], frames["object"])]
    return pd.Series(found, index=frames.index, dtype="Int64").where(lambda v: (v >= 0) & usable.to_numpy())


def _assign(xyz_a: np.ndarray, r_a: np.ndarray, xyz_b: np.ndarray, r_b: np.ndarray, ids_a: np.ndarray) -> np.ndarray:
    """The id of ``ids_a`` that each of B takes (−1: none): the linear assignment of the centres'
    distances, a pair only within the larger of their radii. Pairs out of reach cost more than any
    assignment of pairs in reach (a finite cost: an infinite one spoils the solver's optimum)."""
    from scipy.optimize import linear_sum_assignment

    dist = np.linalg.norm(xyz_a[:, None] - xyz_b[None], axis=2)
    near = dist <= np.maximum(r_a[:, None], r_b[None])
    cost = np.where(near, dist, (dist[near].sum() if near.any() else 0.0) + 1.0)
    rows, cols = linear_sum_assignment(cost)
    out = np.full(len(xyz_b), -1, dtype=np.int64)
    keep = near[rows, cols]
    out[cols[keep]] = ids_a[rows[keep]]
    return out


def summarise_tracks(linked: pd.DataFrame) -> pd.DataFrame:
    """One row per track from a table made by :func:`link_defects`.

    Parameters
    ----------
    linked : DataFrame
        Defects with ``track_id``, ``t``, ``x``, ``y``, ``z``, ``charge_rounded`` (and
        optionally ``charge``, ``S``, ``c``, ``layer``).

    Returns
    -------
    DataFrame, shape (n_tracks, ...)
        Columns ``track_id``, [``c``, ``layer``,] ``charge`` (mean raw charge, NaN if absent),
        ``charge_rounded``, ``first_t``, ``last_t``, ``length`` (number of detections),
        ``span`` (``last_t - first_t + 1``), ``path_length`` (µm, sum of the steps between
        successive detections), ``mean_speed`` (µm per unit of t: path length /
        (last_t - first_t); NaN for a single detection), ``mean_S``; with a ``qc_pass``
        column in ``linked`` (the workflow's defects, from their frames' quality control) also
        ``n_flagged`` (detections in frames that failed it) and ``qc_pass`` (none did); with an
        ``object_id`` column (:func:`link_objects`, the workflow's defects) also ``object_id``
        (the object of most of its detections) and ``n_objects`` (the objects its detections lie
        on: 1 for a track that stays on its object).
    """
    if "track_id" not in linked.columns:
        raise NemoError("table has no 'track_id' column: link the defects first (nemo track)")
    group = [c for c in GROUP_COLUMNS if c in linked.columns]
    cols = ["track_id", *group, "charge", "charge_rounded", "first_t", "last_t", "length",
            "span", "path_length", "mean_speed", "mean_S"]
    if linked.empty:
        extra = (["n_flagged", "qc_pass"] if "qc_pass" in linked.columns else []) + (
            ["object_id", "n_objects"] if "object_id" in linked.columns else [])
        return pd.DataFrame({c: pd.Series(dtype="object" if c == "layer" else float) for c in cols + extra})
    df = linked.sort_values(["track_id", "t"]).reset_index(drop=True)
    xyz = df[["x", "y", "z"]].to_numpy(dtype=float)
    tid = df["track_id"].to_numpy()
    step = np.zeros(len(df))
    same = np.r_[False, tid[1:] == tid[:-1]]
    step[same] = np.linalg.norm(xyz[1:] - xyz[:-1], axis=1)[same[1:]]
    df["_step"] = step
    if "charge" not in df.columns:
        df["charge"] = np.nan
    if "S" not in df.columns:
        df["S"] = np.nan
    agg = df.groupby("track_id", sort=True).agg(
        **{g: (g, "first") for g in group},
        charge=("charge", "mean"),
        charge_rounded=("charge_rounded", "first"),
        first_t=("t", "min"),
        last_t=("t", "max"),
        length=("t", "size"),
        path_length=("_step", "sum"),
        mean_S=("S", "mean"),
    ).reset_index()
    if "qc_pass" in df.columns:
        flagged = (~df["qc_pass"].astype(bool)).groupby(df["track_id"], sort=True).sum()
        agg["n_flagged"] = flagged.to_numpy(dtype=np.int64)
        agg["qc_pass"] = agg["n_flagged"] == 0
        cols += ["n_flagged", "qc_pass"]
    if "object_id" in df.columns:  # the workflow's defects: the object each detection lies on
        ids = df["object_id"].astype("Int64").groupby(df["track_id"], sort=True)
        agg["object_id"] = ids.agg(lambda v: v.mode().min() if v.notna().any() else pd.NA).astype("Int64").array
        agg["n_objects"] = ids.nunique().to_numpy(dtype=np.int64)  # 0: none of its detections has an id
        cols.insert(1 + len(group), "object_id")
        cols.append("n_objects")
    agg["span"] = agg["last_t"] - agg["first_t"] + 1
    dt = (agg["last_t"] - agg["first_t"]).to_numpy(dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        agg["mean_speed"] = np.where(dt > 0, agg["path_length"].to_numpy() / dt, np.nan)
    return agg[cols]
