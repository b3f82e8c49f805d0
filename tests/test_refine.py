"""Sub-voxel refinement and the noise-aware blur against analytic shapes (method note §2)."""

from __future__ import annotations

import functools
import warnings

import numpy as np
import pytest
from scipy import ndimage as ndi
from scipy.spatial.transform import Rotation

from nemo.errors import NemoError, NemoWarning
from nemo.refine import refine_vertices
from nemo.surface import auto_sigma, blur_noise_gain, default_sigma, reconstruct, split_mesh


def _image(shape, spacing, inside, psf, amp=100.0, bg=10.0, noise=0.0, photons=None, seed=0, sub=4):
    """Voxel-averaged indicator of ``inside(x, y, z)`` (supersampled ``sub`` per µm-ish), blurred
    by a Gaussian PSF (σ_z, σ_y, σ_x in µm), on a background, with Poisson and Gaussian noise."""
    dz, dy, dx = spacing
    subs = [max(2, int(round(sub * d))) for d in spacing]
    acc = np.zeros(shape, np.float32)
    for a in range(subs[0]):
        z = (np.arange(shape[0]) + (a + 0.5) / subs[0] - 0.5) * dz
        for b in range(subs[1]):
            y = (np.arange(shape[1]) + (b + 0.5) / subs[1] - 0.5) * dy
            for c in range(subs[2]):
                x = (np.arange(shape[2]) + (c + 0.5) / subs[2] - 0.5) * dx
                acc += inside(x[None, None, :], y[None, :, None], z[:, None, None])
    v = bg + amp * ndi.gaussian_filter(acc / np.prod(subs), [s / d for s, d in zip(psf, spacing)])
    rng = np.random.default_rng(seed)
    if photons:
        v = rng.poisson(v * photons / amp) * (amp / photons)
    return (v + noise * rng.standard_normal(v.shape)).astype(np.float32)


def _setup(R, T, spacing, psf, margin=4.0):
    ext = 2 * (R + T) + 2 * margin + 6 * max(psf)
    shape = tuple(int(np.ceil(ext / d)) for d in spacing)
    c = np.array([(shape[2] - 1) * spacing[2], (shape[1] - 1) * spacing[1], (shape[0] - 1) * spacing[0]]) / 2 + 0.3
    return shape, c


def _radial(mesh, c):
    return np.linalg.norm(np.asarray(mesh.vertices) - c, axis=1)


@pytest.mark.parametrize("spacing, psf", [((1.0, 1.0, 1.0), (1.0, 1.0, 1.0)), ((2.5, 1.0, 1.0), (2.5, 1.0, 1.0))],
                         ids=["isotropic", "dz2.5-psf-z"])
def test_refined_sphere_radius(spacing, psf):
    R = 16.0
    shape, c = _setup(R, 0.0, spacing, psf)
    vol = _image(shape, spacing, lambda x, y, z: (x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2 < R**2, psf)
    mesh = reconstruct(vol, spacing, refine=True)
    assert mesh.metadata["nemo_surface"]["refine"] and mesh.euler_number == 2
    err = np.median(_radial(mesh, c)) - R
    # analytic part of the residual: a ball blurred by σ has its half level σ_t²/R inside (σ_t the
    # blur along the surface); measured -0.07 µm (isotropic), -0.13 µm (σ_z 2.5 µm)
    assert abs(err) < 0.2 * spacing[2], err
    off = reconstruct(vol, spacing, refine=False)
    assert abs(err) <= abs(np.median(_radial(off, c)) - R) + 0.01


@pytest.mark.parametrize("spacing", [(1.0, 1.0, 1.0), (2.0, 2.0, 2.0)], ids=["1um", "2um"])
def test_shell_thickness_unbiased(spacing):
    R, T = 20.0, 10.0
    shape, c = _setup(R, T, spacing, (1.0, 1.0, 1.0))
    rot = Rotation.random(random_state=3).as_matrix()
    axes = np.array([1.0, 0.85, 1.1])  # ellipsoidal shell, randomly rotated

    def shell(x, y, z):
        p = np.stack(np.broadcast_arrays(x - c[0], y - c[1], z - c[2]), -1) @ rot
        r = np.linalg.norm(p / axes, axis=-1)
        return (r >= R) & (r < R + T)

    vol = _image(shape, spacing, shell, (1.0, 1.0, 1.0), photons=200, seed=2)
    inner, outer = split_mesh(reconstruct(vol, spacing, keep="all", refine=True), centre=c)
    # thickness along the normal of the inner wall: the outer wall at the same scaled direction
    ri = np.linalg.norm(((inner.vertices - c) @ rot) / axes, axis=1)
    ro = np.linalg.norm(((outer.vertices - c) @ rot) / axes, axis=1)
    scale = np.median(np.linalg.norm(inner.vertices - c, axis=1) / ri)  # µm per unit of the scaled radius
    thick = (np.median(ro) - np.median(ri)) * scale
    assert abs(thick - T * scale) <= 0.25 + 0.1 * (spacing[0] - 1), (thick, T * scale)


def test_noisy_shell_closed_walls_with_auto_sigma():
    R, T, spacing, psf = 20.0, 10.0, (2.5, 1.0, 1.0), (2.5, 1.0, 1.0)
    shape, c = _setup(R, T, spacing, psf)

    def shell(x, y, z):
        r = np.sqrt((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2)
        return (r >= R) & (r < R + T)

    for snr in (5.0, 3.0):
        vol = _image(shape, spacing, shell, psf, noise=100.0 / snr, seed=int(snr))
        sigma, info = auto_sigma(vol, spacing)
        assert info["limited_by"] == "noise" and sigma > default_sigma(spacing)
        # the raw SNR estimate errs low when the default blur leaves the wall porous (measured
        # 4.5 at SNR 5, 1.4 at SNR 3): more blur, never less
        assert 0.4 * snr < info["snr"] < 1.2 * snr
        inner, outer = split_mesh(reconstruct(vol, spacing, sigma=sigma, keep="all", refine=True), centre=c, keep="largest")
        assert inner.euler_number == 2 and outer.euler_number == 2
        # measured: inner -0.22/-0.35 µm, outer -0.02/+0.08 µm (SNR 5/3)
        assert abs(np.median(_radial(inner, c)) - R) < 0.5
        assert abs(np.median(_radial(outer, c)) - R - T) < 0.5


def test_auto_sigma_keeps_default_on_clean_image():
    spacing = (2.0, 2.0, 2.0)
    shape, c = _setup(20.0, 10.0, spacing, (1.0, 1.0, 1.0))
    vol = _image(shape, spacing, lambda x, y, z: (x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2 < 400, (1, 1, 1))
    sigma, info = auto_sigma(np.round(vol).astype(np.uint8), spacing, step=2)
    assert sigma == default_sigma(spacing, 2) and info["limited_by"] == "default"


def test_blur_noise_gain():
    assert blur_noise_gain(0.0, (1, 1, 1)) == 1.0
    # σ ≥ 1 voxel: close to sqrt(∏ 2 √π σ / d)
    assert blur_noise_gain(3.0, (2.5, 1, 1)) == pytest.approx(np.sqrt((2 * np.sqrt(np.pi)) ** 3 * 9 * 1.2), rel=0.02)
    rng = np.random.default_rng(0)
    noise = rng.standard_normal((60, 60, 60))
    measured = noise.std() / ndi.gaussian_filter(noise, (0.8, 2.0, 2.0), mode="wrap").std()
    assert blur_noise_gain(2.0, (2.5, 1.0, 1.0)) == pytest.approx(measured, rel=0.05)


def test_refine_off_reproduces_old_surface_and_mask_skips():
    spacing = (1.0, 1.0, 1.0)
    shape, c = _setup(8.0, 0.0, spacing, (1, 1, 1))
    inside = lambda x, y, z: (x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2 < 64  # noqa: E731
    vol = _image(shape, spacing, inside, (1, 1, 1))
    on, off = reconstruct(vol, spacing, refine=True), reconstruct(vol, spacing)  # off: the default
    assert len(on.vertices) == len(off.vertices) and np.array_equal(on.faces, off.faces)
    assert off.metadata["nemo_surface"]["refine"] is False
    assert not np.allclose(on.vertices, off.vertices)
    mask = vol > 60
    assert reconstruct(None, spacing, mask=mask, refine=True).metadata["nemo_surface"]["refine"] is False


def test_refine_bad_inputs():
    v = np.zeros((4, 3))
    f = np.array([[0, 1, 2]])
    img = np.zeros((5, 5, 5), np.float32)
    with pytest.raises(NemoError, match="shape"):
        refine_vertices(v, f, np.zeros((3, 3)), img, (1, 1, 1), 0.5)
    with pytest.raises(NemoError, match="3-D"):
        refine_vertices(v, f, v, img[0], (1, 1, 1), 0.5)
    with pytest.raises(NemoError, match="max_shift"):
        refine_vertices(v, f, v, img, (1, 1, 1), 0.5, max_shift=0)
    with pytest.raises(NemoError, match="smooth"):
        refine_vertices(v, f, v, img, (1, 1, 1), 0.5, smooth=-1)
    with pytest.raises(NemoError, match="iso-level"):
        refine_vertices(v, f, v, img, (1, 1, 1), np.nan)
    vol = np.zeros((10, 10, 10), np.float32)
    vol[3:7, 3:7, 3:7] = 1
    with pytest.raises(NemoError, match="refine must be"):
        reconstruct(vol, (1, 1, 1), refine="yes")
    with pytest.raises(NemoError, match="refine_sigma"):
        reconstruct(vol, (1, 1, 1), refine_sigma=-1)
    with pytest.raises(NemoError, match="target_snr"):
        auto_sigma(vol, (1, 1, 1), target_snr=0)
    with pytest.raises(NemoError, match="3-D"):
        auto_sigma(vol[0], (1, 1, 1))


def test_auto_sigma_sees_noise_in_an_image_clipped_at_zero():
    """A shell on a zero background with a bright sheet in it (fibres), noisy (std 25) and clipped
    at 0 like an 8-bit camera image: half the background reads 0, which a median/MAD takes for a
    clean image (it read a raw SNR of 43). The clip-aware spread reads the noise; the blur is
    raised past the default, whose thresholded wall still has noise bubbles, and both walls come
    out closed (χ = 2)."""
    R, T, spacing, psf = 20.0, 10.0, (2.5, 1.0, 1.0), (2.5, 1.0, 1.0)
    shape, c = _setup(R, T, spacing, psf)

    def shell(x, y, z):
        r = np.sqrt((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2)
        return ((r >= R) & (r < R + T)) * 1.0 + 2.5 * ((r >= R + 2) & (r < R + 3.5))

    vol = np.clip(_image(shape, spacing, shell, psf, bg=0.0, noise=25.0, seed=7), 0, None)
    sigma, info = auto_sigma(vol, spacing)
    ladder = info["euler_ladder"]
    assert info["background_noise"] == pytest.approx(25.0, rel=0.1) and abs(info["background"]) < 2.5
    assert ladder[0][1] > 2 * ladder[0][2]  # the default blur leaves noise bubbles in the wall
    assert info["limited_by"] in ("noise", "topology") and sigma >= ladder[-1][0] > default_sigma(spacing)
    inner, outer = split_mesh(reconstruct(vol, spacing, sigma=sigma, keep="all", refine=True), centre=c, keep="largest")
    assert inner.euler_number == 2 and outer.euler_number == 2
    # The blurred shell has no intensity peak (the sheet and the noise smear it): the level is
    # half-way to the object's median, stable over σ (measured: inner −0.83 µm, the sheet 2 µm
    # inside pulls it; outer −0.17 µm). Half-way to a blip of the bright tail, it once read 107
    # at this σ, above the shell, and put the outer wall 3.6 µm inside.
    assert abs(np.median(_radial(inner, c)) - R) < 1.0
    assert abs(np.median(_radial(outer, c)) - R - T) < 0.5


def test_refinement_of_a_noisy_sphere_keeps_its_normals_smooth():
    """A ball (R 18 µm) at SNR 5 (noise 20 on a contrast of 100): each vertex's own edge crossing
    is noisy, and barely smoothed shifts tilt the normals (measured with 3 passes: the normals'
    median angle to the radial direction doubles, 3.8° → 7.6°). The default smoothing keeps them
    as straight as the unrefined mesh's (measured 3.77° both), and the radius within 0.3 µm of R
    (measured −0.05 µm, −0.10 µm unrefined)."""
    from nemo.mesh import vertex_normals

    R, spacing, psf = 18.0, (1.0, 1.0, 1.0), (1.0, 1.0, 1.0)
    shape, c = _setup(R, 0.0, spacing, psf)

    def ball(x, y, z):
        return ((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2 < R**2) * 1.0

    vol = _image(shape, spacing, ball, psf, noise=20.0, seed=3)
    sigma = 1.0

    def tilt(mesh):
        radial = np.asarray(mesh.vertices) - c
        radial /= np.linalg.norm(radial, axis=1, keepdims=True)
        cos = np.einsum("ij,ij->i", vertex_normals(mesh), radial)
        return float(np.median(np.degrees(np.arccos(np.clip(cos, -1, 1)))))

    off = reconstruct(vol, spacing, sigma=sigma, refine=False)
    on = reconstruct(vol, spacing, sigma=sigma, refine=True, refine_sigma=0.0)
    rough = off.copy()  # the same surface refined with the former 3 smoothing passes
    new, _ = refine_vertices(np.asarray(off.vertices), np.asarray(off.faces), vertex_normals(off), vol, spacing,
                             float(off.metadata["nemo_surface"]["level"]), smooth=3)
    rough.vertices = new
    assert tilt(on) <= 1.1 * tilt(off) < tilt(rough)
    assert abs(np.median(_radial(on, c)) - R) < 0.3


def _erf_sphere(radius, spacing, edge_sigma, pad=4.0):
    """A (Z, Y, X) image of a ball (1 inside, 0 outside) with an erf edge of σ ``edge_sigma`` µm."""
    from scipy.special import erf

    half = radius + pad + 4 * edge_sigma
    axes = [np.arange(-half, half + 1e-9, d) for d in spacing]
    z, y, x = np.meshgrid(*axes, indexing="ij")
    r = np.sqrt(x**2 + y**2 + z**2)
    origin = np.array([a[0] for a in axes])  # z, y, x of sample (0, 0, 0)
    return (0.5 - 0.5 * erf((r - radius) / (np.sqrt(2) * edge_sigma))).astype(np.float32), origin


def test_snap_to_level_removes_the_terraces_of_coarse_z_planes():
    """Marching cubes on planes 2.5 × the pixel size puts the vertices of an erf edge (σ 0.8 plane)
    up to 0.06 µm off the true sphere in terraces near the poles (linear interpolation between
    planes); the snap onto the cubic-spline iso-surface brings them within 0.025 µm. (An edge
    sharper than ~0.6 plane is aliased: no interpolant recovers it, measured 0.27 → 0.24 µm at
    σ 0.32 plane.)"""
    import trimesh
    from skimage.measure import marching_cubes

    from nemo.mesh import vertex_normals
    from nemo.refine import snap_to_level

    R, spacing = 12.0, (2.5, 1.0, 1.0)
    field, origin = _erf_sphere(R, spacing, edge_sigma=2.0)
    verts, faces, _, _ = marching_cubes(field, 0.5, spacing=spacing)
    verts_xyz = (verts + origin)[:, ::-1]
    mesh = trimesh.Trimesh(verts_xyz, faces, process=False)  # winding checked just below
    normals = vertex_normals(mesh)
    assert np.einsum("ij,ij->i", normals, verts_xyz).min() > 0  # outward
    snapped, info = snap_to_level(verts_xyz, normals, field, 0.5, spacing, origin)
    err_before = np.abs(np.linalg.norm(verts_xyz, axis=1) - R)
    err_after = np.abs(np.linalg.norm(snapped, axis=1) - R)
    pole = np.abs(normals[:, 2]) > 0.8
    assert err_before[pole].max() > 0.05  # the terraces are there ...
    assert err_after[pole].max() < 0.5 * err_before[pole].max()  # ... and gone
    assert np.sqrt(np.mean(err_after**2)) < 0.4 * np.sqrt(np.mean(err_before**2))
    assert info["snapped"] == len(verts_xyz)
    # a snap never moves a vertex more than a quarter of a sample along its normal
    reach = 0.25 * np.linalg.norm(normals * np.array(spacing[::-1]), axis=1)
    assert (np.linalg.norm(snapped - verts_xyz, axis=1) <= reach + 1e-9).all()
    # fixed vertices and vertices on a flat field stay where they are
    fixed = np.zeros(len(verts_xyz), bool)
    fixed[::3] = True
    again, _ = snap_to_level(verts_xyz, normals, field, 0.5, spacing, origin, fixed=fixed)
    assert np.array_equal(again[fixed], verts_xyz[fixed])
    flat, info_flat = snap_to_level(verts_xyz, normals, np.zeros_like(field), 0.5, spacing, origin)
    assert np.array_equal(flat, verts_xyz) and info_flat["snapped"] == 0


def _thin_shell(spacing, psf, snr, seed, R=20.0, T=4.0):
    shape, c = _setup(R, T, spacing, psf)

    def shell(x, y, z):
        r = np.sqrt((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2)
        return (r >= R) & (r < R + T)

    noise = 0.0 if snr is None else 100.0 / snr
    return _image(shape, spacing, shell, psf, noise=noise, seed=seed), c


@pytest.mark.parametrize("snr", [None, 10.0, 5.0], ids=["clean", "snr10", "snr5"])
def test_steepest_edge_keeps_a_thin_wall_under_a_z_psf(snr):
    """A 4 µm wall under a z-elongated PSF never reaches its plateau, so the half level of the
    histogram's plateau peak lies below the true half level and both walls move outward; the
    steepest point of the edge stays on it. Since session 32 the half level is also corrected
    from the walls' own profiles where noise lowers it (an offset of 0.03-0.1 of the contrast), so
    both are right. Measured (median thickness, T = 4 µm; the mesh blur from auto_sigma, as the
    mesh step): clean / SNR 10 / SNR 5: steepest 4.01 / 4.06 / 4.09 µm, the level 4.12 / 4.01 /
    4.00 (4.12 / 4.41 / 4.83 before the correction)."""
    from nemo.morphology import thickness

    spacing, psf = (2.0, 1.0, 1.0), (1.5, 0.6, 0.6)
    vol, c = _thin_shell(spacing, psf, snr, seed=7)
    sigma = auto_sigma(vol, spacing)[0]  # as the mesh step
    widths = {}
    for to in ("steepest", "level"):
        mesh = reconstruct(vol, spacing, sigma=sigma, keep="all", refine=True, refine_to=to)
        assert mesh.metadata["nemo_surface"]["refine_to"] == to
        inner, outer = split_mesh(mesh, centre=c, keep="largest")
        widths[to] = float(np.nanmedian(thickness(inner, outer)))
    assert abs(widths["steepest"] - 4.0) < (0.2 if snr is None or snr >= 10 else 0.3), widths
    assert abs(widths["level"] - 4.0) < 0.15, widths


def test_steepest_edge_ignores_a_brighter_layer_inside_the_wall(monkeypatch):
    """A bright layer 1.5-2.5 µm inside a ball's edge (fibres in a vesicle wall) has steeper flanks
    than the edge itself; only the intensities between background and plateau compete, so the
    wall stays at its edge. Without that band the refinement would take the layer's flank."""
    import nemo.refine as refine_module

    R, spacing, psf = 16.0, (1.0, 1.0, 1.0), (1.0, 1.0, 1.0)
    shape, c = _setup(R, 0.0, spacing, psf)

    def ball_with_layer(x, y, z):
        r = np.sqrt((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2)
        return (r < R) + 3.0 * ((r > R - 2.5) & (r < R - 1.5))

    vol = _image(shape, spacing, ball_with_layer, psf)
    radius = {}
    for name, band in (("band", refine_module._STEEPEST_BAND), ("no band", 100.0)):
        monkeypatch.setattr(refine_module, "_STEEPEST_BAND", band)
        mesh = reconstruct(vol, spacing, refine=True, refine_to="steepest")
        radius[name] = float(np.median(_radial(mesh, c)))
    assert abs(radius["band"] - R) < 0.25, radius
    assert radius["no band"] < R - 0.5, radius


def test_refine_to_bad_inputs():
    v = np.zeros((4, 3))
    f = np.array([[0, 1, 2]])
    img = np.zeros((5, 5, 5), np.float32)
    with pytest.raises(NemoError, match="refine to"):
        refine_vertices(v, f, v, img, (1, 1, 1), 0.5, to="middle")
    with pytest.raises(NemoError, match="background"):
        refine_vertices(v, f, v, img, (1, 1, 1), 0.5, to="steepest")
    vol = np.zeros((10, 10, 10), np.float32)
    vol[3:7, 3:7, 3:7] = 1
    with pytest.raises(NemoError, match="refine_to"):
        reconstruct(vol, (1, 1, 1), refine=True, refine_to="middle")


def test_steepest_point_of_a_profile_and_its_band():
    """``_steepest`` finds a tanh edge between samples; a profile that does not fall within the
    band (flat, rising, or outside its intensities) gives no edge."""
    from nemo.refine import _steepest

    t = np.tile(np.linspace(-3.0, 3.0, 25), (3, 1))
    edges = np.array([0.13, -0.41, 0.0])
    prof = 50.0 - 40.0 * np.tanh((t - edges[:, None]) / 0.8)  # background 10, plateau 90, half level 50
    np.testing.assert_allclose(_steepest(t, prof, (50 - 16, 50 + 16)), edges, atol=0.02)
    assert np.isnan(_steepest(t, prof[:, ::-1], (50 - 16, 50 + 16))).all()  # rising outward
    assert np.isnan(_steepest(t, np.full_like(t, 50.0), (50 - 16, 50 + 16))).all()  # flat
    assert np.isnan(_steepest(t, prof, (200, 300))).all()  # never in the band


def test_steepest_falls_back_to_the_level_at_the_automatic_threshold():
    R, spacing, psf = 10.0, (1.0, 1.0, 1.0), (1.0, 1.0, 1.0)
    shape, c = _setup(R, 0.0, spacing, psf)
    vol = _image(shape, spacing, lambda x, y, z: (x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2 < R**2, psf)
    with pytest.warns(NemoWarning, match="edge: threshold"):
        mesh = reconstruct(vol, spacing, edge="threshold", refine=True, refine_to="steepest")
    assert mesh.metadata["nemo_surface"]["refine_to"] == "level"
    assert reconstruct(vol, spacing, refine=True, refine_to=None).metadata["nemo_surface"]["refine_to"] == "level"


# ----------------------------------------------------------------------------- edge: profile
def test_a_fitted_box_recovers_a_blurred_walls_parameters():
    """The batched fit of :func:`nemo.refine.wall_profile_level` on exact blurred boxes (walls 2-9 µm,
    blur 0.6-2.5 µm, a sloped background) started from the crossing of the far edge 0.4 µm off:
    every parameter back to 1e-4 (a sharp box or a blur as wide as the wall included)."""
    from nemo.refine import _box_model, _fit_boxes

    rng = np.random.default_rng(3)
    m = 12
    s = np.arange(-6.0, 16.0, 0.25)
    truth = np.column_stack([rng.uniform(0, 30, m), rng.uniform(50, 300, m), rng.uniform(-0.5, 0.5, m),
                             rng.uniform(2, 9, m), np.log(rng.uniform(0.6, 2.5, m)), rng.uniform(-1, 1, m)])
    truth[:, 3] += truth[:, 2]
    profiles = _box_model(truth, s)[0]
    mask = s[None, :] <= truth[:, 3:4] + 5
    fitted = _fit_boxes(s, profiles, mask, truth[:, 3] + 0.4, 1.0)
    expect = truth.copy()
    expect[:, 4] = np.exp(expect[:, 4])
    np.testing.assert_allclose(fitted, expect, atol=1e-4, rtol=1e-4)


@pytest.mark.parametrize("snr", [None, 10.0, 5.0, 3.0], ids=["clean", "snr10", "snr5", "snr3"])
def test_profile_edge_keeps_a_thin_wall_under_a_z_psf(snr):
    """``edge: profile`` on the 4 µm wall under a z-elongated PSF (background 10, wall 110): the
    level is the true half level 60 at every SNR, where the histogram's half level drops with the
    noise (measured, seeds 7 / 8: 57.6 / 55.9-57.7 / 51.9-54.1 / 47.4-48.9 at clean / SNR 10 / 5 / 3,
    thickness 4.14 / 4.14-4.27 / 4.42-4.62 / 4.92-5.15 µm; profile: 59.7-60.7, 3.88-4.00 µm)."""
    from nemo.morphology import thickness

    spacing, psf = (2.0, 1.0, 1.0), (1.5, 0.6, 0.6)
    vol, c = _thin_shell(spacing, psf, snr, seed=7)
    sigma = auto_sigma(vol, spacing)[0]  # as the mesh step
    mesh = reconstruct(vol, spacing, sigma=sigma, keep="all", edge="profile")
    record = mesh.metadata["nemo_surface"]
    assert record["edge"] == "profile" and record["profile"]["fitted"] >= 0.9 * record["profile"]["rays"]
    assert record["level"] == record["profile"]["level"] == pytest.approx(60.0, abs=1.5)
    assert record["profile"]["misfit"] < 0.04  # a plain wall, no warning: boxes fit it (0.004-0.029 clean to SNR 3)
    inner, outer = split_mesh(mesh, centre=c, keep="largest")
    assert float(np.nanmedian(thickness(inner, outer))) == pytest.approx(4.0, abs=0.15)


def test_the_half_level_is_checked_against_the_walls_profiles(caplog):
    """At the default half level the walls' profiles check the level: the 4 µm wall under a z-PSF
    reads an offset of 0.02 clean (thickness 4.14 µm; the surface stays), 0.14 of the contrast at
    SNR 3 (5.15 µm), which is warned about (too large to tell from a bright sheet inside the wall:
    the surface stays), and at SNR 5 an offset within 0.03-0.1 that is corrected (the level 60, the
    true half level; the histogram's 51.9); a wall with bright films (misfit 0.3) gets none."""
    spacing, psf = (2.0, 1.0, 1.0), (1.5, 0.6, 0.6)
    checks, levels = {}, {}
    for snr in (None, 5.0, 3.0):
        vol, c = _thin_shell(spacing, psf, snr, seed=7)
        caplog.clear()
        with caplog.at_level("WARNING", logger="nemo"):
            mesh = reconstruct(vol, spacing, sigma=auto_sigma(vol, spacing)[0], keep="all")
        record = mesh.metadata["nemo_surface"]
        checks[snr], levels[snr] = (record["edge_check"], caplog.text), record["level"]
    (clean, clean_log), (noisy, noisy_log) = checks[None], checks[3.0]
    assert clean["misfit"] < 0.03 and 0 < clean["offset"] < 0.03 and "own profiles" not in clean_log
    assert not clean["corrected"] and levels[None] == clean["level_half"]  # within the half level's own error
    assert clean["thinner_than_blur"] is None and noisy["thinner_than_blur"] is None
    assert noisy["offset"] > noisy["limit"] == 0.1 and noisy["level_profile"] == pytest.approx(60.0, abs=2.0)
    assert "the walls come out outward (thicker)" in noisy_log and not noisy["corrected"]
    # a small offset of plain walls (noise lowers the histogram's plateau) is corrected: meshed at the profiles' level
    snr5, snr5_log = checks[5.0]
    assert 0.03 <= snr5["offset"] <= 0.1 and snr5["level_share"] > 0.35 and snr5["corrected"]
    assert levels[5.0] == snr5["level_profile"] == pytest.approx(60.0, abs=1.5) and snr5["level_half"] < 57.0
    assert "own profiles" not in snr5_log  # corrected, not warned
    vol, c = _films_wall()
    textured = reconstruct(vol, (1.0, 1.0, 1.0), keep="all").metadata["nemo_surface"]["edge_check"]
    assert textured["misfit"] > 0.1 and textured["offset"] is None


def _films_wall():
    """A 10 µm wall (R 15-25 µm, 50 above a background of 10) with two bright films 0.5-2 µm inside its
    surfaces (+100), 1 µm voxels, 1 µm PSF."""
    spacing, psf = (1.0, 1.0, 1.0), (1.0, 1.0, 1.0)
    shape, c = _setup(15.0, 10.0, spacing, psf)

    def radius(x, y, z):
        return np.sqrt((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2)

    def wall(x, y, z):
        return (radius(x, y, z) >= 15.0) & (radius(x, y, z) < 25.0)

    def films(x, y, z):
        r = radius(x, y, z)
        return ((r >= 15.5) & (r < 17.0)) | ((r >= 23.0) & (r < 24.5))

    return _image(shape, spacing, wall, psf, amp=50.0, sub=2) + _image(shape, spacing, films, psf, bg=0.0, sub=2), c


def test_profile_edge_warns_of_walls_that_are_not_boxes(caplog):
    """A 10 µm wall (50 above the background) with two bright films 0.5-2 µm inside its surfaces: the
    boxes' residuals keep the films' pattern (misfit 0.30; a plain wall ≤ 0.03), and the level they
    give (46, the half level 36) comes with a warning that the walls may move inward."""
    vol, _ = _films_wall()
    with caplog.at_level("WARNING", logger="nemo"):
        mesh = reconstruct(vol, (1.0, 1.0, 1.0), keep="all", edge="profile")
    record = mesh.metadata["nemo_surface"]["profile"]
    assert record["misfit"] > 0.1 and record["level"] > record["level_half"] + 5
    assert "not plain blurred boxes" in caplog.text and "compare with edge: half" in caplog.text


def test_profile_edge_stays_at_the_half_level_without_walls_in_reach(caplog):
    """A filled ball 90 µm across at 1 µm voxels (no far edge within the rays' reach, 80 voxels): no
    profile fits, a warning, and the half level's surface (the ball's radius)."""
    shape, c = _setup(45.0, 0.0, (1.0, 1.0, 1.0), (1.0, 1.0, 1.0), margin=2.0)

    def ball(x, y, z):
        return np.sqrt((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2) < 45.0

    vol = _image(shape, (1.0, 1.0, 1.0), ball, (1.0, 1.0, 1.0), sub=1)
    with caplog.at_level("WARNING", logger="nemo"):
        mesh = reconstruct(vol, (1.0, 1.0, 1.0), keep="largest", edge="profile")
    half = reconstruct(vol, (1.0, 1.0, 1.0), keep="largest")
    assert "too few walls' profiles fitted" in caplog.text
    record = mesh.metadata["nemo_surface"]
    assert record["profile"]["level"] is None and record["profile"]["fitted"] == 0
    assert record["level"] == half.metadata["nemo_surface"]["level"]
    np.testing.assert_allclose(mesh.vertices, half.vertices)
    assert np.median(_radial(mesh, c)) == pytest.approx(45.0, abs=0.3)


def _membrane():
    """A 1 µm membrane (R 15-16 µm) under a 1.5 µm z-PSF at 1 × 0.5 × 0.5 µm voxels: (image, spacing)."""
    spacing, psf = (1.0, 0.5, 0.5), (1.5, 0.5, 0.5)
    shape, c = _setup(15.0, 1.0, spacing, psf)

    def membrane(x, y, z):
        r = np.sqrt((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2)
        return (r >= 15.0) & (r < 16.0)

    return _image(shape, spacing, membrane, psf, sub=2), spacing


def test_profile_edge_keeps_the_half_level_on_a_wall_thinner_than_the_blur(caplog):
    """A 1 µm membrane under a 1.5 µm z-PSF never reaches its box's half height: the fitted level
    (~50 for a crest of ~35) would tear the surface (37 pieces, χ 52 in a review). The level stays the
    half level, warned, recorded with the fraction of rays whose crest is below it (57 %)."""
    vol, spacing = _membrane()
    with caplog.at_level("WARNING", logger="nemo"):
        mesh = reconstruct(vol, spacing, keep="all", edge="profile")
    half = reconstruct(vol, spacing, keep="all")
    record = mesh.metadata["nemo_surface"]["profile"]
    assert "above the blurred wall's crest" in caplog.text and record["level"] is None
    assert record["below_crest"] > 0.3
    assert mesh.metadata["nemo_surface"]["level"] == half.metadata["nemo_surface"]["level"]
    assert mesh.euler_number == half.euler_number == 4  # the membrane's two closed sides


def _shifted_profile_level(monkeypatch) -> dict:
    """Make the walls' fitted level ``shift`` × their contrast above the half level (and override the fit's
    ``info`` keys), as the returned dict's ``shift`` and ``info`` say when the mesh step runs."""
    import nemo.refine as refine_module

    found = refine_module.wall_profile_level
    setting = {"shift": 0.0, "info": {}}

    def shifted(*args, **kwargs):
        level, info = found(*args, **kwargs)
        return args[5] + setting["shift"] * info["contrast"], {**info, **setting["info"]}

    monkeypatch.setattr(refine_module, "wall_profile_level", shifted)
    return setting


@functools.cache
def _plain_shell(snr: float) -> np.ndarray:
    """A plain 6 µm wall (R 15 µm, 1 µm voxels and PSF) at ``snr``, made once per SNR."""
    return _thin_shell((1.0, 1.0, 1.0), (1.0, 1.0, 1.0), snr, seed=1, R=15.0, T=6.0)[0]


def _plain_shell_surface(snr: float) -> dict:
    """The mesh step's record (``nemo_surface``) of :func:`_plain_shell` at its defaults."""
    vol = _plain_shell(snr)
    return reconstruct(vol, (1.0, 1.0, 1.0), sigma=auto_sigma(vol, (1.0, 1.0, 1.0))[0],
                       keep="all").metadata["nemo_surface"]


def test_the_half_level_is_corrected_upward_only(monkeypatch):
    """Noise lowers the histogram's plateau, so a plain wall's profiles read a level above the half
    level, by about 0.2 / SNR of the contrast, and only such an offset is corrected; profiles read below
    it (not what noise does: a review found them re-meshed with that reason), or above it by more than
    the noise explains (a bright sheet inside the wall: a review's walls moved 0.3 µm inward), leave
    the half level as it is."""
    fitted = _shifted_profile_level(monkeypatch)
    records = {}
    for snr, shift in ((5.0, 0.05), (5.0, -0.05), (10.0, 0.08)):
        fitted["shift"] = shift
        records[shift] = _plain_shell_surface(snr)
    up, down, sheet = records[0.05], records[-0.05], records[0.08]
    assert up["edge_check"]["corrected"] and up["level"] == pytest.approx(up["edge_check"]["level_profile"])
    assert up["level"] > up["edge_check"]["level_half"] and up["edge_check"]["offset_snr"] < 0.45
    assert not down["edge_check"]["corrected"] and down["level"] == down["edge_check"]["level_half"]
    assert down["edge_check"]["offset"] == pytest.approx(-0.05, abs=1e-6)
    assert sheet["edge_check"]["offset_snr"] > 0.45 and not sheet["edge_check"]["corrected"]
    assert sheet["level"] == sheet["edge_check"]["level_half"]


def test_the_half_level_correction_has_soft_limits(monkeypatch, caplog):
    """The correction's limits are soft: an offset at the lower limit (0.03) or an offset × SNR at its (0.45) moves
    the surface half way to the profiles' level, so the frames of a time-lapse whose walls sit near a limit are
    not meshed at levels a whole correction apart (the validation shells at SNR 10 read offsets 0.029-0.031 by
    seed, and only one was corrected: 0.35 µm thinner); across the upper limit (0.1) the share falls to 0, and the
    warning (and the QC) judge the offset the correction leaves (a review: 0.104 moved 28 % and warned of nothing,
    while the QC flagged it)."""
    fitted = _shifted_profile_level(monkeypatch)
    records, logs = {}, {}
    for snr, shift in ((5.0, 0.015), (5.0, 0.025), (5.0, 0.03), (5.0, 0.035), (5.0, 0.06), (3.0, 0.085), (3.0, 0.1),
                       (3.0, 0.12)):
        fitted["shift"] = shift
        caplog.clear()
        with caplog.at_level("WARNING", logger="nemo"):
            records[shift] = _plain_shell_surface(snr)
        logs[shift] = caplog.text
    expected = {0.015: 0.0, 0.025: 0.25, 0.03: 0.5, 0.035: 0.75, 0.06: 1.0, 0.085: 1.0, 0.1: 0.5, 0.12: 0.0}
    assert "the walls come out outward" in logs[0.12] and "the walls come out" not in logs[0.1]  # 0.1 × 0.5 left
    for shift, share in expected.items():
        check, level = records[shift]["edge_check"], records[shift]["level"]
        assert check["offset_snr"] is None or check["offset_snr"] < 0.4  # the noise's limit not reached here
        assert check["correction"] == pytest.approx(share, abs=1e-6) and check["corrected"] == (share > 0)
        assert level == pytest.approx(check["level_half"] + share * (check["level_profile"] - check["level_half"]))
    # the offset × SNR's soft limit, at SNR ≈ 9.4: 0.06 × 9.4 = 0.57 (more than noise explains) corrects nothing,
    # 0.045 × 9.4 = 0.42, within 0.45 ± 0.05, part of the way
    checks = {}
    for shift in (0.045, 0.06):
        fitted["shift"] = shift
        checks[shift] = _plain_shell_surface(10.0)["edge_check"]
    assert 0.4 < checks[0.045]["offset_snr"] < 0.5 and 0.0 < checks[0.045]["correction"] < 1.0
    assert checks[0.06]["offset_snr"] > 0.5 and checks[0.06]["correction"] == 0.0 and not checks[0.06]["corrected"]
    # the level's share of the boxes' height: 0.35 ± 0.05 (plain walls 0.42-0.49, a sheet inside a wall 0.25)
    fitted["shift"] = 0.06
    for height, share in ((0.30, 0.0), (0.35, 0.5), (0.40, 1.0)):
        fitted["info"] = {"level_share": height}
        check = _plain_shell_surface(5.0)["edge_check"]
        assert check["correction"] == pytest.approx(share, abs=1e-6), height


@pytest.mark.parametrize("factor", [100.0, 5000.0, 1e5])
def test_the_half_level_check_does_not_depend_on_the_intensity_scale(factor):
    """The walls' profiles are fitted in units of each ray's contrast: the fit's damping adds a share of the
    whole Hessian diagonal, whose edge and width terms grow as the intensity squared, and froze the
    background and contrast of bright images (a review: the same shell × 5000 read misfit 0.051 for 0.008
    and lost its correction, × 1e5 0.038 and none)."""
    vol = _plain_shell(5.0)
    sigma = auto_sigma(vol, (1.0, 1.0, 1.0))[0]
    checks = [reconstruct(v, (1.0, 1.0, 1.0), sigma=sigma, keep="all").metadata["nemo_surface"]["edge_check"]
              for v in (vol, (vol.astype(np.float64) * factor).astype(np.float32))]
    assert checks[0]["misfit"] < 0.02 and checks[0]["offset"] is not None
    for key in ("misfit", "offset", "correction", "level_share"):
        assert checks[1][key] == pytest.approx(checks[0][key], rel=1e-3, abs=1e-5), key


def test_the_half_level_check_flags_a_wall_thinner_than_the_blur(caplog):
    """The same 1 µm membrane at the default half level: its profiles' level is refused (their crests
    stay below it), and rather than no check the record says the walls are thinner than the blur, with
    a warning (and a QC flag, tests/test_summary.py; a 2 µm wall under σz 2 µm read 4.5 µm unflagged in
    a review)."""
    vol, spacing = _membrane()
    with caplog.at_level("WARNING", logger="nemo"):
        check = reconstruct(vol, spacing, keep="all").metadata["nemo_surface"]["edge_check"]
    assert check["offset"] is None and check["misfit"] < 0.03 and check["thinner_than_blur"] > 0.3
    assert check["level_share"] > 0.15  # the boxes are the wall (a bright texture on a dim wall: < 0.1)
    assert "thinner than the image's blur" in caplog.text


def test_a_wall_thinner_than_the_blur_is_flagged_when_deconvolved_too(caplog):
    """Deconvolving (a PSF given, or psf: auto) does not thin a wall thinner than the blur: the mesh step
    reads the profiles of the image before deconvolution along the deconvolved mesh's normals and keeps
    the flag (a review's 2-3 µm walls read 2.2 times too thick and passed under the default psf: auto)."""
    from nemo import stages

    vol, spacing = _membrane()
    with caplog.at_level("WARNING", logger="nemo"), warnings.catch_warnings():
        warnings.simplefilter("ignore", NemoWarning)
        _, p = stages.mesh(vol, spacing, {"split": "none"}, psf=(1.5, 0.5, 0.5))
    check = p["edge_check"]
    assert p["deconvolution"]["iterations"] > 0 and check["image"] == "before deconvolution"
    assert check["thinner_than_blur"] > 0.3 and check["offset"] is None and not check["corrected"], check
    assert "thinner than the image's blur" in caplog.text


def test_profile_edge_reports_pieces_of_different_brightness(caplog):
    """Two 4 µm shells, 100 and 60 above a background of 10 (noise 2), which the stack's level does not
    part into objects of their own levels: each wall's fitted level is its own true half level (60,
    40); one level serves the stack, and a warning names the levels (a review: the dim one shrank
    unannounced, area 2472 → 2114)."""
    spacing = (1.0, 1.0, 1.0)
    centres = (np.array([20.3, 20.3, 20.3]), np.array([58.3, 20.3, 20.3]))

    def shell(c):
        return lambda x, y, z: np.abs(np.sqrt((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2) - 12.0) < 2.0

    vol = (_image((40, 40, 80), spacing, shell(centres[0]), (1.0, 1.0, 1.0), sub=2)
           + _image((40, 40, 80), spacing, shell(centres[1]), (1.0, 1.0, 1.0), amp=60.0, bg=0.0, sub=2))
    vol += np.random.default_rng(0).normal(0, 2, vol.shape).astype(np.float32)
    with caplog.at_level("WARNING", logger="nemo"):
        mesh = reconstruct(vol, spacing, keep="all", edge="profile")
    levels = mesh.metadata["nemo_surface"]["profile"]["piece_levels"]
    assert "walls of different brightness" in caplog.text
    np.testing.assert_allclose(levels, [40.0, 40.0, 60.0, 60.0], atol=1.0)


def test_profile_edge_is_not_applied_to_a_mask_or_a_given_level():
    """A numeric threshold is the level, and a mask is meshed as given: ``edge: profile`` says so in
    the record (``skipped``) and changes nothing."""
    vol, c = _thin_shell((2.0, 1.0, 1.0), (1.5, 0.6, 0.6), None, seed=7)
    given = reconstruct(vol, (2.0, 1.0, 1.0), threshold=55.0, keep="all", edge="profile")
    assert given.metadata["nemo_surface"]["profile"] == {"level": None, "skipped": "the threshold is a given level"}
    assert given.metadata["nemo_surface"]["level"] == pytest.approx(55.0)
    masked = reconstruct(None, (2.0, 1.0, 1.0), mask=vol > 60, keep="all", edge="profile")
    assert masked.metadata["nemo_surface"]["profile"]["skipped"] == "a mask gives the surface"
