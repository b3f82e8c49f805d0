"""napari layers, reader, plugin manifest and viewer for NEMO results.

The layer construction (coordinates x, y, z -> napari z, y, x; scales; colour ranges) is
tested without napari on the layer data tuples. The viewer tests need napari + PyQt6 and an X
server: they start their own Xvfb (Debian ``xvfb``) and are skipped when either is missing.
Offscreen Qt renders black here, hence the real (virtual) X server.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from nemo.errors import NemoError
from nemo.napari._reader import get_reader
from nemo.napari._sample import write_demo_results
from nemo.napari.layers import layer_data, lift, set_surface_field, to_napari
from nemo.render import robust_limits

MANIFEST = Path(__file__).resolve().parents[1] / "nemo" / "napari" / "napari.yaml"


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    return write_demo_results(tmp_path_factory.mktemp("results"), subdivisions=3, n_frames=3)


def _by_name(tuples):
    return {kw["name"]: (data, kw, kind) for data, kw, kind in tuples}


def _frame_mesh(surface_data, t: int | None) -> trimesh.Trimesh:
    """The napari-coordinate mesh of one time point of a (stacked) surface layer."""
    verts, faces = surface_data[0], surface_data[1]
    if t is None:
        return trimesh.Trimesh(verts, faces, process=False)
    sel = verts[:, 0] == t
    keep = sel[faces].all(axis=1)
    index = np.full(len(verts), -1)
    index[sel] = np.arange(sel.sum())
    return trimesh.Trimesh(verts[sel][:, 1:], index[faces[keep]], process=False)


# ------------------------------------------------------------------- layers without napari


def test_to_napari_swaps_axes():
    xyz = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    np.testing.assert_array_equal(to_napari(xyz), [[3, 2, 1], [6, 5, 4]])
    np.testing.assert_array_equal(to_napari(xyz, 2), [[2, 3, 2, 1], [2, 6, 5, 4]])


def test_layer_data_builds_every_layer(demo):
    layers = _by_name(layer_data(demo["dataset_dir"]))
    assert set(layers) == {
        "image c0", "surface inner", "surface outer", "directors (a)", "averaged directors (a)",
        "directors (b)", "averaged directors (b)", "defects (a)", "defects (b)",
    }
    img, kw, kind = layers["image c0"]
    assert kind == "image" and kw["scale"] == (1.0, *demo["spacing"])
    assert img.shape == (3, *demo["image_shape"])
    surf, kw, kind = layers["surface inner"]
    assert kind == "surface" and surf[0].shape == (3 * demo["n_vertices"], 4)
    assert kw["metadata"]["nemo_field"] == "intensity (a)" and kw["colormap"] == "gray"
    lo, hi = kw["contrast_limits"]
    vmin, vmax = demo["intensity_a"]
    assert vmin <= lo < hi <= vmax and (lo, hi) == robust_limits(surf[2])
    assert (hi - lo) > 0.9 * (vmax - vmin)
    assert not layers["surface outer"][1]["visible"]
    assert layers["defects (a)"][1]["visible"] and not layers["defects (b)"][1]["visible"]
    _, kw, _ = layers["defects (a)"]
    assert list(kw["features"]["label"]) == ["+1/2"] * 12
    assert kw["face_contrast_limits"] == (-1.0, 1.0)
    vec, kw, _ = layers["averaged directors (a)"]
    assert vec.shape[1:] == (2, 4) and kw["edge_contrast_limits"] == (0.0, 1.0)
    np.testing.assert_array_equal(vec[:, 1, 0], 0)  # vectors stay in their time point


def _lifted_off(points: np.ndarray, mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray]:
    """The surface points under lifted markers (closest points on ``mesh``) and their heights."""
    foot, dist, _ = trimesh.proximity.closest_point(mesh, points)
    return foot, dist


def test_defects_sit_on_the_surface_in_napari_coordinates(demo):
    layers = _by_name(layer_data(demo["dataset_dir"]))
    pts, kw, _ = layers["defects (a)"]
    surf = layers["surface inner"][0]
    lift = kw["metadata"]["nemo"]["lift"]
    assert lift == pytest.approx(0.6 * kw["size"])  # more than the marker radius
    centre = demo["centre"][::-1]
    for t, truth in enumerate(demo["frames"]):
        mine = pts[pts[:, 0] == t][:, 1:]
        mesh = _frame_mesh(surf, t)
        foot, height = _lifted_off(mine, mesh)
        np.testing.assert_allclose(foot, truth["defects"][:, ::-1], atol=0.01 * demo["radius"])  # (z, y, x)
        feats = kw["features"]
        np.testing.assert_allclose(np.column_stack([feats[k] for k in "xyz"])[pts[:, 0] == t], truth["defects"])
        np.testing.assert_allclose(height, lift, rtol=0.05)
        # outward: the marker is farther from the centre than the surface point under it
        out = np.linalg.norm(mine - centre, axis=1) - np.linalg.norm(foot - centre, axis=1)
        np.testing.assert_allclose(out, lift, rtol=0.05)
        # control: the same points left in (x, y, z) order are far off the surface
        _, wrong, _ = trimesh.proximity.closest_point(mesh, truth["defects"])
        assert wrong.max() > 1.0


def test_lift_moves_points_along_the_outward_normal():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=10.0)
    on = sphere.vertices[[0, 50, 400]]  # on the surface, at vertices
    between = trimesh.sample.sample_surface_even(sphere, 5, seed=1)[0]  # inside faces
    for xyz in (on, between):
        up = lift(sphere, xyz, 0.5)
        np.testing.assert_allclose(np.linalg.norm(up, axis=1), np.linalg.norm(xyz, axis=1) + 0.5, atol=2e-3)
        radial = xyz / np.linalg.norm(xyz, axis=1, keepdims=True)
        np.testing.assert_allclose(np.einsum("ij,ij->i", up - xyz, radial), 0.5, atol=2e-3)
    flipped = trimesh.Trimesh(sphere.vertices, sphere.faces[:, ::-1], process=False)  # inward normals
    assert (np.linalg.norm(lift(flipped, on, 0.5), axis=1) < 10.0).all()  # follows the mesh normals
    assert lift(sphere, np.empty((0, 3)), 0.5).shape == (0, 3)


def test_directors_are_tangent_and_centred(demo):
    layers = _by_name(layer_data(demo["dataset_dir"], t=0))
    vec = layers["averaged directors (a)"][0]
    mesh = _frame_mesh(layers["surface inner"][0], None)
    centre = demo["centre"][::-1]
    mid = vec[:, 0] + 0.5 * vec[:, 1]
    _, dist, _ = trimesh.proximity.closest_point(mesh, mid)
    assert dist.max() < 0.02 * demo["radius"]
    radial = (mid - centre) / np.linalg.norm(mid - centre, axis=1, keepdims=True)
    d = vec[:, 1] / np.linalg.norm(vec[:, 1], axis=1, keepdims=True)
    assert np.abs(np.einsum("ij,ij->i", radial, d)).max() < 1e-3  # (pole evaluated 1e-4 aside)
    length = np.linalg.norm(vec[:, 1], axis=1)
    spacing = np.sqrt(mesh.area / len(vec))  # thinned evenly: length ~ the glyph spacing
    assert 0.3 * spacing < length.mean() < 1.5 * spacing


def test_image_and_surface_share_world_coordinates(demo):
    """The image's bright shell (R + 2.5 µm) is found 2.5 µm outside the surface vertices."""
    layers = _by_name(layer_data(demo["dataset_dir"], t=1))
    img, kw, _ = layers["image c0"]
    img = np.asarray(img)
    scale = np.asarray(kw["scale"])
    verts = layers["surface inner"][0][0]
    outward = (verts - demo["centre"][::-1]) / demo["radius"]

    def sample(world):
        idx = np.rint(world / scale).astype(int)  # napari: data index = world / scale
        idx = np.clip(idx, 0, np.array(img.shape) - 1)
        return img[idx[:, 0], idx[:, 1], idx[:, 2]].astype(float)

    assert sample(verts + 2.5 * outward).mean() > 150
    assert sample(verts - 5.0 * outward).mean() < 20
    assert sample(verts[:, ::-1] + 2.5 * outward[:, ::-1]).mean() < 100  # control: x, z swapped


def test_one_time_point_and_errors(demo):
    layers = _by_name(layer_data(demo["dataset_dir"].parent, dataset="demo", t=2, layer="b"))
    assert layers["surface inner"][0][0].shape == (demo["n_vertices"], 3)
    assert layers["surface inner"][1]["metadata"]["nemo_field"] == "intensity (b)"
    assert layers["defects (b)"][1]["visible"] and not layers["defects (a)"][1]["visible"]
    foot, _ = _lifted_off(layers["defects (b)"][0], _frame_mesh(layers["surface inner"][0], None))
    np.testing.assert_allclose(foot, demo["frames"][2]["defects"][:, ::-1], atol=0.01 * demo["radius"])
    with pytest.raises(NemoError, match="time point t=7"):
        layer_data(demo["dataset_dir"], t=7)
    with pytest.raises(NemoError, match="channel c=3"):
        layer_data(demo["dataset_dir"], c=3)
    with pytest.raises(NemoError, match="layer 'zz' not found"):
        layer_data(demo["dataset_dir"], layer="zz")


def test_nemo_run_folder_and_missing_image(tmp_path):
    truth = write_demo_results(tmp_path / "run", subdivisions=3, layout="run", image=False)
    with pytest.warns(UserWarning, match="no image found"):
        layers = _by_name(layer_data(tmp_path / "run"))
    assert "image c0" not in layers
    assert set(layers) >= {"surface inner", "surface mesh", "defects (layer)", "averaged directors (layer)"}
    foot, _ = _lifted_off(layers["defects (layer)"][0], _frame_mesh(layers["surface inner"][0], None))
    np.testing.assert_allclose(foot, truth["frames"][0]["defects"][:, ::-1], atol=0.01 * truth["radius"])


def test_nan_field_is_displayable(demo):
    layers = _by_name(layer_data(demo["dataset_dir"], t=0))
    meta = layers["surface inner"][1]["metadata"]
    thick = meta["nemo_fields"]["thickness"]
    assert np.isnan(thick).any()  # kept in the metadata...

    class FakeSurface:  # set_surface_field only uses these attributes
        name = "surface inner"
        metadata = meta
        data = layers["surface inner"][0]
        colormap = None
        contrast_limits = None

    s = FakeSurface()
    set_surface_field(s, "thickness")
    assert np.isfinite(s.data[2]).all()  # ...but napari gets finite values
    assert s.colormap == "magma" and s.contrast_limits == robust_limits(thick, "thickness")
    with pytest.raises(NemoError, match="no field 'nope'"):
        set_surface_field(s, "nope")


def test_reader_accepts_results_folders_only(demo, tmp_path):
    assert callable(get_reader(str(demo["dataset_dir"])))
    assert callable(get_reader([str(demo["frames"][0]["dir"])]))
    assert get_reader(str(tmp_path)) is None
    assert get_reader(str(demo["image"])) is None
    reader = get_reader(str(demo["dataset_dir"]))
    assert {kw["name"] for _, kw, _ in reader(str(demo["dataset_dir"]))} >= {"surface inner", "defects (a)"}


def test_manifest_is_valid():
    npe2 = pytest.importorskip("npe2")
    m = npe2.PluginManifest.from_file(MANIFEST)
    assert m.name == "nemo-nematics"
    assert [r.command for r in m.contributions.readers] == ["nemo-nematics.get_reader"]
    assert {s.key for s in m.contributions.sample_data} == {"demo", "vesicle"}
    import importlib

    for cmd in m.contributions.commands:  # every python_name resolves
        module, _, attr = cmd.python_name.partition(":")
        assert callable(getattr(importlib.import_module(module), attr))


# ------------------------------------------------------------------- viewer under Xvfb

_XVFB: dict = {}

#: Started in a subprocess before any viewer: Qt aborts its process (no Python exception) when
#: its platform plugin cannot load, e.g. Xvfb installed without Qt's xcb libraries.
_QT_PROBE = """\
from PyQt6.QtWidgets import QApplication
from PyQt6.QtOpenGLWidgets import QOpenGLWidget
app = QApplication([])
w = QOpenGLWidget()
w.show()
app.processEvents()
w.close()
"""


def _start_xvfb() -> tuple[subprocess.Popen, str]:
    """Start an Xvfb on a free display; return the process and ':N'."""
    r, w = os.pipe()
    proc = subprocess.Popen(
        # -terminate: the server exits when its last client (this process's Qt) disconnects
        ["Xvfb", "-displayfd", str(w), "-screen", "0", "1280x1024x24", "-nolisten", "tcp", "-terminate"],
        pass_fds=(w,), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )
    os.close(w)
    with os.fdopen(r) as f:
        number = f.readline().strip()
    if not number:
        proc.kill()
        proc.wait()
        pytest.skip("Xvfb did not start")
    return proc, f":{number}"


def _qt_error(platform: str = "xcb", timeout: float = 120.0) -> str | None:
    """Why Qt cannot open a window under Xvfb (None: it can), tried in a subprocess.

    The probe has an Xvfb of its own: with ``-terminate`` a server ends when its first client
    leaves, so the viewer tests get a fresh one.
    """
    proc, display = _start_xvfb()
    env = {**os.environ, "DISPLAY": display, "QT_QPA_PLATFORM": platform}
    try:
        done = subprocess.run([sys.executable, "-c", _QT_PROBE], env=env, capture_output=True, text=True,
                              timeout=timeout, check=False)
    except subprocess.TimeoutExpired:
        return f"Qt did not start within {timeout:.0f} s"
    finally:
        proc.kill()
        proc.wait()
    if done.returncode == 0:
        return None
    lines = [line for line in done.stderr.splitlines() if line.strip()] or ["no message"]
    return f"exit status {done.returncode}: {lines[0][:200]}"


def _display() -> str:
    """The Xvfb display of the viewer tests, started once per process."""
    if "display" not in _XVFB:
        proc, _XVFB["display"] = _start_xvfb()
        # Xvfb outlives the tests (Qt keeps its connection until exit) and ends with -terminate;
        # mark it reaped so Popen.__del__ does not warn at interpreter exit
        proc.returncode = 0
    return _XVFB["display"]


@pytest.fixture(scope="module")
def viewer_env():
    pytest.importorskip("napari")
    pytest.importorskip("PyQt6")
    if shutil.which("Xvfb") is None:
        pytest.skip("Xvfb not installed (Debian: apt-get install xvfb xauth)")
    if "qt_error" not in _XVFB:
        _XVFB["qt_error"] = _qt_error()
    if _XVFB["qt_error"]:
        pytest.skip(f"Qt cannot open a window under Xvfb ({_XVFB['qt_error']}); missing system "
                    "libraries? see the README's list (Debian: libxcb-cursor0 libxkbcommon-x11-0 ...)")
    old = {k: os.environ.get(k) for k in ("DISPLAY", "QT_QPA_PLATFORM")}
    os.environ["DISPLAY"] = _display()
    os.environ["QT_QPA_PLATFORM"] = "xcb"
    yield
    for k, v in old.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v


def test_qt_probe_reports_a_broken_qt():
    """The probe says why Qt cannot start (here: an unknown platform plugin) instead of aborting."""
    pytest.importorskip("PyQt6")
    if shutil.which("Xvfb") is None:
        pytest.skip("Xvfb not installed")
    error = _qt_error(platform="nonexistent")
    assert error is not None and "nonexistent" in error


def _not_blank(img: np.ndarray) -> None:
    rgb = img[..., :3].astype(np.int64)
    assert rgb.std() > 10
    assert len(np.unique(rgb[..., 0] * 65536 + rgb[..., 1] * 256 + rgb[..., 2])) > 50


def test_viewer_layers_screenshot_and_time(viewer_env, demo):
    import napari

    from nemo.napari.layers import add_nemo_layers, field_selector

    viewer = napari.Viewer(show=True)
    try:
        added = add_nemo_layers(viewer, demo["dataset_dir"], layer="a")
        widget = field_selector(viewer)
        viewer.window.add_dock_widget(widget, name="NEMO field")
        assert set(added) >= {"image c0", "surface inner", "averaged directors (a)", "defects (a)"}
        assert viewer.dims.ndisplay == 3 and viewer.dims.axis_labels == ("t", "z", "y", "x")
        assert viewer.dims.nsteps[0] == 3
        assert tuple(viewer.layers["image c0"].scale) == (1.0, *demo["spacing"])
        surf = viewer.layers["surface inner"]
        vmin, vmax = demo["intensity_a"]
        lo, hi = surf.contrast_limits
        assert vmin <= lo < hi <= vmax and surf.colormap.name == "gray"
        pts = viewer.layers["defects (a)"]
        assert pts.face_colormap.name == "bwr" and tuple(pts.face_contrast_limits) == (-1, 1)
        # the points layer in world coordinates sits on the surface layer (lifted by its radius+)
        mesh = _frame_mesh((surf.data[0], surf.data[1]), 0)
        world = np.array([pts.data_to_world(p) for p in pts.data[pts.data[:, 0] == 0]])[:, 1:]
        _, dist = _lifted_off(world, mesh)
        np.testing.assert_allclose(dist, pts.metadata["nemo"]["lift"], rtol=0.05)
        assert (dist > 0.5 * pts.size[0]).all()
        shot0 = viewer.screenshot(canvas_only=True)
        _not_blank(shot0)
        viewer.dims.set_current_step(0, 2)
        shot2 = viewer.screenshot(canvas_only=True)
        _not_blank(shot2)
        assert np.abs(shot2.astype(float) - shot0.astype(float)).mean() > 0.1  # defects moved
        # the field selector recolours the surface
        surface_box, field_box = widget[0], widget[1]
        assert surface_box.value == "surface inner"
        assert "thickness" in field_box.choices and "c (a-b)" in field_box.choices
        field_box.value = "c (a-b)"
        assert surf.metadata["nemo_field"] == "c (a-b)"
        assert tuple(surf.contrast_limits) == (-1.0, 1.0) and surf.colormap.name == "coolwarm"
        assert "alignment c" in widget[2].value
        field_box.value = "H"
        assert surf.colormap.name == "RdBu_r"
        np.testing.assert_allclose(surf.contrast_limits, robust_limits(surf.metadata["nemo_fields"]["H"], "H"))
        _not_blank(viewer.screenshot(canvas_only=True))
    finally:
        viewer.close()


def test_plugin_reader_and_sample(viewer_env, demo):
    import napari
    import npe2

    pm = npe2.PluginManager.instance()
    if "nemo-nematics" not in pm._manifests:  # entry point not installed: register the file
        pm.register(npe2.PluginManifest.from_file(MANIFEST))
    viewer = napari.Viewer(show=True)
    try:
        viewer.open(str(demo["dataset_dir"]), plugin="nemo-nematics")
        assert {"surface inner", "defects (a)", "image c0"} <= {lay.name for lay in viewer.layers}
        viewer.layers.clear()
        viewer.open_sample("nemo-nematics", "demo")
        assert "surface inner" in [lay.name for lay in viewer.layers]
        viewer.dims.ndisplay = 3
        _not_blank(viewer.screenshot(canvas_only=True))
    finally:
        viewer.close()


def test_cli_view_screenshot(viewer_env, demo, run_cli, tmp_path):
    out = tmp_path / "view.png"
    code, _, err = run_cli("view", demo["dataset_dir"], "--t", "1", "--layer", "b", "--screenshot", out)
    assert code == 0, err
    from matplotlib.image import imread

    _not_blank((imread(out) * 255).astype(np.uint8))
    code, _, err = run_cli("view", demo["dataset_dir"], "--c", "4")
    assert code == 2 and "channel c=4" in err


def test_cli_view_without_napari(demo, run_cli, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "napari", None)  # import napari -> ImportError
    code, _, err = run_cli("view", demo["dataset_dir"])
    assert code == 2 and "pip install 'nemo-nematics[napari]'" in err and "Traceback" not in err
