"""Figures of NEMO results: discovery, loading, spherical maps, pyvista renders, CLI.

Ground truth: an analytic results folder (icosphere of radius R around an off-centre point,
four +1/2 defects at tetrahedron vertices on mesh vertices, analytic fields) written by
``nemo.napari._sample.write_demo_results`` (numpy only, no napari).
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import warnings

import numpy as np
import pandas as pd
import pytest

from nemo.errors import NemoError, NemoWarning
from nemo.napari._sample import defect_field, write_demo_results
from nemo.render import (
    CAPTIONS,
    alignment_figure,
    charge_text,
    chart_directions,
    defect_lonlat,
    defect_map_figure,
    discover_frame,
    distributions_figure,
    field_label,
    find_frames,
    frame_qc,
    frames_figure,
    load_frame,
    morphology_figure,
    planned_figures,
    render_frame,
    render_summary,
    robust_limits,
    spherical_angles,
    spherical_figure,
    spherical_grid,
    surface_centre,
    surface_plotter,
    tracks_figure,
)
from nemo.tables import write_table


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    root = tmp_path_factory.mktemp("results")
    return write_demo_results(root, subdivisions=3, n_frames=3)


@pytest.fixture(scope="module")
def rendered(demo, tmp_path_factory):
    """All figures of frame 1 (pyvista renders included), written once for several tests."""
    out = tmp_path_factory.mktemp("figs")
    figs = render_frame(demo["frames"][1]["dir"], out)
    return out, figs


def _png(path):
    from matplotlib.image import imread

    img = imread(path)[..., :3]
    return img


def _colour_labels(fig) -> set[str]:
    return {ax.get_ylabel() for ax in fig.axes} | {ax.get_xlabel() for ax in fig.axes}


# ------------------------------------------------------------------------------ package layout


def test_package_reexports_and_imports_stay_light():
    """``nemo.render`` re-exports its modules' names and the discovery of ``nemo.layout``;
    importing it loads no plotting library, importing ``nemo.layout`` (the workflow does) no
    numerical one."""
    import nemo.layout
    import nemo.render

    assert nemo.render.discover_frame is nemo.layout.discover_frame
    assert nemo.render.find_frames is nemo.layout.find_frames
    assert nemo.render.FrameFiles is nemo.layout.FrameFiles
    assert all(hasattr(nemo.render, name) for name in nemo.render.__all__)
    code = ("import json, sys; import nemo.layout; a = sorted(sys.modules); import nemo.render; "
            "print(json.dumps([a, sorted(sys.modules)]))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    after_layout, after_render = ({m.split(".")[0] for m in mods} for mods in json.loads(out))
    assert not after_layout & {"numpy", "pandas", "scipy", "pyarrow", "trimesh"}
    assert not after_render & {"matplotlib", "pyvista", "vtk", "vtkmodules"}


# ------------------------------------------------------------------------------ discovery


def test_discovery_classifies_workflow_files(demo):
    ff = discover_frame(demo["frames"][0]["dir"])
    assert set(ff.meshes) == {"inner", "outer"}
    assert set(ff.layers) == set(ff.order) == set(ff.directors) == set(ff.defects) == {"a", "b"}
    assert set(ff.curvature) == {""} and set(ff.thickness) == {""}
    assert set(ff.align) == {"a_b"}
    assert (ff.t, ff.c) == (0, 0)
    assert ff.image is not None and ff.image.samefile(demo["image"])  # from the provenance


def test_find_frames_from_root_dataset_and_frame(demo):
    ds = demo["dataset_dir"]
    for path in (ds.parent, ds):
        tree = find_frames(path)
        assert sorted(tree.frames) == [(0, 0), (1, 0), (2, 0)]
        assert tree.summary == ds / "summary"
    tree = find_frames(ds / "t2" / "c0")
    assert list(tree.frames) == [(2, 0)]
    with pytest.raises(NemoError, match="dataset 'nope' not found"):
        find_frames(ds.parent, dataset="nope")
    with pytest.raises(NemoError, match="no NEMO results"):
        find_frames(ds / "summary")


def test_load_frame_places_fields_on_the_right_mesh(demo):
    fr = load_frame(demo["frames"][0]["dir"])
    inner = fr.surfaces["inner"]
    n = demo["n_vertices"]
    assert len(inner.mesh.vertices) == n
    assert {"intensity (a)", "S (a)", "intensity (b)", "H", "K", "thickness", "c (a-b)"} <= set(inner.fields)
    assert fr.surfaces["outer"].fields == {}
    z = (np.asarray(inner.mesh.vertices)[:, 2] - demo["centre"][2]) / demo["radius"]
    np.testing.assert_allclose(inner.fields["intensity (a)"], 100 + 50 * z, atol=1e-5)
    np.testing.assert_allclose(inner.fields["H"], (1 + 0.2 * z) / demo["radius"], rtol=1e-5)
    assert np.isnan(inner.fields["thickness"]).any()  # no-hit NaN kept, never filled
    assert inner.label("H") == "H [1/µm]" and inner.label("K") == "K [1/µm²]"
    assert inner.label("thickness") == "thickness [µm]"
    assert fr.layers["a"].surface == "inner" and len(fr.layers["a"].defects) == 4
    assert fr.align_surface[("a", "b")] == "inner"


def test_nemo_run_layout_is_readable(tmp_path):
    truth = write_demo_results(tmp_path / "run", subdivisions=3, layout="run")
    fr = load_frame(tmp_path / "run")
    assert set(fr.files.meshes) == {"mesh", "inner"}
    assert list(fr.layers) == ["layer"]
    # layer.parquet has one row per inner vertex: it goes on mesh.inner.ply, not on mesh.ply
    assert fr.layers["layer"].surface == "inner"
    assert set(fr.surfaces["inner"].fields) >= {"intensity (layer)", "S (layer)", "H", "K"}
    np.testing.assert_allclose(fr.layers["layer"].defects[["x", "y", "z"]], truth["frames"][0]["defects"])


def test_missing_and_foreign_tables_are_skipped(demo, tmp_path):
    src = demo["frames"][0]["dir"]
    frame = tmp_path / "t0" / "c0"
    shutil.copytree(src, frame)
    (frame / "order_b.parquet").unlink()
    (frame / "thickness.parquet").unlink()
    write_table(pd.DataFrame({"vertex": [10**6], "H": [1.0], "K": [1.0]}), frame / "curvature.parquet")
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        fr = load_frame(frame)
    assert any("beyond every mesh" in str(w.message) for w in rec)
    inner = fr.surfaces["inner"]
    assert "S (b)" not in inner.fields and "thickness" not in inner.fields and "H" not in inner.fields
    assert fr.layers["b"].order is None and fr.layers["b"].intensity is not None
    names = planned_figures(fr.files)
    assert "surface_order_b.png" not in names and "surface_order_a.png" in names


def test_discover_errors(tmp_path):
    with pytest.raises(NemoError, match="does not exist"):
        discover_frame(tmp_path / "missing")
    (tmp_path / "layer_a.parquet").write_bytes(b"")
    with pytest.raises(NemoError, match="no mesh"):
        discover_frame(tmp_path)


# ------------------------------------------------------------------------------ geometry


def test_spherical_angles_and_chart_directions():
    centre = np.array([3.0, -2.0, 5.0])
    az_true = np.array([-150.0, -30.0, 0.0, 45.0, 120.0])
    pol_true = np.array([20.0, 60.0, 90.0, 135.0, 170.0])
    a, p = np.radians(az_true), np.radians(pol_true)
    u = np.stack([np.sin(p) * np.cos(a), np.sin(p) * np.sin(a), np.cos(p)], axis=1)
    az, pol = spherical_angles(centre + 7.0 * u, centre)
    np.testing.assert_allclose(az, az_true, atol=1e-9)
    np.testing.assert_allclose(pol, pol_true, atol=1e-9)
    e_phi = np.stack([-np.sin(a), np.cos(a), np.zeros_like(a)], axis=1)
    e_theta = np.stack([np.cos(p) * np.cos(a), np.cos(p) * np.sin(a), -np.sin(p)], axis=1)
    np.testing.assert_allclose(chart_directions(centre + 7 * u, e_phi, centre), [[1, 0]] * 5, atol=1e-9)
    np.testing.assert_allclose(chart_directions(centre + 7 * u, e_theta, centre), [[0, 1]] * 5, atol=1e-9)


def test_spherical_grid_resamples_polar_angle(demo):
    fr = load_frame(demo["frames"][0]["dir"])
    mesh = fr.surfaces["inner"].mesh
    centre = surface_centre(mesh)
    np.testing.assert_allclose(centre, demo["centre"], atol=1e-6)
    _, pol = spherical_angles(np.asarray(mesh.vertices), centre)
    grid = spherical_grid(mesh.vertices, pol, centre, n_polar=90)
    rows = (np.arange(90) + 0.5) * 2.0
    # nearest vertex: error below the vertex spacing (642 vertices: ~8.5° apart)
    assert np.abs(grid - rows[:, None]).max() < 8.0
    assert np.abs(grid - rows[:, None]).mean() < 2.5  # rings of vertices: quantised, unbiased


def test_spherical_map_puts_defects_at_their_angles(demo):
    for k in (0, 2):
        truth = demo["frames"][k]
        fr = load_frame(truth["dir"])
        fig = spherical_figure(fr, "a")
        ax = fig.axes[0]
        coll = next(c for c in ax.collections if c.get_gid() == "defects")
        xy = np.asarray(coll.get_offsets())
        np.testing.assert_allclose(xy[:, 0], truth["azimuth"], atol=1e-3)
        np.testing.assert_allclose(xy[:, 1], truth["polar"], atol=1e-3)
        texts = [t.get_text() for t in ax.texts]
        assert texts.count("+1/2") == 4
        labels = {a.get_ylabel() for a in fig.axes[1:]}  # the colour bars
        assert {"intensity [a.u.]", "S", "charge m"} <= labels
        assert ax.get_xlabel() == "azimuth φ [°]" and ax.get_ylabel() == "polar angle θ [°]"


def test_spherical_map_of_several_objects_centres_each_object():
    """A surface of two labelled spheres 100 µm apart (mesh.keep: all): one panel per object, each
    about its own centre, so each object's defect at its north pole reads polar angle 0 (about the
    centroid of both, the maps overlaid and the poles read 27°)."""
    from pathlib import Path
    from types import SimpleNamespace

    import trimesh

    from nemo.objects import concatenate
    from nemo.render.data import Layer, Surface

    spheres = [trimesh.creation.icosphere(subdivisions=3, radius=25.0) for _ in range(2)]
    spheres[1].apply_translation([100.0, 0.0, 0.0])
    mesh = concatenate(spheres, [0, 1])
    n = len(mesh.vertices)
    order = pd.DataFrame({"vertex": np.arange(n), **dict(zip("xyz", np.asarray(mesh.vertices).T)), "S": 0.8,
                          "nx": 1.0, "ny": 0.0, "nz": 0.0})
    defects = pd.DataFrame({"x": [0.0, 100.0], "y": 0.0, "z": 25.0, "charge": [1.0, 0.5], "object": [0, 1]})
    layer = Layer("a", "inner", intensity=np.linspace(0, 1, n), order=order, defects=defects)
    frame = SimpleNamespace(layers={"a": layer}, surfaces={"inner": Surface("inner", Path("m.ply"), mesh)})
    fig = spherical_figure(frame, "a")
    maps = [ax for ax in fig.axes if ax.get_xlabel() == "azimuth φ [°]"]
    assert len(maps) == 2
    for k, ax in enumerate(maps):
        assert f"object {k}" in ax.get_title()
        xy = np.asarray(next(c for c in ax.collections if c.get_gid() == "defects").get_offsets())
        assert len(xy) == 1 and xy[0, 1] < 1.0  # its own north pole
        glyphs = next(c for c in ax.collections if c.get_gid() == "directors")
        assert 0 < len(glyphs.X) < n  # its own directors only


def test_spherical_map_directors_follow_the_field(demo):
    """A glyph's chart direction is the analytic director mapped into the chart."""
    truth = demo["frames"][0]
    fr = load_frame(truth["dir"])
    fig = spherical_figure(fr, "a")
    q = next(c for c in fig.axes[0].collections if c.get_gid() == "directors")
    az, pol = np.asarray(q.X), np.asarray(q.Y)
    a, p = np.radians(az), np.radians(pol)
    unit = np.stack([np.sin(p) * np.cos(a), np.sin(p) * np.sin(a), np.cos(p)], axis=1)
    d_unit = (truth["defects"] - demo["centre"]) / demo["radius"]
    n = defect_field(unit, d_unit, np.full(4, 0.5))
    expect = chart_directions(demo["centre"] + demo["radius"] * unit, n, demo["centre"])
    got = np.stack([q.U, q.V], axis=1)
    cos = np.abs(np.einsum("ij,ij->i", got, expect))  # headless: n and -n are the same
    assert np.median(cos) > 0.999


# ------------------------------------------------------------------------------ figures


def test_alignment_figure_shows_the_averaged_alignment_beside_c(demo):
    """With the order tables' c_avg and weight (nemo align --order-a/--order-b), the histogram also
    draws c_avg (S_A·S_B-weighted) and its title gives the weighted mean; without them, c alone."""
    def histogram(fig):
        (ax,) = [a for a in fig.axes if a.get_ylabel() == "probability density"]
        return ax

    fr = load_frame(demo["frames"][0]["dir"])
    plain = histogram(alignment_figure(fr, ("a", "b")))
    assert plain.get_title().startswith("mean c = ") and "c_avg" not in plain.get_title()
    assert plain.get_legend() is None
    df = fr.align[("a", "b")]
    n = len(df)
    fr.align[("a", "b")] = df.assign(c_avg=np.r_[np.full(n - 1, -0.9), 1.0], weight=np.r_[np.full(n - 1, 0.5), 0.0])
    hist = histogram(alignment_figure(fr, ("a", "b")))
    assert hist.get_title().endswith("c_avg = -0.90")  # the zero-weight +1 left out
    assert [t.get_text() for t in hist.get_legend().get_texts()] == ["c per director", "c_avg (S-weighted)"]


def test_colour_bar_labels_have_units(demo):
    fr = load_frame(demo["frames"][0]["dir"])
    fig = morphology_figure(fr.surfaces["inner"])
    labels = {a.get_ylabel() for a in fig.axes}
    assert {"H [1/µm]", "K [1/µm²]", "thickness [µm]"} <= labels
    fig = alignment_figure(fr, ("a", "b"))
    assert "alignment c = cos 2Δθ" in _colour_labels(fig)
    fig = distributions_figure(fr.surfaces["inner"].fields["S (a)"], fr.layers["a"].defects["charge"])
    assert {"S", "charge m"} <= {a.get_xlabel() for a in fig.axes}
    p = surface_plotter(fr.surfaces["inner"].mesh, scalars=fr.surfaces["inner"].fields["H"],
                        label=field_label("H"), defects=(fr.layers["a"].defects[["x", "y", "z"]].to_numpy(),
                                                         fr.layers["a"].defects["charge"].to_numpy()))
    try:
        assert {"H [1/µm]", "charge m"} <= set(p.scalar_bars.keys())
    finally:
        p.close()


def test_distributions_histograms_are_densities(rng):
    S = rng.uniform(0, 1, 5000)
    fig = distributions_figure(S, [0.49, 0.51, -0.5])
    ax_s, ax_q = fig.axes[:2]
    heights = np.array([p.get_height() for p in ax_s.patches])
    assert abs(heights.sum() * 1 / 40 - 1) < 1e-6  # density over 40 bins of width 1/40
    assert abs(heights.mean() - 1) < 0.02  # uniform S
    centres = np.array([p.get_x() + p.get_width() / 2 for p in ax_q.patches if p.get_height() > 0])
    np.testing.assert_allclose(np.sort(centres), [-0.5, 0.5], atol=1e-9)


def test_tracks_figure_follows_the_tracks(demo):
    df = pd.read_parquet(demo["dataset_dir"] / "summary" / "defects.parquet")
    centres = {(f["t"], 0): demo["centre"] for f in demo["frames"]}
    fig = tracks_figure(df, "a", centres)
    ax = fig.axes[0]
    pts = np.concatenate([np.asarray(c.get_offsets()) for c in ax.collections])
    expect = np.concatenate([[f["azimuth"][k], f["polar"][k]] for k in range(4) for f in demo["frames"]]).reshape(-1, 2)
    assert len(pts) == 12
    d = np.linalg.norm(pts[:, None] - expect[None], axis=2).min(axis=1)
    assert d.max() < 1e-6
    # right panel: great-circle distance (radius R) from each track's first position
    dist_lines = fig.axes[1].get_lines()
    assert len(dist_lines) == 4
    for line, k in zip(dist_lines, range(4)):
        u = np.array([(f["defects"][k] - demo["centre"]) / demo["radius"] for f in demo["frames"]])
        great = np.arccos(np.clip(u @ u[0], -1, 1)) * demo["radius"]
        assert great[-1] > 5.0  # the defects do move
        np.testing.assert_allclose(line.get_ydata(), great, atol=1e-4)


def test_render_frame_writes_every_planned_figure(demo, rendered):
    out, figs = rendered
    planned = planned_figures(discover_frame(demo["frames"][1]["dir"]))
    assert {f.path.name for f in figs} == set(planned)
    assert len(planned) == 15
    manifest = json.loads((out / "figures.json").read_text())
    for name, kind in planned.items():
        assert manifest[name]["kind"] == kind and manifest[name]["caption"]
        img = _png(out / name)
        assert img.std() > 0.02, name
        rgb = (img.reshape(-1, 3) * 255).astype(np.int64)
        colours = np.unique(rgb[:, 0] * 65536 + rgb[:, 1] * 256 + rgb[:, 2])
        assert len(colours) > 20, name
    assert manifest["surface_order_a.png"]["parameters"]["order_a.parquet"]["radius"] == pytest.approx(5.0)
    assert all("{" not in m["caption"] for m in manifest.values())


def test_surface_render_shows_the_field(rendered):
    """The intensity render is dark at the bottom (z low) and bright at the top: 50 … 150."""
    out, _ = rendered
    img = _png(out / "surface_intensity_a.png").mean(axis=2)
    h, w = img.shape
    left = img[:, : w // 2]
    sphere = left[int(0.1 * h): int(0.85 * h)]
    col = sphere[:, sphere.shape[1] // 2]
    fg = col[col < 0.99]  # skip the white background
    assert fg[: len(fg) // 4].mean() > fg[-len(fg) // 4:].mean() + 0.2


def test_summary_figures(demo, tmp_path):
    figs = render_summary(demo["dataset_dir"] / "summary", tmp_path)
    assert sorted(f.path.name for f in figs) == ["defect_map_a.png", "defect_map_b.png", "frames.png",
                                                 "tracks_a.png", "tracks_b.png"]
    manifest = json.loads((tmp_path / "figures.json").read_text())
    assert manifest["defect_map_a.png"]["kind"] == "defect_map"
    assert "Layer a" in manifest["defect_map_a.png"]["caption"]
    for f in figs:
        assert _png(f.path).std() > 0.02


def _frames_table(n_t: int = 3) -> pd.DataFrame:
    """frames.parquet as the workflow writes it: two layers on one surface, tiny numerical noise."""
    rows = []
    for t in range(n_t):
        for layer in ("apical", "basal"):
            rows.append({"t": t, "c": 0, "layer": layer, "surface": "inner", "area": 125535.38 - 2.1 * t,
                         "volume": 4162053.0 + 180 * t, "euler_characteristic": 2.0,
                         "H_mean": 0.010019 - 1e-6 * t, "K_mean": 1e-4, "H_fit_mean": 0.00997,
                         "thickness_mean": 10.84 - 0.001 * t, "thickness_median": 10.89,
                         "S_mean": 0.918, "S_median": 0.95, "n_defects": 4, "charge_sum": 2.004,
                         "qc_pass": True, "qc_flags": ""})
    return pd.DataFrame(rows)


def _axis(fig, title: str):
    return next(ax for ax in fig.axes if ax.get_title().startswith(title))


def test_frames_figure_reads_without_offsets(tmp_path):
    """Units on every y axis, no offset text, integer t ticks, S on [0, 1], noise looks flat."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    fig = frames_figure(_frames_table(), unit="um")
    FigureCanvasAgg(fig).draw()
    labels = {ax.get_title(): ax.get_ylabel() for ax in fig.axes if ax.get_title()}
    assert labels["wall thickness"] == "thickness [µm]"
    assert labels["mean curvature H"] == "H [1/µm]"
    assert labels["surface area"].startswith("area [") and labels["surface area"].endswith("µm²]")
    assert labels["enclosed volume"].endswith("µm³]")
    for ax in fig.axes:
        if ax.axison:
            assert ax.yaxis.get_offset_text().get_text() == "", ax.get_title()
            assert ax.xaxis.get_offset_text().get_text() == "", ax.get_title()
    ax_t = _axis(fig, "wall thickness")
    ticks = [tk for tk in ax_t.get_xticks() if ax_t.get_xlim()[0] <= tk <= ax_t.get_xlim()[1]]
    assert ticks == [0, 1, 2]
    assert _axis(fig, "nematic order").get_ylim() == (0.0, 1.0)
    for title, mean in (("mean curvature H", 0.010019), ("wall thickness", 10.84)):
        lo, hi = _axis(fig, title).get_ylim()
        assert hi - lo >= 0.099 * mean and lo < mean < hi, title  # spans at least ±5 % of the mean
    assert _axis(fig, "number of defects").get_ylim()[0] == 0
    # unit from the table's provenance
    fig = frames_figure(_frames_table(), unit="nm")
    assert _axis(fig, "wall thickness").get_ylabel() == "thickness [nm]"


def test_frames_figure_of_one_time_point_has_one_tick_and_short_reasons():
    """A single frame (the real stacks): one integer t tick per panel, not a crowd of fractions;
    a long QC reason is shortened to fit the figure."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    df = _frames_table(1)
    df.loc[0, ["qc_pass", "qc_flags"]] = [False, "no defect search: " + "a very long reason " * 30]
    fig = frames_figure(df)
    FigureCanvasAgg(fig).draw()
    for ax in fig.axes:
        if ax.axison and ax.get_xlabel():
            lo, hi = ax.get_xlim()
            assert [tk for tk in ax.get_xticks() if lo <= tk <= hi] == [0], ax.get_title()
    text = [t.get_text() for a in fig.axes for t in a.texts if "Flagged frames" in t.get_text()][0]
    assert max(len(line) for line in text.splitlines()) <= 190 and "(frames.parquet qc_flags)" in text


def test_frames_figure_marks_flagged_frames():
    df = _frames_table()
    bad = (df["t"] == 1) & (df["layer"] == "basal")
    df.loc[bad, ["charge_sum", "n_defects", "qc_pass", "qc_flags"]] = [1.5, 3, False, "Σ charge 1.50 ≠ χ 2"]
    fig = frames_figure(df)
    ax = _axis(fig, "Σ charge")
    crosses = [ln for ln in ax.get_lines() if ln.get_marker() == "x" and ln.get_color() == "red"]
    assert len(crosses) == 1
    np.testing.assert_allclose(crosses[0].get_xdata(), [1], atol=0.1)
    np.testing.assert_allclose(crosses[0].get_ydata(), [1.5])
    spans = [p for p in ax.patches if p.get_facecolor()[:3] == (1.0, 0.0, 0.0)]
    assert len(spans) == 1 and spans[0].get_x() < 1 < spans[0].get_x() + spans[0].get_width()
    text = " ".join(t.get_text() for a in fig.axes for t in a.texts)
    assert "t = 1, layer basal: Σ charge 1.50 ≠ χ 2" in text
    assert not [p for p in _axis(fig, "nematic order").patches if p.get_facecolor()[:3] == (1.0, 0.0, 0.0)
                if not p.get_x() < 1 < p.get_x() + p.get_width()]


def test_frames_figure_leaves_out_an_empty_frames_morphology():
    """A frame whose segmented channel looks empty meshes a noise speck: its area is not the
    object's, so it is not drawn (nor sets the panel's scale)."""
    df = _frames_table().assign(snr=8.0, closed=True, walls=pd.array([2] * 6, dtype="Int64"),
                                object_id=pd.array([0] * 6, dtype="Int64"))  # the dtypes of frames.parquet
    empty = df["t"] == 1
    df.loc[empty, ["area", "snr", "qc_pass", "qc_flags"]] = [12.5, 0.9, False, "the segmented channel looks empty"]
    fig = frames_figure(df)
    ax = _axis(fig, "surface area")
    drawn = np.concatenate([ln.get_ydata() for ln in ax.get_lines() if ln.get_marker() != "x"])
    assert ax.get_ylabel().startswith("area [10$^{3}$")  # drawn in 10³ µm²
    np.testing.assert_allclose(drawn[np.isfinite(drawn)], [125.53538, 125.53118])  # t 0 and 2 only
    assert ax.get_ylim()[0] > 100  # the speck's 12.5 µm² does not set the scale
    s_crosses = [ln for ln in _axis(fig, "nematic order").get_lines() if ln.get_marker() == "x"]
    assert not [x for ln in s_crosses for x in ln.get_xdata()]  # no ✕ at a value not drawn


def test_frames_figure_draws_a_line_per_object():
    """frames.parquet of two objects (mesh.keep: all): each object its own line, not a zigzag."""
    one = _frames_table()
    two = pd.concat([one.assign(object=0), one.assign(object=1, S_mean=0.5)], ignore_index=True)
    fig = frames_figure(two)
    lines = _axis(fig, "nematic order").get_lines()
    assert len(lines) == 8  # 2 layers x 2 objects x (mean, median)
    for ln in lines:  # every line runs over t once, at its object's constant value
        np.testing.assert_allclose(ln.get_xdata(), [0, 1, 2], atol=0.2)  # lines are dodged a little in t
        assert np.ptp(ln.get_ydata()) == 0
    assert sum(np.allclose(ln.get_ydata(), 0.5) for ln in lines) == 2
    legend = " ".join(t.get_text() for a in fig.axes for lg in [a.get_legend()] if lg for t in lg.get_texts())
    legend += " ".join(t.get_text() for lg in fig.legends for t in lg.get_texts())
    assert "object 1" in legend


def test_frames_figure_follows_objects_by_their_id_not_their_label():
    """Two objects whose area ranks swap at t = 1 (labels 0 and 1 swap): with ``object_id`` each
    line keeps one object's values (S 0.9 or 0.5 throughout), not a zigzag between them."""
    one = _frames_table()
    swap = one["t"] >= 1
    a = one.assign(object=np.where(swap, 1, 0), object_id=0, S_mean=0.9)
    b = one.assign(object=np.where(swap, 0, 1), object_id=1, S_mean=0.5)
    fig = frames_figure(pd.concat([a, b], ignore_index=True))
    solid = [ln for ln in _axis(fig, "nematic order").get_lines() if ln.get_linestyle() == "-"]
    assert len(solid) == 4 and all(np.ptp(ln.get_ydata()) == 0 for ln in solid)  # 2 layers × 2 objects


def test_frame_qc_without_qc_columns():
    df = _frames_table().drop(columns=["qc_pass", "qc_flags"])
    df.loc[1, "charge_sum"] = 1.5
    df.loc[4, "n_defects"] = 0
    qc = frame_qc(df)
    assert qc["qc_pass"].tolist() == [True, False, True, True, False, True]
    assert "Σ charge 1.50 ≠ χ 2" in qc.loc[1, "qc_flags"] and qc.loc[4, "qc_flags"] == "no defects"
    fig = frames_figure(df)
    strip = _axis(fig, "quality control")
    fails = [ln for ln in strip.get_lines() if ln.get_marker() == "X" and len(ln.get_xdata())]
    assert sorted(x for ln in fails for x in ln.get_xdata()) == [0, 2]


def test_defect_map_of_several_objects_centres_each_object():
    """Two objects' defects in one frame (an object column): each is placed about its own centre,
    not about a point between the objects."""
    u = np.array([[1.0, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]])
    a, b = np.array([0.0, 0, 0]), np.array([500.0, 0, 0])
    xyz = np.concatenate([a + 30 * u, b + 20 * u])
    df = pd.DataFrame({"t": 0, "c": 0, "object": np.repeat([0, 1], 6), "x": xyz[:, 0], "y": xyz[:, 1],
                       "z": xyz[:, 2], "charge": 0.5})
    lon, lat = defect_lonlat(df, {(0, 0): np.array([250.0, 0, 0])})  # the frame centroid is ignored
    np.testing.assert_allclose(lon[:6], lon[6:], atol=1e-9)
    np.testing.assert_allclose(lat[:6], lat[6:], atol=1e-9)
    np.testing.assert_allclose(lat[4:6], [90, -90], atol=1e-9)  # degrees
    # one defect per object: placed about each object's surface centroid (from its mesh), not itself
    one = df.iloc[[4, 6]]  # object 0's north pole, object 1's +x point
    lon, lat = defect_lonlat(one, {(0, 0): np.array([250.0, 0, 0]), (0, 0, 0): a, (0, 0, 1): b})
    np.testing.assert_allclose(lat, [90, 0], atol=1e-9)
    np.testing.assert_allclose(lon[1], 0, atol=1e-9)


def test_defect_map_places_defects_at_longitude_latitude():
    centre = np.array([10.0, -5.0, 3.0])
    lon, lat = np.radians([60.0, -150.0]), np.radians([-30.0, 45.0])
    u = np.stack([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)], axis=1)
    xyz = centre + 40.0 * u
    df = pd.DataFrame({"t": [0, 0], "c": 0, "layer": "a", "x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2],
                       "charge": [0.5, -0.5], "track_id": [0, 1]})
    got_lon, got_lat = defect_lonlat(df, {(0, 0): centre})
    np.testing.assert_allclose(got_lon, [60, -150], atol=1e-9)
    np.testing.assert_allclose(got_lat, [-30, 45], atol=1e-9)
    fig = defect_map_figure(df, "a", {(0, 0): centre})
    ax = fig.axes[0]
    assert ax.name == "mollweide"
    colls = [c for c in ax.collections if c.get_gid() == "defects"]
    pts = np.concatenate([np.asarray(c.get_offsets()) for c in colls])
    np.testing.assert_allclose(sorted(map(tuple, pts)), sorted(zip(lon, lat)), atol=1e-9)
    # diverging charge colours centred on 0: +1/2 red, -1/2 blue, at mirrored positions
    cols = {round(float(c.get_array()[0]), 1): c.to_rgba(c.get_array())[0][:3] for c in colls}
    assert cols[0.5][0] > cols[0.5][2] + 0.3 and cols[-0.5][2] > cols[-0.5][0] + 0.3
    norm = colls[0].norm
    assert norm(0.0) == pytest.approx(0.5) and norm(0.5) + norm(-0.5) == pytest.approx(1.0)


def test_curvature_colour_limits_are_symmetric_about_zero(demo):
    """An all-positive sphere: H limits ±m (m ≥ max H), so it is red, never half blue."""
    fr = load_frame(demo["frames"][0]["dir"])
    H = fr.surfaces["inner"].fields["H"]
    assert (H > 0).all()
    lo, hi = robust_limits(H, "H")
    assert lo == -hi and hi >= np.percentile(H, 99)
    lo_k, hi_k = robust_limits(fr.surfaces["inner"].fields["K"], "K")
    assert lo_k == -hi_k > -1
    fig = morphology_figure(fr.surfaces["inner"])
    clim = fig.axes[0].images[0].get_clim()
    assert clim[0] == -clim[1] and clim[1] > 0
    assert robust_limits(np.array([-3.0, 0.5]), "H") == (-3.0, 3.0)


def test_charge_text_and_captions():
    assert [charge_text(q) for q in (0.49, -0.52, 1.02, 0.1, -1.0, 1.5)] == ["+1/2", "-1/2", "+1", "0", "-1", "+3/2"]
    assert set(CAPTIONS) >= {"surface_intensity", "surface_order", "surface_defects", "distributions",
                             "spherical", "surface_H", "surface_K", "surface_thickness",
                             "morphology_map", "alignment", "tracks", "frames"}


# ------------------------------------------------------------------------------ CLI


def test_cli_list_and_render(demo, run_cli, tmp_path):
    d = demo["frames"][0]["dir"]
    code, out, _ = run_cli("render", d, "--list", "--layer", "a")
    assert code == 0
    assert out.split() == list(planned_figures(discover_frame(d), ["a"]))
    files = [d / "mesh.inner.ply", d / "layer_a.parquet", d / "order_a.parquet", d / "defects_a.parquet"]
    code, out, err = run_cli("render", *files, "-o", tmp_path, "--no-surfaces")
    assert code == 0, err
    written = sorted(p.name for p in tmp_path.glob("*.png"))
    assert written == ["distributions_a.png", "spherical_a.png"]
    code, out, err = run_cli("render", "--summary", demo["dataset_dir"] / "summary", "-o", tmp_path)
    assert code == 0 and (tmp_path / "tracks_a.png").exists()


def test_cli_errors(demo, run_cli, tmp_path):
    code, _, err = run_cli("render", tmp_path / "nothing", "-o", tmp_path)
    assert code == 2 and "does not exist" in err and "Traceback" not in err
    code, _, err = run_cli("render", demo["frames"][0]["dir"], "-o", tmp_path, "--layer", "zz")
    assert code == 2 and "layer(s) zz have no tables" in err
    code, _, err = run_cli("render", demo["frames"][0]["dir"])
    assert code == 2 and "-o OUTDIR" in err
    code, _, err = run_cli("render", "--summary", demo["frames"][0]["dir"], "-o", tmp_path)
    assert code == 2 and "no summary tables" in err


def test_warning_class_for_unreadable_table(demo, tmp_path):
    frame = tmp_path / "f"
    shutil.copytree(demo["frames"][0]["dir"], frame)
    (frame / "order_a.parquet").write_bytes(b"not parquet")
    with pytest.warns(NemoWarning, match="not a Parquet table"):
        fr = load_frame(frame)
    assert fr.layers["a"].order is None


def test_provenance_names_the_mesh(demo, tmp_path):
    """A partial table goes to the mesh its provenance names, not to the preferred inner one."""
    frame = tmp_path / "t0" / "c0"
    shutil.copytree(demo["frames"][0]["dir"], frame)
    sub = np.arange(0, 100)
    write_table(pd.DataFrame({"vertex": sub, "intensity": np.ones(100)}), frame / "layer_o.parquet",
                mesh=str(frame / "mesh.outer.ply"), mesh_to="mesh.inner.ply")
    write_table(pd.DataFrame({"vertex": sub, "intensity": np.ones(100)}), frame / "layer_p.parquet")
    fr = load_frame(frame)
    assert fr.layers["o"].surface == "outer" and "intensity (o)" in fr.surfaces["outer"].fields
    assert fr.layers["p"].surface == "inner"  # no provenance: first of inner, mesh, outer


def test_open_surface_render_draws_its_rim(tmp_path):
    """A ball cut by the top of the stack (border open): its rim is drawn in magenta; the
    closed (capped) surface has none."""
    from nemo.render import render_surface
    from nemo.surface import reconstruct

    z, y, x = np.mgrid[0:24, 0:40, 0:40].astype(np.float32)
    vol = 200.0 * (np.sqrt((x - 20) ** 2 + (y - 20) ** 2 + (z - 16) ** 2) < 12)
    counts = {}
    for border in ("open", "closed"):
        mesh = reconstruct(vol, (1.0, 1.0, 1.0), sigma=1.0, border=border)
        img = _png(render_surface(tmp_path / f"{border}.png", mesh, scalars=mesh.vertices[:, 2], label="z"))
        rgb = img[..., :3]
        counts[border] = int(((rgb[..., 0] > 0.8) & (rgb[..., 1] < 0.3) & (rgb[..., 2] > 0.8)).sum())
    assert counts["open"] > 500 and counts["closed"] == 0, counts
