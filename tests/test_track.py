"""Defect tracking (nemo.track, nemo track) on synthetic series with known moving defects."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from nemo.errors import NemoError
from nemo.tables import read_table, write_table
from nemo.track import link_defects, summarise_tracks

R = 100.0  # µm


def _tetrahedron() -> np.ndarray:
    v = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], dtype=float)
    return R * v / np.linalg.norm(v, axis=1, keepdims=True)


def _rotz(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _series(n_frames=8, omega=0.05, noise=0.5, rng=None, extra=None, drop=()):
    """4 × +½ at tetrahedron vertices rotating about z by ``omega`` rad per frame.

    Returns the shuffled defect table and the true identity of each row (column ``truth``).
    """
    rng = np.random.default_rng(rng)
    base = _tetrahedron()
    charges = [0.5] * 4
    if extra is not None:  # (position (3,), charge)
        base = np.vstack([base, extra[0]])
        charges.append(extra[1])
    rows = []
    for t in range(n_frames):
        pos = base @ _rotz(omega * t).T + rng.normal(0, noise, base.shape)
        for k, (p, q) in enumerate(zip(pos, charges)):
            if (t, k) in drop:
                continue
            rows.append(dict(t=t, c=0, layer="basal", x=p[0], y=p[1], z=p[2],
                             charge=q + rng.normal(0, 0.02), charge_rounded=q, S=0.05, truth=k))
    return pd.DataFrame(rows).sample(frac=1.0, random_state=3).reset_index(drop=True)


def _check_identity(linked: pd.DataFrame) -> None:
    """Every track holds exactly one true defect and every true defect exactly one track."""
    pairs = linked.groupby("track_id")["truth"].nunique()
    assert (pairs == 1).all(), "a track mixes two defects"
    per_truth = linked.groupby("truth")["track_id"].nunique()
    assert (per_truth == 1).all(), "a defect was split into several tracks"


def test_one_track_per_rotating_defect_with_right_charge_and_speed():
    omega = 0.05
    df = _series(omega=omega, noise=0.3, rng=1)
    linked = link_defects(df, max_distance=15.0, gap_frames=1)
    _check_identity(linked)
    tracks = summarise_tracks(linked)
    assert len(tracks) == 4
    assert (tracks["charge_rounded"] == 0.5).all()
    assert np.allclose(tracks["charge"], 0.5, atol=0.03)
    assert (tracks["first_t"] == 0).all() and (tracks["last_t"] == 7).all()
    assert (tracks["length"] == 8).all()
    # analytic speed: chord of the rotation per frame, 2 r sin(ω/2), r = distance to the z axis
    truth = _tetrahedron()
    r_axis = np.hypot(truth[:, 0], truth[:, 1])
    expected = 2 * r_axis * np.sin(omega / 2)
    first = linked.sort_values("t").groupby("track_id")["truth"].first()
    got = tracks.set_index("track_id")["mean_speed"]
    exp = pd.Series(expected[first.to_numpy()], index=first.index)
    # noise adds sqrt(2·3)·σ per step in quadrature at most; 0.3 µm noise on a 4 µm step
    assert np.allclose(got.loc[exp.index], exp, rtol=0.15)


def test_per_frame_tables_concatenated_with_repeated_labels():
    """Per-frame tables joined by pd.concat without ignore_index repeat the labels 0, 1, 2, 3 in
    every frame; selecting rows by label then picked every frame's rows at once and every defect
    became its own track. The rows are linked by position and keep their labels."""
    df = _series(omega=0.05, noise=0.3, rng=1).sort_values(["t", "truth"])
    frames = [f.reset_index(drop=True) for _, f in df.groupby("t")]
    joined = pd.concat(frames)  # labels 0..3 in every frame
    assert joined.index.has_duplicates
    linked = link_defects(joined, max_distance=15.0, gap_frames=1)
    _check_identity(linked)
    assert linked["track_id"].nunique() == 4
    assert linked.index.equals(joined.index)
    assert linked.drop(columns="track_id").equals(joined)


def test_same_charge_links_only():
    # a −½ sitting where a +½ will be one frame later: a charge-blind linker would swap them
    omega = 0.05
    p0 = _tetrahedron()[0]
    minus = _rotz(omega) @ p0 + np.array([0.0, 0.0, 0.5])
    df = _series(omega=omega, noise=0.0, rng=2, extra=(minus, -0.5))
    linked = link_defects(df, max_distance=15.0, gap_frames=1)
    _check_identity(linked)
    tracks = summarise_tracks(linked)
    assert len(tracks) == 5
    assert sorted(tracks["charge_rounded"]) == [-0.5, 0.5, 0.5, 0.5, 0.5]
    mixed = linked.groupby("track_id")["charge_rounded"].nunique()
    assert (mixed == 1).all()


def test_gap_closing_and_max_displacement():
    df = _series(n_frames=6, omega=0.05, noise=0.2, rng=3, drop={(3, 1)})
    closed = link_defects(df, max_distance=15.0, gap_frames=1)
    _check_identity(closed)
    tr = summarise_tracks(closed)
    assert len(tr) == 4
    assert sorted(tr["length"]) == [5, 6, 6, 6]  # the missed frame is bridged
    assert (tr["span"] == 6).all()
    open_ = summarise_tracks(link_defects(df, max_distance=15.0, gap_frames=0))
    assert len(open_) == 5  # without gap closing the missed defect restarts a track
    # a step (≈ 4 µm) larger than max_distance is never linked
    cut = summarise_tracks(link_defects(df, max_distance=3.0, gap_frames=1))
    assert len(cut) == len(df)


def test_a_link_between_consecutive_frames_is_never_longer_than_max_distance():
    """laptrack's gap closing also joins segments of adjacent frames, up to its own cut-off: a
    larger gap_max_distance let a 4 µm step through a 1 µm max_distance (an independent review)."""
    one_then_another = pd.DataFrame({"t": [0, 1, 2, 3], "x": [0.0, 0.1, 4.1, 4.2], "y": 0.0, "z": 0.0,
                                     "charge_rounded": 0.5})
    for gap_max in (None, 2.0, 5.0):
        linked = link_defects(one_then_another, max_distance=1.0, gap_frames=1, gap_max_distance=gap_max)
        assert linked["track_id"].tolist() == [0, 0, 1, 1], gap_max
    # a missed frame is still bridged up to gap_max_distance
    missed = one_then_another.drop(index=2)
    assert link_defects(missed, max_distance=1.0, gap_frames=1, gap_max_distance=5.0,
                        frames=range(4))["track_id"].nunique() == 1
    assert link_defects(missed, max_distance=1.0, gap_frames=1, gap_max_distance=2.0,
                        frames=range(4))["track_id"].nunique() == 2


def test_a_step_of_exactly_max_distance_is_linked():
    step = pd.DataFrame({"t": [0, 1, 2], "x": [0.0, 2.0, 4.0], "y": 0.0, "z": 0.0, "charge_rounded": -0.5})
    assert link_defects(step, max_distance=2.0)["track_id"].nunique() == 1
    assert link_defects(step, max_distance=1.99)["track_id"].nunique() == 3


@pytest.mark.parametrize("t", [[0, 0.5, 1.0, 1.5], [0, 1, np.nan, 3], ["0", "1", "2", "3"], [True, False, True, False]])
def test_time_points_that_are_not_indices_are_refused(t):
    df = pd.DataFrame({"t": t, "x": [0.0, 0.1, 0.2, 0.3], "y": 0.0, "z": 0.0, "charge_rounded": 0.5})
    with pytest.raises(NemoError, match="not whole time-point indices"):
        link_defects(df, max_distance=1.0)
    whole = df.assign(t=[0.0, 1.0, 2.0, 3.0])  # whole numbers in a float column are indices
    assert link_defects(whole, max_distance=1.0)["track_id"].nunique() == 1
    with pytest.raises(NemoError, match="frames has values"):
        link_defects(whole, max_distance=1.0, frames=[0, 1, 2, 2.5, 3])


def test_non_consecutive_time_points_are_consecutive_frames():
    df = _series(n_frames=5, omega=0.05, noise=0.1, rng=4)
    df["t"] = df["t"] * 2  # analysed t = 0, 2, 4, 6, 8
    linked = link_defects(df, max_distance=15.0, gap_frames=0, frames=[0, 2, 4, 6, 8])
    _check_identity(linked)
    tr = summarise_tracks(linked)
    assert len(tr) == 4 and (tr["last_t"] == 8).all()
    # speed is per unit of t: half the per-frame step
    assert tr["mean_speed"].max() < 0.6 * 2 * R * np.sin(0.05 / 2)


def test_layers_and_channels_are_tracked_separately():
    a = _series(n_frames=4, rng=5)
    b = a.copy()
    b["layer"] = "apical"  # identical positions in another layer must not share tracks
    linked = link_defects(pd.concat([a, b], ignore_index=True), max_distance=15.0)
    assert linked["track_id"].nunique() == 8
    assert (linked.groupby("track_id")["layer"].nunique() == 1).all()


def test_empty_and_bad_tables():
    empty = _series(n_frames=1).iloc[:0]
    assert summarise_tracks(link_defects(empty, max_distance=5.0)).empty
    with pytest.raises(NemoError, match="charge_rounded"):
        link_defects(_series(n_frames=2).drop(columns="charge_rounded"), max_distance=5.0)
    with pytest.raises(NemoError, match="max_distance"):
        link_defects(_series(n_frames=2), max_distance=-1.0)
    with pytest.raises(NemoError, match="not among the analysed frames"):
        link_defects(_series(n_frames=3), max_distance=5.0, frames=[0, 1])


def test_cli_track(tmp_path, run_cli):
    df = _series(n_frames=5, omega=0.05, noise=0.2, rng=6)
    src = tmp_path / "defects_untracked.parquet"
    write_table(df, src)
    code, out, err = run_cli("track", src, "-o", tmp_path / "tracks.parquet",
                             "--linked", tmp_path / "defects.parquet", "--max-distance", "15")
    assert code == 0, err
    tracks = read_table(tmp_path / "tracks.parquet")
    linked = read_table(tmp_path / "defects.parquet")
    assert len(tracks) == 4 and "track_id" in linked
    _check_identity(linked)
    code, out, err = run_cli("track", tmp_path / "tracks.parquet", "-o", tmp_path / "x.parquet",
                             "--max-distance", "15")
    assert code == 2 and "lacks column" in err and "\n" not in err.strip()


def test_cli_default_max_distance_is_the_median_over_frames(tmp_path, run_cli):
    """Every defect row repeats its frame's suppression radius: the default is their median over the
    frames, not over the distinct values (three frames at 3 µm and two at 10 and 12 µm: 3, not 10)."""
    from nemo.tables import read_provenance

    df = _series(n_frames=5, omega=0.05, noise=0.2, rng=6)
    df["min_distance"] = df["t"].map({0: 3.0, 1: 3.0, 2: 3.0, 3: 10.0, 4: 12.0})
    write_table(df, tmp_path / "d.parquet")
    code, out, err = run_cli("track", tmp_path / "d.parquet", "-o", tmp_path / "tracks.parquet")
    assert code == 0, err
    assert read_provenance(tmp_path / "tracks.parquet")["parameters"]["max_distance"] == 3.0


def test_tracks_count_their_detections_in_flagged_frames():
    """With the workflow's defects (each with its frame's qc_pass), a track says how many of its
    detections come from frames that failed the quality control."""
    df = _series(n_frames=4, omega=0.05, noise=0.0, rng=1)
    df["qc_pass"] = df["t"] != 2
    tracks = summarise_tracks(link_defects(df, max_distance=15.0, gap_frames=1))
    assert len(tracks) == 4 and (tracks["n_flagged"] == 1).all() and not tracks["qc_pass"].any()
    df["qc_pass"] = True
    assert summarise_tracks(link_defects(df, max_distance=15.0, gap_frames=1))["qc_pass"].all()
    assert "n_flagged" not in summarise_tracks(link_defects(df.drop(columns="qc_pass"), 15.0, 1)).columns


def _two_objects_crossing(n_t: int = 4) -> pd.DataFrame:
    """frames.parquet of two shells whose areas cross at t = 2 (labels are area ranks: they swap),
    two layer rows per object, and a third object entering at t = 3 far from both."""
    a = [(50.0, 8500.0), (52.0, 7200.0), (54.0, 6100.0), (56.0, 5000.0)]
    b = [(120.0, 2800.0), (116.0, 3600.0), (112.0, 6500.0), (108.0, 7800.0)]
    rows = []
    for t in range(n_t):
        objs = [("A", *a[t]), ("B", *b[t])] + ([("C", 180.0, 2000.0)] if t == 3 else [])
        for label, (name, x, area) in enumerate(sorted(objs, key=lambda o: -o[2])):
            for layer, surface, dx in (("fibres", "inner", 0.4), ("cortex", "outer", -0.3)):  # each surface its centre
                rows.append({"t": t, "c": 0, "layer": layer, "surface": surface, "object": label, "centre_x": x + dx,
                             "centre_y": 65.0, "centre_z": 40.0, "area": area, "name": name})
    return pd.DataFrame(rows)


def test_objects_keep_their_identity_when_their_area_ranks_swap():
    """Each object keeps one id over time although its label (area rank) changes; every row of an
    object has its id; an object entering the field gets a new one; channels of one segmentation
    share the ids; an empty frame or an object missing for a time point does not renumber them."""
    from nemo.track import link_objects

    df = _two_objects_crossing()
    df["object_id"] = link_objects(df)
    ids = df.groupby("name")["object_id"].agg(lambda v: sorted(set(v)))
    assert ids.to_dict() == {"A": [0], "B": [1], "C": [2]}
    assert df.loc[(df["t"] == 3) & (df["name"] == "A"), "object"].iloc[0] == 1  # the label did swap
    # a second channel peeled from the same meshes: the same objects, the same ids
    two = pd.concat([df.drop(columns="object_id"), df.drop(columns="object_id").assign(c=1)], ignore_index=True)
    linked = link_objects(two)
    assert (linked[two["c"] == 1].to_numpy() == linked[two["c"] == 0].to_numpy()).all()
    # an empty frame (its noise speck far away) and an object missing for a time point keep the ids
    gappy = df.drop(columns="object_id").assign(snr=8.0)
    gappy.loc[gappy["t"] == 1, ["centre_x", "area", "snr"]] = [300.0, 5.0, 0.9]
    gappy = gappy[~((gappy["t"] == 2) & (gappy["name"] == "B"))]
    ids = link_objects(gappy)
    assert ids[gappy["t"] == 1].isna().all()
    assert gappy.assign(i=ids).dropna().groupby("name")["i"].agg(lambda v: sorted(set(v))).to_dict() == {
        "A": [0], "B": [1], "C": [2]}
    # an object whose centre jumps by more than its radius is another object
    jump = df.drop(columns="object_id")
    jump.loc[(jump["name"] == "A") & (jump["t"] >= 2), "centre_x"] += 80.0
    assert sorted(set(link_objects(jump)[jump["name"] == "A"])) == [0, 2]  # ids in order of appearance
    # no finite centre: no id
    gone = df.drop(columns="object_id")
    gone.loc[gone["t"] == 1, "centre_x"] = np.nan
    assert link_objects(gone)[gone["t"] == 1].isna().all()


def test_a_track_reports_the_object_it_lies_on():
    """summarise_tracks gives each track the object_id of its detections and counts the objects
    (a track that stays on its object: 1)."""
    linked = pd.DataFrame({"track_id": [0, 0, 0, 1, 1], "t": [0, 1, 2, 0, 1], "x": [0.0, 1, 2, 50, 51],
                           "y": 0.0, "z": 0.0, "charge_rounded": [1.0, 1, 1, 0.5, 0.5],
                           "object_id": pd.array([3, 3, 3, 1, 2], dtype="Int64")})
    tracks = summarise_tracks(linked)
    assert tracks["object_id"].tolist() == [3, 1] and tracks["n_objects"].tolist() == [1, 2]
    assert str(tracks["object_id"].dtype) == "Int64"
    assert {"object_id", "n_objects"} <= set(summarise_tracks(linked.iloc[:0]).columns)
    assert "object_id" not in summarise_tracks(linked.drop(columns="object_id"))
