"""Synthetic vesicle: analytic director field, fibres, rasterisation, truth, CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy import ndimage
from scipy.spatial.transform import Rotation

from nemo.errors import NemoError, NemoWarning
from nemo.geometry import axis_frames
from nemo.io import read_info, read_stack
from nemo.synthetic import (
    PRESETS,
    check_defects,
    director_field,
    nematic_angle,
    parse_defects,
    preset_defects,
    projection_pole,
    read_truth,
    trace_fibres,
    truth_directors,
    truth_path,
    vesicle,
    write_vesicle,
)

SMALL = dict(radius=25.0, fibre_spacing=3.0, fibre_length=20.0, shell_thickness=8.0)


def _random_unit(rng, n):
    p = rng.normal(size=(n, 3))
    return p / np.linalg.norm(p, axis=1, keepdims=True)


def _tangent_basis(c):
    t1 = np.cross(c, [1.0, 0, 0] if abs(c[0]) < 0.9 else [0, 1.0, 0])
    t1 /= np.linalg.norm(t1)
    return t1, np.cross(c, t1)


def _loop_charge(centre, dirs, charges, rho=0.03, n=600, **kw):
    """Charge enclosed by a counter-clockwise loop of angular radius rho around ``centre``:
    3-D winding of the director (head-tail aligned) + enclosed Gaussian curvature / 2 pi."""
    c = np.asarray(centre, float) / np.linalg.norm(centre)
    t1, t2 = _tangent_basis(c)
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    p = np.cos(rho) * c + np.sin(rho) * (np.cos(a)[:, None] * t1 + np.sin(a)[:, None] * t2)
    nn = director_field(p, dirs, charges, **kw)
    total = 0.0
    for i in range(n):  # small fixed loop in a test, not a hot path
        j = (i + 1) % n
        if nn[i] @ nn[j] < 0:
            nn[j] = -nn[j]
        total += np.arctan2(np.cross(nn[i], nn[j]) @ p[i], nn[i] @ nn[j])
    # 2 pi (1 - cos rho) is the integral of K over the spherical cap on the unit sphere
    return total / (2 * np.pi) + (1 - np.cos(rho))


def _random_defect_set(rng, charges):
    while True:
        d = _random_unit(rng, len(charges))
        cos = d @ d.T
        np.fill_diagonal(cos, -1)
        if cos.max() < np.cos(0.5):  # well separated
            return d, np.asarray(charges, float)


# ---------------------------------------------------------------------------------------------
# defects and the analytic field
# ---------------------------------------------------------------------------------------------
def test_charges_must_sum_to_two():
    with pytest.raises(NemoError, match="sum to 1.5"):
        check_defects(np.eye(3), [0.5, 0.5, 0.5])
    with pytest.raises(NemoError, match="multiples of 1/2"):
        check_defects(np.eye(3)[:2], [0.7, 1.3])
    with pytest.raises(NemoError, match="same position"):
        check_defects([[0, 0, 1], [0, 0, 2]], [1, 1])
    with pytest.raises(NemoError, match="sum to"):
        director_field(np.eye(3), np.eye(3), [0.5, 0.5, 0.5])
    with pytest.raises(NemoError, match="sum to"):
        vesicle(radius=10, defects=np.eye(3)[:2], charges=[0.5, 0.5])
    for name, (d, m) in PRESETS.items():
        assert m.sum() == pytest.approx(2.0), name
        check_defects(d, m)


def test_parse_defects():
    d, m = parse_defects("0,0,2:-1/2; 1,0,0:0.5;0,1,0:1/2;-1,0,0:.5;0,-1,0:0.5;0,0,-1:0.5")
    assert m.tolist() == [-0.5, 0.5, 0.5, 0.5, 0.5, 0.5]
    np.testing.assert_allclose(d[0], [0, 0, 1])
    with pytest.raises(NemoError, match="x,y,z:charge"):
        parse_defects("1,0,0;0,1,0")
    with pytest.raises(NemoError, match="sum to"):
        parse_defects("1,0,0:1;0,1,0:1/2")


@pytest.mark.parametrize("name", list(PRESETS))
def test_director_unit_and_tangent(name, rng):
    d, m = preset_defects(name)
    d = d @ Rotation.random(random_state=3).as_matrix().T
    p = _random_unit(rng, 5000)
    n = director_field(p, d, m)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-12)
    assert np.abs(np.einsum("ij,ij->i", n, p)).max() < 1e-12
    # scaling the points does not matter (directions from the centre)
    np.testing.assert_allclose(director_field(7.0 * p, d, m), n, atol=1e-12)


@pytest.mark.parametrize(
    "charges",
    [[0.5] * 4, [0.5] * 5 + [-0.5], [1.0, 1.0], [1.0, 0.5, 0.5], [0.5] * 6 + [-0.5] * 2, [1.5, 0.5]],
)
def test_winding_around_each_defect(charges, rng):
    d, m = _random_defect_set(rng, charges)
    got = [_loop_charge(d[k], d, m) for k in range(len(d))]
    np.testing.assert_allclose(got, m, atol=2e-3)
    # a loop that encloses no defect has charge 0, including around the projection pole
    pole = projection_pole(d)
    assert _loop_charge(pole, d, m, rho=0.2) == pytest.approx(0.0, abs=2e-3)
    # the orthogonal field (phase pi/2) has the same defects
    np.testing.assert_allclose([_loop_charge(d[k], d, m, phase=np.pi / 2) for k in range(len(d))],
                               m, atol=2e-3)


def test_tetrahedron_winding_and_pole():
    d, m = preset_defects("tetrahedron")
    np.testing.assert_allclose([_loop_charge(x, d, m) for x in d], 0.5, atol=2e-3)
    pole = projection_pole(d)
    # farthest point from a regular tetrahedron's vertices: the antipode of a vertex
    assert np.max(d @ pole) == pytest.approx(1 / 3, abs=1e-6)


def test_field_smooth_away_from_defects(rng):
    """No jumps anywhere away from defects: at the projection pole, across the chart seam."""
    d, m = preset_defects("five-one")
    d = d @ Rotation.random(random_state=5).as_matrix().T
    pole = projection_pole(d)
    t1, t2 = _tangent_basis(pole)
    # points around the pole (down to 1e-9 rad) and everywhere else
    rho = np.concatenate([np.geomspace(1e-9, 0.8, 2000), np.arccos(rng.uniform(-1, 1, 3000))])
    a = rng.uniform(0, 2 * np.pi, len(rho))
    p = np.cos(rho)[:, None] * pole + np.sin(rho)[:, None] * (
        np.cos(a)[:, None] * t1 + np.sin(a)[:, None] * t2)
    p = p[(p @ d.T).max(axis=1) < np.cos(0.1)]  # >= 0.1 rad from any defect
    step = _random_unit(rng, len(p))
    step -= np.einsum("ij,ij->i", step, p)[:, None] * p
    step /= np.linalg.norm(step, axis=1, keepdims=True)
    q = p + 1e-5 * step
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    n1 = director_field(p, d, m)
    n2 = director_field(q, d, m)
    angle = np.arccos(np.clip(np.abs(np.einsum("ij,ij->i", n1, n2)), 0, 1))
    # field gradient ~ 1/(distance to a defect) <= 10 per radian: change <= ~1e-4 rad per 1e-5 rad
    assert angle.max() < 3e-4
    # the exact pole is evaluated (no NaN) and continuous with its neighbourhood
    n_pole = director_field(np.vstack([pole, pole + 1e-7 * t1]), d, m)
    assert np.all(np.isfinite(n_pole)) and abs(n_pole[0] @ n_pole[1]) > 1 - 1e-10


def test_projection_pole_only_changes_a_global_phase(rng):
    """The field is the direction field of prod (w - w_k)^(-2 m_k) dw^2, unique up to a constant:
    another projection pole rotates every director by the same angle in its tangent plane."""
    d, m = preset_defects("tetrahedron")
    p = _random_unit(rng, 3000)
    p = p[(p @ d.T).max(axis=1) < np.cos(0.05)]
    other_pole = np.array([0.3, -0.8, 0.5])
    th0 = nematic_angle(p, d, m)
    th1 = nematic_angle(p, d, m, pole=other_pole)
    diff = np.mod(th1 - th0, np.pi)
    circ = np.angle(np.mean(np.exp(2j * diff))) / 2  # nematic circular mean
    dev = np.abs(np.angle(np.exp(2j * (diff - circ)))) / 2
    assert dev.max() < 1e-8
    # and phase shifts the angle by exactly that constant
    th2 = nematic_angle(p, d, m, phase=0.3)
    np.testing.assert_allclose(np.cos(2 * (th2 - th0)), np.cos(0.6), atol=1e-9)


def test_nematic_angle_basis(rng):
    d, m = preset_defects("tetrahedron")
    p = _random_unit(rng, 500)
    n = director_field(p, d, m)
    # an explicit basis: t1 = N x z^, t2 = N x t1
    t1 = np.cross(p, [0, 0, 1.0])
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(p, t1)
    th = nematic_angle(p, d, m, t1, t2)
    rebuilt = np.cos(th)[:, None] * t1 + np.sin(th)[:, None] * t2
    assert np.all(np.abs(np.einsum("ij,ij->i", rebuilt, n)) > 1 - 1e-12)
    assert th.min() >= 0 and th.max() < np.pi
    # the documented default basis is NEMO's one axis construction, nemo.geometry.axis_frames,
    # including near N ∥ x^ where the x^/y^ switch happens (N = (0.93, 0.3, 0.21): once 123° vs 86°)
    p = np.vstack([p, [[0.93, 0.3, 0.21]], [[1.0, 0.0, 0.0]], [[-0.95, 0.0, 0.31]]])
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    n = director_field(p, d, m)
    t1, t2 = axis_frames(p)
    th = nematic_angle(p, d, m)
    rebuilt = np.cos(th)[:, None] * t1 + np.sin(th)[:, None] * t2
    assert np.all(np.abs(np.einsum("ij,ij->i", rebuilt, n)) > 1 - 1e-12)


def test_fibres_follow_the_field():
    d, m = preset_defects("tetrahedron")
    pts, tan = trace_fibres(d, m, n_seeds=200, length=0.6, step_size=0.01, rng=1)
    np.testing.assert_allclose(np.linalg.norm(pts, axis=1), 1.0, atol=1e-12)
    # each step's chord is along the director at the chord's midpoint (RK2 on the sphere)
    np.testing.assert_allclose(np.abs(np.einsum("ij,ij->i", director_field(pts[:200], d, m), tan[:200])), 1.0)
    pts, tan = pts[200:], tan[200:]  # after the seeds
    mid = pts - 0.5 * 0.01 * tan
    mid /= np.linalg.norm(mid, axis=1, keepdims=True)
    dots = np.abs(np.einsum("ij,ij->i", director_field(mid, d, m), tan))
    assert np.median(dots) > 1 - 1e-8 and np.percentile(dots, 1) > 1 - 1e-6
    # bidirectional: about 200 fibres x (1 + 2 x 30 steps) points, fewer only at defect cores
    assert 0.9 * 200 * 60 < len(pts) <= 200 * 60


# ---------------------------------------------------------------------------------------------
# images
# ---------------------------------------------------------------------------------------------
def _physical_radius(shape, spacing, centre):
    z, y, x = np.meshgrid(*(np.arange(n) * s for n, s in zip(shape, spacing)), indexing="ij")
    return np.sqrt((x - centre[0]) ** 2 + (y - centre[1]) ** 2 + (z - centre[2]) ** 2)


@pytest.mark.parametrize("spacing", [(1.0, 1.0, 1.0), (2.0, 1.0, 1.0), (1.5, 0.8, 1.0)])
def test_fibres_lie_on_the_layer_radius(spacing):
    data, truth = vesicle(**SMALL, spacing=spacing, background=0.0, layer_depth=3.0)
    assert data.dtype == np.uint8 and data.shape[0] == 1 and data.shape[2] == 1
    vol = data[0, :, 0].astype(float)
    r = _physical_radius(vol.shape, spacing, truth["centre"])
    w = vol / vol.sum()
    mean_r = (w * r).sum()
    # blurred thin spherical shell at a: mean radius a + sigma^2 / a (+ discretisation)
    assert mean_r == pytest.approx(28.0 + 1.0 / 28.0, abs=0.1)
    assert np.sqrt((w * (r - mean_r) ** 2).sum()) < 1.3  # ~ blur sigma = 1 µm
    assert truth["layers"][0]["radius"] == 28.0


@pytest.mark.parametrize("spacing", [(1.0, 1.0, 1.0), (2.0, 1.0, 1.0)])
def test_shell_edges_at_physical_radius(spacing):
    """Half the shell background is reached exactly at R and R + shell, along every axis."""
    data, truth = vesicle(**SMALL, spacing=spacing, fibre_intensity=0.0, background=0.5)
    vol = data[0, :, 0].astype(float)
    half = 0.5 * 0.5 * 255
    c = np.asarray(truth["centre"])
    rs = np.arange(15.0, 40.0, 0.01)
    for u in [(1, 0, 0), (0, 1, 0), (0, 0, 1), (0.6, 0, 0.8), (-0.48, 0.6, -0.64)]:
        xyz = c + rs[:, None] * np.asarray(u)
        idx = (xyz[:, ::-1] / np.asarray(spacing)).T
        prof = ndimage.map_coordinates(vol, idx, order=3)
        above = prof >= half
        r_in = rs[np.argmax(above)]
        r_out = rs[len(rs) - 1 - np.argmax(above[::-1])]
        assert r_in == pytest.approx(25.0, abs=0.06), u
        assert r_out == pytest.approx(33.0, abs=0.06), u


def _line_directions(vol, spacing):
    """Per voxel the direction of least intensity variation (3-D gradient structure tensor)."""
    g = np.gradient(ndimage.gaussian_filter(vol, 0.7), *spacing)
    s = np.empty(vol.shape + (3, 3))
    for i in range(3):
        for j in range(i, 3):
            s[..., i, j] = s[..., j, i] = ndimage.gaussian_filter(g[i] * g[j], 1.5)
    _, vec = np.linalg.eigh(s)
    return vec[..., :, 0][..., ::-1]  # (z, y, x) components -> (x, y, z)


def test_rasterised_fibres_follow_their_fields():
    """Two layers in two channels with orthogonal fields: each channel's stripes follow its own
    analytic field (and so are orthogonal to the other layer's)."""
    data, truth = vesicle(
        radius=30.0, fibre_spacing=3.0, fibre_length=20.0, shell_thickness=10.0, background=0.0,
        layer_depth=3.0, second_layer_depth=7.0, second_layer_channel=1, seed=2,
    )
    assert data.shape[2] == 2
    sp = truth["spacing"]
    for layer in (0, 1):
        lay = truth["layers"][layer]
        vol = data[0, :, lay["channel"]].astype(float)
        line = _line_directions(vol, sp)
        r = _physical_radius(vol.shape, sp, truth["centre"])
        sel = (np.abs(r - lay["radius"]) < 0.7) & (vol > 0.5 * vol.max())
        z, y, x = np.nonzero(sel)
        xyz = np.column_stack([x * sp[2], y * sp[1], z * sp[0]])
        d = np.asarray(lay["defect_dirs"])
        u = (xyz - truth["centre"]) / lay["radius"]
        far = (u @ d.T).max(axis=1) < np.cos(4.0 / lay["radius"])
        own = np.abs(np.einsum("ij,ij->i", line[sel][far], truth_directors(truth, xyz[far], layer=layer)))
        other = np.abs(np.einsum("ij,ij->i", line[sel][far], truth_directors(truth, xyz[far], layer=1 - layer)))
        assert far.sum() > 1000
        assert np.median(own) > 0.95, layer
        assert np.median(other) < 0.3, layer


def test_second_layer_is_orthogonal(rng):
    _, truth = vesicle(**SMALL, second_layer_depth=6.0, second_layer_rotation=90.0)
    assert [lay["depth"] for lay in truth["layers"]] == [3.0, 6.0]
    assert [lay["channel"] for lay in truth["layers"]] == [0, 0]
    p = truth["centre"] + 27 * _random_unit(rng, 2000)
    dots = np.einsum("ij,ij->i", truth_directors(truth, p, layer=0), truth_directors(truth, p, layer=1))
    assert np.abs(dots).max() < 1e-9
    # parallel second layer
    _, truth = vesicle(**SMALL, second_layer_depth=6.0, second_layer_rotation=0.0)
    dots = np.einsum("ij,ij->i", truth_directors(truth, p, layer=0), truth_directors(truth, p, layer=1))
    assert np.abs(dots).min() > 1 - 1e-9


def test_second_layer_own_defects():
    d, m = preset_defects("two-plus-one")
    data, truth = vesicle(**SMALL, second_layer_depth=6.0, second_layer_defects=d,
                          second_layer_charges=m, second_layer_channel=1)
    assert data.shape[2] == 2
    charges = {(r["layer"], r["charge"]) for r in truth["defects"]}
    assert charges == {(0, 0.5), (1, 1.0)}
    assert data[0, :, 1].max() > 100 and data[0, :, 0].max() > 100


def test_moving_defects_rotate_the_image_and_truth():
    """A 90° turn about z maps the voxel grid onto itself: frame 1 must be frame 0 turned."""
    data, truth = vesicle(**SMALL, frames=3, frame_rotation=90.0, frame_axis=(0, 0, 1))
    f0, f1 = data[0, :, 0].astype(int), data[1, :, 0].astype(int)
    assert np.abs(f0 - f1).max() > 100  # the texture did move
    # frame1 at (x, y) = frame0 at R^-1 (x, y) = (y, -x): frame1[z, r, c] = frame0[z, n-1-c, r]
    turned = np.rot90(f0, k=-1, axes=(1, 2))
    assert np.abs(turned - f1).max() <= 1
    # truth: each defect turned by t x 90° about z through the centre
    c = np.asarray(truth["centre"])
    for t in (1, 2):
        g = Rotation.from_rotvec([0, 0, np.deg2rad(90.0 * t)]).as_matrix()
        p0 = np.array([[r["x"], r["y"], r["z"]] for r in truth["defects"] if r["t"] == 0])
        pt = np.array([[r["x"], r["y"], r["z"]] for r in truth["defects"] if r["t"] == t])
        np.testing.assert_allclose(pt - c, (p0 - c) @ g.T, atol=1e-9)
        np.testing.assert_allclose(np.linalg.norm(pt - c, axis=1), 25.0)
    # defects move along a generic axis too, by the given angle
    _, truth = vesicle(**SMALL, frames=2, frame_rotation=10.0, frame_axis=(1, 2, 3))
    u0 = np.array([[r["ux"], r["uy"], r["uz"]] for r in truth["defects"] if r["t"] == 0])
    u1 = np.array([[r["ux"], r["uy"], r["uz"]] for r in truth["defects"] if r["t"] == 1])
    a = np.array([1, 2, 3]) / np.sqrt(14)
    perp0 = u0 - (u0 @ a)[:, None] * a
    perp1 = u1 - (u1 @ a)[:, None] * a
    ang = np.arctan2(np.einsum("ij,ij->i", np.cross(perp0, perp1), np.tile(a, (4, 1))),
                     np.einsum("ij,ij->i", perp0, perp1))
    np.testing.assert_allclose(np.rad2deg(ang), 10.0, atol=1e-9)


def test_seed_reproducible_and_noise():
    a, ta = vesicle(**SMALL, noise=5.0, seed=7)
    b, tb = vesicle(**SMALL, noise=5.0, seed=7)
    c, _ = vesicle(**SMALL, noise=5.0, seed=8)
    assert np.array_equal(a, b) and ta == tb
    assert not np.array_equal(a, c)
    clean, _ = vesicle(**SMALL, noise=0.0, seed=7)
    resid = a.astype(float) - clean
    unclipped = (clean > 30) & (clean < 220)
    assert resid[unclipped].std() == pytest.approx(5.0, rel=0.05)


def test_rotate_random_moves_defects():
    _, t0 = vesicle(**SMALL)
    _, t1 = vesicle(**SMALL, rotate=11)
    u0 = np.array([[r["ux"], r["uy"], r["uz"]] for r in t0["defects"]])
    u1 = np.array([[r["ux"], r["uy"], r["uz"]] for r in t1["defects"]])
    np.testing.assert_allclose(u1, u0 @ Rotation.random(random_state=11).as_matrix().T, atol=1e-12)


def test_volume_must_fit():
    with pytest.raises(NemoError, match="needs"):
        vesicle(size=(400, 450, 450))
    with pytest.warns(NemoWarning, match="outside the 8 µm background shell"):
        vesicle(**SMALL, layer_depth=9.0)


@pytest.mark.slow
def test_paper_default():
    """The default is the paper's vesicle: R = 200 µm, 1 µm voxels, 450^3, 4 x +1/2 tetrahedron."""
    data, truth = vesicle()
    assert data.shape == (1, 450, 1, 450, 450) and data.dtype == np.uint8
    assert truth["radius"] == 200.0 and truth["spacing"] == [1.0, 1.0, 1.0]
    np.testing.assert_allclose(truth["centre"], 224.5)
    u = np.array([[r["ux"], r["uy"], r["uz"]] for r in truth["defects"]])
    cos = u @ u.T
    np.testing.assert_allclose(cos[~np.eye(4, dtype=bool)], -1 / 3, atol=1e-12)  # regular tetrahedron
    assert [r["charge"] for r in truth["defects"]] == [0.5] * 4
    assert 0 <= truth["layers"][0]["depth"] <= 5
    vol = data[0, :, 0]
    # along +x from the centre (r = index - 0.5): empty inside, shell background (+ fibres) for
    # R + 2.5 sigma <= r <= R + shell - 2.5 sigma, empty outside
    line = vol[224, 224, 224:]
    assert line[:190].max() == 0 and line[215:].max() == 0 and line[203:208].min() >= 0.25 * 255 - 1


def test_write_truth_round_trip_and_read_frames(tmp_path):
    kw = dict(**SMALL, spacing=(2.0, 1.0, 1.0), frames=2, frame_rotation=20.0, channels=3,
              second_layer_depth=6.0, second_layer_channel=1, seed=3)
    data, truth = vesicle(**kw)
    path = tmp_path / "vesicle.tif"
    written = write_vesicle(path, **kw)
    assert truth_path(path) == tmp_path / "vesicle.truth.json"
    loaded = json.loads((tmp_path / "vesicle.truth.json").read_text())
    assert loaded == written == read_truth(path)
    written.pop("image")
    assert written == json.loads(json.dumps(truth))
    info = read_info(path)
    assert info.shape == {"T": 2, "C": 3, "Z": data.shape[1], "Y": data.shape[3], "X": data.shape[4]}
    assert info.spacing == pytest.approx((2.0, 1.0, 1.0)) and info.unit == "um"
    for t in range(2):
        for c in range(3):
            stack, _ = read_stack(path, t=t, c=c)
            assert np.array_equal(stack, data[t, :, c])
    assert not np.array_equal(data[0, :, 0], data[1, :, 0])
    assert not np.array_equal(data[0, :, 0], data[0, :, 1])
    # channel 2 holds no fibres: only the shell background
    assert data[0, :, 2].max() == round(0.25 * 255)
    # truth content
    assert loaded["radius"] == 25.0 and loaded["unit"] == "um" and loaded["spacing"] == [2.0, 1.0, 1.0]
    assert [(lay["depth"], lay["radius"], lay["channel"]) for lay in loaded["layers"]] == [
        (3.0, 28.0, 0), (6.0, 31.0, 1)]
    recs = loaded["defects"]
    assert len(recs) == 2 * 2 * 4 and {r["charge"] for r in recs} == {0.5}
    c = np.asarray(loaded["centre"])
    for r in recs:
        assert np.linalg.norm([r["x"] - c[0], r["y"] - c[1], r["z"] - c[2]]) == pytest.approx(25.0)
        rl = loaded["layers"][r["layer"]]["radius"]
        assert np.linalg.norm([r["x_layer"] - c[0], r["y_layer"] - c[1], r["z_layer"] - c[2]]) == pytest.approx(rl)
    np.testing.assert_allclose(c, [(n - 1) / 2 * s for n, s in zip(
        (data.shape[4], data.shape[3], data.shape[1]), (1.0, 1.0, 2.0))])


def test_other_presets_generate():
    for name in ("five-one", "two-plus-one"):
        data, truth = vesicle(**SMALL, defects=name)
        assert data[0, :, 0].max() > 150
        assert sum(r["charge"] for r in truth["defects"]) == pytest.approx(2.0)


def test_bad_input():
    with pytest.raises(NemoError, match="spacing"):
        vesicle(**SMALL, spacing=(1, 0, 1))
    with pytest.raises(NemoError, match="radius"):
        vesicle(radius=-3)
    with pytest.raises(NemoError, match="channel 1 but the image has 1"):
        vesicle(**SMALL, second_layer_depth=5.0, second_layer_channel=1, channels=1)
    with pytest.raises(NemoError, match="unknown defect preset"):
        vesicle(**SMALL, defects="cube")
    with pytest.raises(NemoError, match="increase size"):
        vesicle(**SMALL, size=40)


# ---------------------------------------------------------------------------------------------
# CLI
# ---------------------------------------------------------------------------------------------
def test_cli_synth(tmp_path, run_cli):
    out = tmp_path / "v.tif"
    code, stdout, err = run_cli(
        "synth", out, "--radius", "20", "--spacing", "2", "1", "1", "--preset", "five-one",
        "--frames", "2", "--frame-rotation", "15", "--second-layer-depth", "6",
        "--second-layer-channel", "1", "--noise", "3", "--seed", "4", "--fibre-spacing", "3",
        "--fibre-length", "20", "--rotate-random", "2",
    )
    assert code == 0, err
    assert "wrote" in stdout and "v.truth.json" in stdout
    info = read_info(out)
    assert info.shape["T"] == 2 and info.shape["C"] == 2 and info.spacing == pytest.approx((2, 1, 1))
    truth = read_truth(out)
    assert sorted({r["charge"] for r in truth["defects"]}) == [-0.5, 0.5]
    assert truth["parameters"]["rotate"] == 2


def test_cli_custom_defects(tmp_path, run_cli):
    out = tmp_path / "v.tif"
    code, _, err = run_cli("synth", out, "--radius", "15", "--defects", "0,0,1:1;0,0,-1:1")
    assert code == 0, err
    assert [r["charge"] for r in read_truth(out)["defects"]] == [1.0, 1.0]


@pytest.mark.parametrize(
    "args, message",
    [
        (["--radius", "15", "--defects", "1,0,0:0.5;0,1,0:0.5"], "sum to 1"),
        (["--radius", "300", "--size", "100"], "increase size"),
        (["--spacing", "1", "0", "1"], "spacing"),
        (["--radius", "15", "--second-layer-depth", "5", "--second-layer-channel", "2", "--channels", "2"], "channel"),
    ],
)
def test_cli_errors(tmp_path, run_cli, args, message):
    code, _, err = run_cli("synth", tmp_path / "v.tif", *args)
    assert code == 2
    assert message in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_cli_bad_suffix(tmp_path, run_cli):
    code, _, err = run_cli("synth", tmp_path / "v.png", "--radius", "15")
    assert code == 2 and ".tif" in err


# ---------------------------------------------------------------------------------------------
# realistic images: anisotropic PSF, shot noise, SNR, open (cut) vesicles
# ---------------------------------------------------------------------------------------------
#: md5 of vesicle(**_PINNED) computed by the generator before the PSF/shot-noise options existed:
#: the defaults must keep producing the same bytes.
_PINNED = dict(radius=20, spacing=(2, 2, 2), noise=5, seed=1)
_PINNED_MD5 = "23b028170489405a50d5a11f44b78e80"


def test_defaults_keep_their_bytes():
    import hashlib

    data, truth = vesicle(**_PINNED)
    assert hashlib.md5(data.tobytes()).hexdigest() == _PINNED_MD5
    assert truth["psf"]["sigma_zyx"] == [1.0, 1.0, 1.0] and truth["noise"]["photons"] is None
    assert "field_of_view" not in truth and all("in_view" not in r for r in truth["defects"])


def _edge_width(profile, step):
    """Std of an error-function edge rising along ``profile``: half the 15.9 % -> 84.1 % distance."""
    top = profile.max()

    def crossing(level):
        i = int(np.argmax(profile >= level))
        return (i - 1 + (level - profile[i - 1]) / (profile[i] - profile[i - 1])) * step

    return (crossing(0.8413 * top) - crossing(0.1587 * top)) / 2


@pytest.mark.parametrize("sigmas", [(2.0, 0.8, 0.8), (1.2, 1.2, 1.2)])
def test_anisotropic_psf_edge_width_is_sigma_along_each_axis(sigmas):
    # the shell alone (no fibres), 255 inside the shell: the inner edge along z is an error
    # function of std sigma_z, along x of std sigma_x
    data, truth = vesicle(radius=25, spacing=(0.5, 0.5, 0.5), blur=sigmas, fibre_intensity=0.0,
                          background=1.0, shell_thickness=12)
    vol = data[0, :, 0].astype(float)
    cz, cy, cx = (np.array(vol.shape) - 1) // 2
    along_z = vol[cz:, cy, cx]  # from the centre outwards: 0 inside, the shell's inner edge at R
    along_x = vol[cz, cy, cx:]
    assert _edge_width(along_z, 0.5) == pytest.approx(sigmas[0], rel=0.06)
    assert _edge_width(along_x, 0.5) == pytest.approx(sigmas[2], rel=0.06)
    assert truth["psf"]["sigma_zyx"] == list(sigmas)
    # the half-intensity level sits at R along every axis, up to the blurred sphere's own inward
    # shift (about sigma^2 / R: 0.16 µm for sigma 2 µm at R = 25 µm)
    for prof, c, sg in ((along_z, truth["centre"][2] - cz * 0.5, sigmas[0]),
                        (along_x, truth["centre"][0] - cx * 0.5, sigmas[2])):
        i = int(np.argmax(prof >= 127.5))
        half = (i - 1 + (127.5 - prof[i - 1]) / (prof[i] - prof[i - 1])) * 0.5
        assert half - c == pytest.approx(25.0, abs=0.05 + sg**2 / 25)


def test_fibres_blurred_along_z_by_sigma_z():
    # at the top pole the fibre layer (r = R + 3) is a horizontal sheet of fibres: its profile
    # along z is a Gaussian of std sigma_z (the sphere's sag over the 2 µm patch is 0.1 µm)
    sig = (2.0, 0.7, 0.7)
    clean, truth = vesicle(radius=20, spacing=(0.5, 0.5, 0.5), blur=sig, background=0.0, fibre_intensity=0.3)
    vol = clean[0, :, 0].astype(float)
    cz, cy, cx = (np.array(vol.shape) - 1) // 2
    zl = cz + int(round(23 / 0.5))  # the layer's top
    prof = vol[zl - 16:zl + 17, cy - 4:cy + 5, cx - 4:cx + 5].mean(axis=(1, 2))
    z = (np.arange(len(prof)) - 16) * 0.5
    mu = (prof * z).sum() / prof.sum()
    assert mu == pytest.approx(0.0, abs=0.3)
    assert np.sqrt((prof * (z - mu) ** 2).sum() / prof.sum()) == pytest.approx(sig[0], rel=0.1)


def test_shot_noise_variance_is_photon_scaled_mean_plus_gaussian():
    # a flat region (the shell, no fibres): variance = 255 * mean / photons + sigma^2 (+ 1/12 rounding)
    kw = dict(radius=20, spacing=(1, 1, 1), fibre_intensity=0.0, background=0.25, shell_thickness=14)
    clean, _ = vesicle(**kw)
    for photons, noise in ((100.0, 5.0), (30.0, 0.0)):
        noisy, truth = vesicle(**kw, photons=photons, noise=noise, seed=3)
        flat = clean[0, :, 0] == 64  # interior of the shell: 63.75 before rounding
        vals = noisy[0, :, 0][flat].astype(float)
        assert flat.sum() > 50_000
        assert vals.mean() == pytest.approx(63.75, abs=0.15)
        expect = 255 * 63.75 / photons + noise**2 + 1 / 12
        assert vals.var() == pytest.approx(expect, rel=0.03)
        assert truth["noise"]["noise_std_shell"] ** 2 == pytest.approx(expect - 1 / 12, rel=1e-9)
        assert truth["noise"]["photons"] == photons and truth["noise"]["gaussian_std"] == noise
    # outside the vesicle (intensity 0) shot noise is zero: only the (clipped) Gaussian remains
    noisy, _ = vesicle(**kw, photons=30.0, seed=3)
    assert noisy[0, 0, 0].max() == 0


def test_snr_definition():
    from nemo.synthetic import snr

    assert snr(216.75, 63.75, noise=15.3) == pytest.approx(10.0)
    assert snr(216.75, 63.75, noise=0.0, photons=255 * 63.75 / 15.3**2) == pytest.approx(10.0)
    assert snr(200, 20, noise=3.0, photons=255 * 20 / 16) == pytest.approx(180 / 5)
    assert snr(216.75, 63.75) is None
    _, truth = vesicle(**SMALL, noise=10.0, photons=50.0)
    n = truth["noise"]
    assert n["snr"] == pytest.approx(153 / np.sqrt(100 + 255 * 63.75 / 50))
    assert n["snr_wall"] == pytest.approx(6.375)


def test_cut_top_opens_the_vesicle():
    full, t_full = vesicle(radius=20, spacing=(2, 1, 1), rotate=5)
    cut, t_cut = vesicle(radius=20, spacing=(2, 1, 1), rotate=5, cut_top=10.0)
    z_max = t_cut["field_of_view"]["z_max"]
    nz = cut.shape[1]
    assert z_max == pytest.approx((nz - 1) * 2.0) and z_max <= t_cut["centre"][2] + 10.0
    assert t_cut["shape"]["Z"] == nz < full.shape[1]
    np.testing.assert_array_equal(cut, full[:, :nz])  # the same image, cut
    assert t_cut["centre"] == t_full["centre"]
    assert [r["in_view"] for r in t_cut["defects"]] == [r["z"] <= z_max for r in t_cut["defects"]]
    assert cut[0, -1, 0].max() > 0  # the top slice cuts through the shell
    with pytest.raises(NemoError, match="cut_top"):
        vesicle(radius=20, spacing=(2, 1, 1), cut_top=-100.0)


def test_cli_psf_and_shot_noise(tmp_path, run_cli):
    common = ["--radius", "15", "--spacing", "2", "1", "1", "--photons", "60", "--noise", "4"]
    code, out, err = run_cli("synth", tmp_path / "a.tif", *common, "--blur", "2.5", "1", "1")
    assert code == 0 and "SNR" in out, err
    code, _, err = run_cli("synth", tmp_path / "b.tif", *common, "--blur", "1", "--blur-z", "2.5")
    assert code == 0, err
    np.testing.assert_array_equal(read_stack(tmp_path / "a.tif")[0], read_stack(tmp_path / "b.tif")[0])
    truth = read_truth(tmp_path / "a.tif")
    assert truth["psf"]["sigma_zyx"] == [2.5, 1.0, 1.0]
    assert truth["noise"]["photons"] == 60 and truth["noise"]["snr"] == pytest.approx(
        153 / np.sqrt(16 + 255 * 63.75 / 60))
    code, out, err = run_cli("synth", tmp_path / "c.tif", "--radius", "15", "--cut-top", "5")
    assert code == 0 and "defects in view" in out, err
    code, _, err = run_cli("synth", tmp_path / "d.tif", "--radius", "15", "--blur", "1", "2")
    assert code == 2 and "--blur" in err
