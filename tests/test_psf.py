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


def test_auto_assumes_a_nyquist_sampled_psf_from_the_voxel_size(tmp_path):
    """psf: auto is σ = 2 / 2.355 voxel on each axis (two voxels per FWHM): a z edge blurred by that
    PSF at 2.5 µm planes is sharpened in place as by the PSF given; the record names it assumed, and
    a deconvolution written with auto reads back for auto at its spacing only."""
    from nemo.psf import assumed_psf, check_psf_spec, read_deconvolved, write_deconvolved

    spacing = (2.5, 1.0, 1.0)
    sigma = assumed_psf(spacing)
    assert sigma == pytest.approx((2.5 * 2 / 2.355, 2 / 2.355, 2 / 2.355))
    assert 2.355 * sigma[0] == pytest.approx(2 * spacing[0])  # the FWHM spans two planes
    assert check_psf("auto") == "auto" and check_psf_spec([None, "auto"]) == [None, "auto"]
    stack, z = _z_edge(sigma[0], spacing[0], n=150)
    out, record = deconvolve(stack, spacing, "auto")
    given, _ = deconvolve(stack, spacing, sigma)
    assert np.array_equal(out, given) and record["assumed"] and record["psf"] == list(sigma)
    before, mid_before = _edge_sigma_and_middle(stack.mean(axis=(1, 2)), z)
    after, mid_after = _edge_sigma_and_middle(out.mean(axis=(1, 2)), z)
    assert after < 0.7 * before and abs(mid_after - 30.0) < 0.1 * sigma[0], (before, after, mid_after)
    path = tmp_path / "d.tif"
    write_deconvolved(path, out, record, stack, spacing, 0, 0, "x.tif")
    assert read_deconvolved(path, stack, spacing, "auto", 0, 0)[1] == record
    assert read_deconvolved(path, stack, spacing, sigma, 0, 0)[1] == record  # the same numbers given
    with pytest.raises(NemoError, match="made for the PSF"):
        read_deconvolved(path, stack, spacing, (3.0, 1.0, 1.0), 0, 0)
    assert not deconvolve(stack, spacing, (3.0, 1.0, 1.0))[1]["assumed"]


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
