"""Deconvolving a Gaussian PSF (nemo.psf) against analytic edges and points."""

from __future__ import annotations

import numpy as np
import pytest
import tifffile
from scipy import ndimage as ndi
from scipy import special

from nemo.errors import NemoError
from nemo.psf import DECONVOLVE_ITERATIONS, check_psf, deconvolve, richardson_lucy_gaussian


def _z_edge(sigma_z: float, dz: float = 1.0, noise: float = 0.0, n: int = 60) -> tuple[np.ndarray, np.ndarray]:
    """A step at z = 30 (background 0.1, plateau 1.1) blurred along z by ``sigma_z``; (stack, z)."""
    z = (np.arange(int(n / dz)) + 0.5) * dz
    profile = 0.1 + 0.5 * (1 + special.erf((z - 30.0) / (np.sqrt(2) * sigma_z)))
    stack = np.broadcast_to(profile[:, None, None], (len(z), 12, 12)).copy()
    stack += noise * np.random.default_rng(0).standard_normal(stack.shape)
    return stack, z


def _edge_sigma_and_middle(profile: np.ndarray, z: np.ndarray) -> tuple[float, float]:
    """Gaussian σ of an edge from its 25-75 % rise (1.349 σ) and its half-way crossing."""
    lo, mid, hi = (np.interp(0.1 + f, profile, z) for f in (0.25, 0.5, 0.75))
    return (hi - lo) / 1.349, mid


@pytest.mark.parametrize("sigma_z, dz", [(2.0, 1.0), (3.0, 1.0), (2.5, 2.5)])
def test_a_z_blurred_edge_is_sharpened_in_place(sigma_z, dz):
    """A step blurred along z by σz: deconvolved by the PSF (σz, 1, 1), its edge is at most 60 % as
    wide, its half-way crossing stays within 0.1 σz, and the total intensity is kept
    (Richardson-Lucy conserves flux)."""
    stack, z = _z_edge(sigma_z, dz)
    out, record = deconvolve(stack, (dz, 1.0, 1.0), (sigma_z, 1.0, 1.0))
    before, mid_before = _edge_sigma_and_middle(stack.mean(axis=(1, 2)), z)
    after, mid_after = _edge_sigma_and_middle(out.mean(axis=(1, 2)), z)
    assert record["sigma_voxels"] == pytest.approx([sigma_z / dz, 1.0, 1.0])
    assert record["iterations"] == DECONVOLVE_ITERATIONS and out.dtype == np.float32
    assert before == pytest.approx(sigma_z, rel=0.03 if dz == 1.0 else 0.12)  # planes one σ apart read wider
    assert after < 0.6 * before, (before, after)
    assert abs(mid_after - mid_before) < 0.1 * sigma_z
    assert out.sum() == pytest.approx(stack.sum(), rel=1e-4)


def test_more_iterations_sharpen_further_and_noise_stays_bounded():
    stack, z = _z_edge(3.0, noise=0.02)
    widths = [_edge_sigma_and_middle(deconvolve(stack, (1, 1, 1), (3, 1, 1), iterations=k)[0].mean(axis=(1, 2)), z)[0]
              for k in (5, 10, 40)]
    assert widths[0] > widths[1] > widths[2] > 1.0
    out = deconvolve(stack, (1, 1, 1), (3, 1, 1))[0]
    flat = out[:15]  # the background far from the edge: the noise is not amplified much
    assert flat.std() < 2.0 * stack[:15].std()


def test_nothing_to_undo_returns_the_stack_itself():
    stack, _ = _z_edge(1.0)
    for psf in (None, (0.4, 0.2, 0.2), (0, 0, 0)):  # below a quarter of a voxel on every axis
        out, record = deconvolve(stack, (2.0, 1.0, 1.0), psf)
        assert out is stack and record["iterations"] == 0


def test_negative_offsets_are_kept():
    """Richardson-Lucy needs non-negative data: a stack with a negative background (a subtracted
    camera offset) is shifted for it and back."""
    stack, z = _z_edge(2.0)
    out = deconvolve(stack - 0.5, (1, 1, 1), (2.0, 1.0, 1.0))[0]
    assert out.min() < 0
    assert _edge_sigma_and_middle(out.mean(axis=(1, 2)) + 0.5, z)[0] < 0.6 * 2.0


def test_richardson_lucy_of_a_blurred_point_concentrates_it():
    """The Gaussian-blurred image of a point is pulled back towards the point."""
    from scipy import ndimage as ndi

    point = np.zeros((31, 9, 9), np.float32)
    point[15, 4, 4] = 100.0
    blurred = ndi.gaussian_filter(point, (3.0, 0, 0), mode="nearest") + 1.0
    out = richardson_lucy_gaussian(blurred, (3.0, 0.0, 0.0), 30)
    col = out[:, 4, 4] - 1.0
    assert np.argmax(col) == 15
    spread = np.sqrt(np.sum(col * (np.arange(31) - 15) ** 2) / col.sum())
    assert spread < 0.6 * 3.0


@pytest.mark.parametrize("psf", [(1, 2), "abc", (1, -1, 1), (1, float("nan"), 1), ((1, 2), 1, 1)])
def test_bad_psf_is_named(psf):
    with pytest.raises(NemoError, match="psf must be three numbers"):
        check_psf(psf)


def test_missing_voxels_stay_missing_and_huge_values_are_scaled():
    """NaN voxels (no data) come back NaN, the rest as without them nearby; a float64 image beyond
    float32's range is deconvolved like the same image scaled down."""
    stack, z = _z_edge(2.0)
    holed = stack.copy()
    holed[:5] = np.nan  # far from the edge at 30
    out = deconvolve(holed, (1, 1, 1), (2.0, 1.0, 1.0))[0]
    ref = deconvolve(stack, (1, 1, 1), (2.0, 1.0, 1.0))[0]
    assert np.isnan(out[:5]).all() and np.isfinite(out[5:]).all()
    np.testing.assert_allclose(out[5:], ref[5:], rtol=1e-3)
    huge = deconvolve(stack.astype(np.float64) * 1e35, (1, 1, 1), (2.0, 1.0, 1.0))[0]
    np.testing.assert_allclose(huge / 1e35, ref, rtol=1e-4)
    with pytest.raises(NemoError, match="no finite voxel"):
        deconvolve(np.full((10, 4, 4), np.nan), (1, 1, 1), (2.0, 1.0, 1.0))


def test_a_psf_wider_than_the_stack_is_named():
    stack, _ = _z_edge(2.0)  # 60 planes of 1 µm
    with pytest.raises(NemoError, match="psf σz 500 is 500 voxels, more than half the stack's 60 along z"):
        deconvolve(stack, (1, 1, 1), (500, 1, 1))


def test_bad_iterations_are_named():
    stack, _ = _z_edge(2.0)
    for bad in (0, 2.5, True):
        with pytest.raises(NemoError, match="iterations must be a whole number"):
            deconvolve(stack, (1, 1, 1), (2, 1, 1), iterations=bad)


def test_a_written_deconvolution_reads_back_bit_for_bit_and_only_for_its_frame(tmp_path):
    """write_deconvolved / read_deconvolved: the float32 stack and record come back unchanged (so a
    workflow step that reads it meshes and peels the same numbers as one that deconvolves), and a
    file made for another PSF, frame, shape or spacing, or another TIFF, is refused by name."""
    from nemo.psf import read_deconvolved, write_deconvolved

    rng = np.random.default_rng(0)
    raw = ndi.gaussian_filter(rng.random((12, 20, 20)) * 200, 1).astype(np.uint16)
    sharp, record = deconvolve(raw, (2.0, 1.0, 1.0), (2.0, 1.0, 1.0))
    path = tmp_path / "d.tif"
    write_deconvolved(path, sharp, record, raw, (2.0, 1.0, 1.0), 1, 2, "x.tif")
    back, rec = read_deconvolved(path, raw, (2.0, 1.0, 1.0), (2.0, 1.0, 1.0), 1, 2)
    assert back.dtype == np.float32 and np.array_equal(back, sharp) and rec == record
    for args, what in [((raw, (2.0, 1.0, 1.0), (2.5, 1.0, 1.0), 1, 2), "the PSF"),
                       ((raw, (2.0, 1.0, 1.0), (2.0, 1.0, 1.0), 0, 2), "the frame"),
                       ((raw[:-1], (2.0, 1.0, 1.0), (2.0, 1.0, 1.0), 1, 2), "the stack's shape"),
                       ((raw, (2.5, 1.0, 1.0), (2.0, 1.0, 1.0), 1, 2), "the spacing")]:
        with pytest.raises(NemoError, match=f"made for {what}.*run nemo deconvolve again"):
            read_deconvolved(path, *args)
    with pytest.raises(NemoError, match="made from another image"):  # same frame, shape and spacing
        read_deconvolved(path, raw + 1, (2.0, 1.0, 1.0), (2.0, 1.0, 1.0), 1, 2)
    other = tmp_path / "other.tif"
    tifffile.imwrite(other, raw, imagej=True)
    with pytest.raises(NemoError, match="not a deconvolved stack written by nemo deconvolve"):
        read_deconvolved(other, raw, (2.0, 1.0, 1.0), (2.0, 1.0, 1.0), 1, 2)
    # nothing to deconvolve (a PSF below a quarter voxel): only the record is stored, the image is used
    same, tiny = deconvolve(raw, (2.0, 1.0, 1.0), (0.1, 0.1, 0.1))
    write_deconvolved(path, same, tiny, raw, (2.0, 1.0, 1.0), 1, 2, "x.tif")
    back, rec = read_deconvolved(path, raw, (2.0, 1.0, 1.0), (0.1, 0.1, 0.1), 1, 2)
    assert back is raw and rec["iterations"] == 0 and path.stat().st_size < 2000


def _textured(sigma_z: float, sigma_xy: float, dz: float, dx: float, shape: str = "ball", snr: float | None = None,
              seed: int = 0) -> np.ndarray:
    """An isotropic random texture (white noise smoothed by 0.7 µm) on a bright ball of radius 25 µm, a
    flat membrane 1 µm thick (``shape="sheet"``) or a bright wall 4-5 µm thick, textured, of
    semi-axes 16, 16, 24 µm along x, y, z (``shape="prolate"``; 17.6, 17.6, 22: ``"prolate125"``),
    blurred by the PSF (σz, σxy, σxy) on a 0.5 µm grid and sampled every dz / dx; Gaussian noise of
    1 / ``snr`` of the texture's spread."""
    rng = np.random.default_rng(seed)
    fine = 0.5
    n = 128
    texture = ndi.gaussian_filter(rng.standard_normal((n, n, n)), 0.7 / fine)
    r = (np.indices((n, n, n)) - n / 2) * fine
    inside = {"ball": np.sqrt((r**2).sum(0)) < 25, "sheet": np.abs(r[0]) < 0.5,
              "prolate": np.abs((r[0] / 24) ** 2 + (r[1] / 16) ** 2 + (r[2] / 16) ** 2 - 0.85) < 0.15,
              "prolate125": np.abs((r[0] / 22) ** 2 + (r[1] / 17.6) ** 2 + (r[2] / 17.6) ** 2 - 0.85) < 0.15}[shape]
    wall = {"sheet": 0.0, "ball": 0.15}.get(shape, 1.0)  # brighter than its surroundings: an outline facing every way
    image = ndi.gaussian_filter(np.where(inside, texture + wall, 0.0), (sigma_z / fine, sigma_xy / fine, sigma_xy / fine))
    image = image[::int(round(dz / fine)), ::int(round(dx / fine)), ::int(round(dx / fine))]
    image = image / image[image != 0].std()
    if snr is not None:
        image = image + rng.standard_normal(image.shape) / snr
    return (image + 10).astype(np.float32)


@pytest.mark.parametrize("sigma_z, sigma_xy, dz, snr", [(2.2, 0.8, 2.5, None), (2.2, 0.8, 2.5, 1.0),
                                                         (3.0, 1.0, 2.0, None), (1.6, 0.6, 1.0, 2.0)])
def test_the_z_blur_is_estimated_from_the_image(sigma_z, sigma_xy, dz, snr):
    """psf: auto: an isotropic texture blurred by (σz, σxy, σxy) reads the z blur beyond the lateral,
    √(σz² − σxy²), within 15 %, also under white noise as strong as the texture (the lags of one voxel
    and more do not see it); deconvolve deconvolves that along z alone and records the estimate."""
    from nemo.psf import estimate_psf

    image = _textured(sigma_z, sigma_xy, dz, 1.0, snr=snr)
    psf, estimate = estimate_psf(image, (dz, 1.0, 1.0))
    truth = np.sqrt(sigma_z**2 - sigma_xy**2)
    assert psf is not None and psf[1:] == (0.0, 0.0), estimate
    assert psf[0] == pytest.approx(truth, rel=0.15), (psf, truth, estimate)
    out, record = deconvolve(image, (dz, 1.0, 1.0), "auto")
    assert record["estimated"] and record["psf"] == list(psf) and record["estimate"] == estimate
    assert np.array_equal(out, deconvolve(image, (dz, 1.0, 1.0), psf)[0])


def _plain_shell(sigma_z: float, sigma_xy: float, dz: float, snr: float, seed: int = 0) -> np.ndarray:
    """A plain wall (R 17-23 µm, no texture) blurred by (σz, σxy, σxy) on a 0.5 µm grid, sampled every
    dz / 1 µm, Gaussian noise of 1 / ``snr`` of the wall's height."""
    fine, n = 0.5, 128
    r = np.sqrt((((np.indices((n, n, n)) - n / 2) * fine) ** 2).sum(0))
    wall = ((r > 17) & (r < 23)).astype(np.float32)
    image = ndi.gaussian_filter(wall, (sigma_z / fine, sigma_xy / fine, sigma_xy / fine))[::int(dz / fine), ::2, ::2]
    return (10 + image + np.random.default_rng(seed).standard_normal(image.shape) / snr).astype(np.float32)


@pytest.mark.parametrize("seed", [0, 1])
def test_the_noise_is_fitted_with_the_object_at_fine_sampling(seed):
    """At 1 µm voxels the high-pass makes white noise covary negatively at a voxel's lag: unfitted, a
    plain shell at SNR 5 read its z blur at the search's limit (refused), and one under a round PSF
    a blur of 0.7 µm that it then deconvolved (a review: 1 µm stacks read 20-50 % high). The noise's
    covariance, with its share taken from the lag 0, is fitted with the object's."""
    from nemo.psf import estimate_psf

    psf, estimate = estimate_psf(_plain_shell(2.0, 0.8, 1.0, 5.0, seed), (1.0, 1.0, 1.0))
    assert psf is not None and psf[0] == pytest.approx(np.sqrt(2.0**2 - 0.8**2), rel=0.1), estimate
    assert 0.5 < estimate["noise_share"] < 0.98, estimate
    psf, estimate = estimate_psf(_plain_shell(1.0, 1.0, 1.0, 5.0, seed), (1.0, 1.0, 1.0))
    assert psf is None and "nothing to deconvolve" in estimate["reason"], estimate
    noise = 10 + np.random.default_rng(seed).standard_normal((40, 64, 64)).astype(np.float32)
    assert estimate_psf(noise, (1.0, 1.0, 1.0))[0] is None  # noise alone: no texture


@pytest.mark.parametrize("planes", [0.7, 1.5])
def test_noise_correlated_between_planes_is_not_read_as_a_z_blur(planes):
    """Noise smoothed along z (a denoised or z-resampled stack) on a shell under a round PSF fits as a z
    blur (a review: deconvolved by 0.8-1.1 µm, its defects 2-4 times farther off); the background's
    correlation between planes beyond that between columns tells it from a PSF, which blurs the object,
    not the noise: refused. The same shell with white noise, and a z-blurred one, read ~0."""
    from nemo.psf import ESTIMATE_MAX_Z_NOISE, estimate_psf

    clean = _plain_shell(1.0, 1.0, 1.0, np.inf)
    noise = ndi.gaussian_filter1d(np.random.default_rng(1).standard_normal(clean.shape), planes, axis=0)
    psf, estimate = estimate_psf((clean + noise / noise.std() / 8).astype(np.float32), (1.0, 1.0, 1.0))
    assert psf is None and estimate["z_noise"] > 3 * ESTIMATE_MAX_Z_NOISE, estimate
    assert type(estimate["z_noise"]) is float  # the record goes to YAML and JSON
    assert "correlated between planes" in estimate["reason"], estimate
    for image in (_plain_shell(1.0, 1.0, 1.0, 8.0), _plain_shell(2.0, 0.8, 1.0, 8.0)):
        assert abs(estimate_psf(image, (1.0, 1.0, 1.0))[1]["z_noise"]) < ESTIMATE_MAX_Z_NOISE / 3
    # at SNR 1000 the "background" is the object's blurred halo, not noise: no verdict (a review: refused)
    psf, estimate = estimate_psf(_plain_shell(2.9, 0.7, 1.0, 1000.0), (1.0, 1.0, 1.0))
    assert estimate["z_noise"] is None and psf[0] == pytest.approx(np.sqrt(2.9**2 - 0.7**2), rel=0.1), estimate


def test_the_estimate_reads_values_beyond_float32s_range():
    """Its arithmetic is in float32: a stack in units of 1e30 (or 1e-30) is read at its own scale, the same
    estimate, with a record JSON can write (a review: z_noise NaN at 1e30); a voxel at inf is filled."""
    import json

    from nemo.psf import estimate_psf

    image = _plain_shell(2.0, 0.8, 1.0, 5.0).astype(np.float64)
    psf, _ = estimate_psf(image, (1.0, 1.0, 1.0))
    for scale in (1e30, 1e-30):
        scaled, estimate = estimate_psf(image * scale, (1.0, 1.0, 1.0))
        assert scaled == psf and json.dumps(estimate, allow_nan=False), estimate
    image[3, 3, 3] = np.inf
    assert estimate_psf(image, (1.0, 1.0, 1.0))[0] == psf


def test_the_estimate_high_passes_only_the_slices_it_reads(monkeypatch):
    """The slices the lag covariances read are high-passed on their own, as the whole stack would be
    (the cost bound: 1 s for 450³ voxels, 12 s with the stack high-passed whole), fewer of them on
    large stacks; the z share read from coarser blocks on a large stack stays that of the full grid."""
    from nemo import psf as npsf

    rng = np.random.default_rng(3)
    volume = rng.random((40, 30, 50)).astype(np.float32) * 100
    sigma = (0.8, 1.5, 1.5)
    full = volume - ndi.gaussian_filter(volume, sigma, mode="nearest")
    for axis, keep in ((0, np.array([0, 1, 17, 39])), (1, np.array([0, 12, 29]))):
        part = np.take(full, keep, axis=axis)
        high, low = npsf._highpassed_slices(volume, sigma, axis, keep)
        np.testing.assert_allclose(high, part - part.mean(), atol=1e-3)
        np.testing.assert_allclose(low, np.take(volume - full, keep, axis=axis), atol=1e-3)
    assert len(npsf._kept_slices((40, 30, 50), 0)) == 40 and len(npsf._kept_slices((450, 450, 450), 0)) == 20
    assert len(npsf._kept_slices((30, 1536, 1536), 0)) == 4 and len(npsf._lags(45)) == npsf.ESTIMATE_MAX_LAGS
    image = _textured(2.2, 0.8, 2.5, 1.0)
    share = npsf.z_facing_share(image, (2.5, 1.0, 1.0), 6.0)
    monkeypatch.setattr(npsf, "ESTIMATE_SHARE_VOXELS", image.size // 20)  # as on a stack 20 times larger
    coarse = npsf.z_facing_share(image, (2.5, 1.0, 1.0), 6.0)
    assert 0.25 < share < 0.4 and coarse == pytest.approx(share, abs=0.02), (share, coarse)


def test_no_z_blur_is_estimated_from_a_sheet_or_an_isotropic_psf(tmp_path):
    """A flat textured membrane under an isotropic PSF (its autocovariance far from isotropic) and
    bodies 1.5 and 1.25 times as long along z as across (their walls face z less: a review's prolate
    shells read 2.5 times their z blur; a 1.25 one a blur of 1.3 µm under a round PSF) give no
    estimate, and a ball under a PSF as wide along z as across it nothing to deconvolve: the stack is
    not deconvolved and the record says why."""
    from nemo.psf import estimate_psf

    sheet = _textured(0.8, 0.8, 2.5, 1.0, shape="sheet")
    psf, estimate = estimate_psf(sheet, (2.5, 1.0, 1.0))
    assert psf is None and "not that of an isotropic object" in estimate["reason"], estimate
    from nemo.psf import ESTIMATE_Z_SHARE

    for shape, (sz, sxy) in (("prolate", (2.2, 0.8)), ("prolate125", (1.0, 1.0))):  # longer along z: refused
        estimate = estimate_psf(_textured(sz, sxy, 2.5, 1.0, shape=shape), (2.5, 1.0, 1.0))[1]
        assert estimate["beta"] is None and estimate["z_share"] < ESTIMATE_Z_SHARE[0], (shape, estimate)
        assert "does not face every way" in estimate["reason"], estimate
    ball = _textured(1.0, 1.0, 2.0, 1.0)
    out, record = deconvolve(ball, (2.0, 1.0, 1.0), "auto")
    assert out is ball and record["psf"] is None and record["estimated"] and record["iterations"] == 0
    assert "nothing to deconvolve" in record["estimate"]["reason"], record


def test_a_deconvolution_estimated_reads_back_for_auto_only(tmp_path):
    """A file nemo deconvolve --psf auto wrote serves --psf auto, not the numbers it estimated, and a
    file made with numbers does not serve --psf auto; a PSF given as an array is a PSF, and the
    estimate is the same in metres as in µm."""
    from nemo.psf import estimate_psf, read_deconvolved, write_deconvolved

    image, spacing = _textured(2.2, 0.8, 2.5, 1.0), (2.5, 1.0, 1.0)
    out, record = deconvolve(image, spacing, "auto")
    path = tmp_path / "d.tif"
    write_deconvolved(path, out, record, image, spacing, 0, 0, "x.tif")
    assert read_deconvolved(path, image, spacing, "auto", 0, 0)[1] == record
    with pytest.raises(NemoError, match=r"made for the PSF auto, this step has \["):
        read_deconvolved(path, image, spacing, record["psf"], 0, 0)
    given = deconvolve(image, spacing, np.array(record["psf"]))  # an array, as numpy users give it
    write_deconvolved(path, *given, image, spacing, 0, 0, "x.tif")
    with pytest.raises(NemoError, match=r"made for the PSF \[.*this step has auto"):
        read_deconvolved(path, image, spacing, "auto", 0, 0)
    assert check_psf(np.array([2.0, 1.0, 1.0])) == (2.0, 1.0, 1.0)
    # the estimate in any unit: the same in metres as in µm
    assert estimate_psf(image, (2.5e-6, 1e-6, 1e-6))[0][0] == pytest.approx(record["psf"][0] * 1e-6, rel=1e-5)


def test_one_psf_or_one_per_channel():
    """psf: one PSF for every channel, or a list in channel order (null: that channel is not
    deconvolved); a list too short for a channel is refused with the fix."""
    from nemo.psf import channel_psf, check_psf_spec

    assert channel_psf([2, 1, 1], 3) == (2.0, 1.0, 1.0)
    assert channel_psf(None, 0) is None
    spec = [[2, 1, 1], None, [3.5, 1.2, 1.2]]
    assert check_psf_spec(spec) == [(2.0, 1.0, 1.0), None, (3.5, 1.2, 1.2)]
    assert [channel_psf(spec, c) for c in range(3)] == [(2.0, 1.0, 1.0), None, (3.5, 1.2, 1.2)]
    with pytest.raises(NemoError, match=r"channels 0 to 2, not for channel 3.*one per channel"):
        channel_psf(spec, 3)
    with pytest.raises(NemoError, match=r"psf\[1\] must be three numbers"):
        check_psf_spec([[2, 1, 1], [2, 1]])
