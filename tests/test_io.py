"""Hyperstack I/O: axes, calibration, lazy (t, c) reads, errors (nemo.io)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import tifffile

from nemo.errors import NemoError, NemoWarning
from nemo.io import read_info, read_mask, read_stack, write_hyperstack

SPACING = (2.5, 0.4, 0.3)  # distinct dz, dy, dx so that any axis mix-up shows


def _data(shape, rng, dtype=np.uint16):
    return rng.integers(0, 60000 if dtype == np.uint16 else 250, size=shape).astype(dtype)


def _slice(data, axes, t, c):
    """The (Z, Y, X) stack of (t, c) taken directly from the array in memory."""
    index = tuple({"T": t, "C": c}.get(a, slice(None)) for a in axes)
    kept = [a for a in axes if a not in "TC"]
    return np.transpose(data[index], [kept.index(a) for a in "ZYX"])


CASES = [
    ("ZYX", (5, 12, 14), False),
    ("ZCYX", (5, 3, 12, 14), False),
    ("TZYX", (4, 5, 12, 14), False),
    ("TZCYX", (3, 5, 2, 12, 14), False),
    ("TZCYX", (3, 5, 2, 12, 14), True),
    ("ZYX", (5, 12, 14), True),
    ("CZYX", (2, 5, 12, 14), True),  # OME allows other axis orders
    ("TCZYX", (2, 3, 5, 12, 14), True),
]


@pytest.mark.parametrize("axes,shape,ome", CASES, ids=[f"{a}{'-ome' if o else ''}" for a, _, o in CASES])
def test_round_trip_axes_spacing_and_every_frame(tmp_path, rng, axes, shape, ome):
    data = _data(shape, rng)
    path = tmp_path / "stack.ome.tif" if ome else tmp_path / "stack.tif"
    write_hyperstack(path, data, SPACING, unit="um", axes=axes, ome=ome)
    info = read_info(path)
    sizes = dict(zip(axes, shape))
    assert info.shape == {a: sizes.get(a, 1) for a in "TCZYX"}
    assert info.dtype == "uint16"
    assert info.unit == "um" and info.calibrated
    np.testing.assert_allclose(info.spacing, SPACING, rtol=1e-6)
    assert set(info.to_json()) == {"path", "axes", "shape", "dtype", "spacing", "unit", "calibrated"}
    for t in range(sizes.get("T", 1)):
        for c in range(sizes.get("C", 1)):
            stack, sinfo = read_stack(path, t, c)
            assert stack.shape == (sizes["Z"], sizes["Y"], sizes["X"])
            np.testing.assert_array_equal(stack, _slice(data, axes, t, c))
            np.testing.assert_allclose(sinfo.spacing, SPACING, rtol=1e-6)


def test_compressed_file_reads_the_same_frame(tmp_path, rng):
    data = _data((3, 4, 2, 16, 16), rng)
    write_hyperstack(tmp_path / "z.tif", data, SPACING, compression="zlib")
    stack, _ = read_stack(tmp_path / "z.tif", 2, 1)
    np.testing.assert_array_equal(stack, data[2, :, 1])


def test_uint8_and_float_dtypes(tmp_path, rng):
    for dtype in (np.uint8, np.float32):
        data = (rng.random((2, 4, 8, 9)) * 200).astype(dtype)
        write_hyperstack(tmp_path / "d.tif", data, (1, 1, 1), axes="ZCYX")
        stack, info = read_stack(tmp_path / "d.tif", c=1)
        assert stack.dtype == dtype and info.dtype == np.dtype(dtype).name
        np.testing.assert_array_equal(stack, data[:, 1])


@pytest.mark.parametrize("unit,scale", [("nm", 1e-3), ("mm", 1e3), ("micron", 1.0), ("um", 1.0),
                                        ("\\u00B5m", 1.0), ("microns", 1.0)])
def test_imagej_unit_normalised_to_um(tmp_path, rng, unit, scale):
    data = _data((4, 6, 7), rng)
    dz, dy, dx = 3.0, 2.0, 1.5
    # written with tifffile directly, the way ImageJ stores it (µm may come escaped)
    tifffile.imwrite(tmp_path / "u.tif", data, imagej=True, resolution=(1 / dx, 1 / dy),
                     metadata={"axes": "ZYX", "spacing": dz, "unit": unit})
    info = read_info(tmp_path / "u.tif")
    assert info.unit == "um"
    np.testing.assert_allclose(info.spacing, (dz * scale, dy * scale, dx * scale), rtol=1e-6)


@pytest.mark.parametrize("unit,scale", [("nm", 1e-3), ("mm", 1e3), ("µm", 1.0)])
def test_ome_unit_normalised_to_um(tmp_path, rng, unit, scale):
    data = _data((4, 6, 7), rng)
    write_hyperstack(tmp_path / "u.ome.tif", data, (300.0, 120.0, 100.0), unit=unit, axes="ZYX", ome=True)
    info = read_info(tmp_path / "u.ome.tif")
    assert info.unit == "um"
    np.testing.assert_allclose(info.spacing, (300 * scale, 120 * scale, 100 * scale), rtol=1e-6)


def test_uncalibrated_file_warns_and_uses_pixels(tmp_path, rng):
    data = _data((5, 6, 7), rng)
    # plain multi-page TIFF, no calibration
    tifffile.imwrite(tmp_path / "raw.tif", data, photometric="minisblack")
    info = read_info(tmp_path / "raw.tif")
    assert info.unit == "pixel" and not info.calibrated and info.spacing == (1.0, 1.0, 1.0)
    with pytest.warns(NemoWarning, match="`spacing`"):
        stack, info = read_stack(tmp_path / "raw.tif")
    np.testing.assert_array_equal(stack, data)
    # an explicit spacing overrides silently
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _, info = read_stack(tmp_path / "raw.tif", spacing=(2.0, 0.5, 0.5))
    assert info.spacing == (2.0, 0.5, 0.5) and info.calibrated


def test_spacing_override_beats_file_calibration(tmp_path, rng):
    write_hyperstack(tmp_path / "s.tif", _data((3, 5, 5), rng), SPACING, axes="ZYX")
    _, info = read_stack(tmp_path / "s.tif", spacing=[1, 2, 3])
    assert info.spacing == (1.0, 2.0, 3.0)
    for bad in ([1, 2], [1, 0, 1], [1, -2, 1], ["a", 1, 1], [1, float("nan"), 1]):
        with pytest.raises(NemoError, match="spacing"):
            read_stack(tmp_path / "s.tif", spacing=bad)


def test_imagej_pixel_unit_is_uncalibrated_and_spacing_override_sets_um(tmp_path):
    data = np.zeros((4, 5, 6), np.uint8)
    tifffile.imwrite(tmp_path / "px.tif", data, imagej=True, metadata={"axes": "ZYX", "unit": "pixel"})
    with pytest.warns(NemoWarning, match="no spatial calibration"):
        _, info = read_stack(tmp_path / "px.tif")
    assert info.unit == "pixel" and not info.calibrated
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _, info = read_stack(tmp_path / "px.tif", spacing=(2, 0.5, 0.5))
    assert info.unit == "um" and info.spacing == (2.0, 0.5, 0.5)


def test_an_imagej_voxel_depth_in_pixels_keeps_the_z_step(tmp_path):
    """ImageJ's "pixel" unit with a voxel depth (spacing=2: every second plane of a stack kept) is uncalibrated
    but its z step is not 1: it read (1, 1, 1), so the object came out half as deep (an independent review:
    area −26 %, wall thickness 7.6 µm for 11.8). The ratio is kept, as for an OME file without units."""
    data = np.zeros((4, 5, 6), np.uint8)
    tifffile.imwrite(tmp_path / "px2.tif", data, imagej=True, metadata={"axes": "ZYX", "unit": "pixel", "spacing": 2.0})
    with pytest.warns(NemoWarning, match=r"no spatial calibration: using spacing \[2.0, 1.0, 1.0\]"):
        _, info = read_stack(tmp_path / "px2.tif")
    assert info.unit == "pixel" and not info.calibrated and info.spacing == (2.0, 1.0, 1.0)
    for odd in (0.0, -1.0, float("nan")):  # no usable depth: one pixel, as before
        tifffile.imwrite(tmp_path / "odd.tif", data, imagej=True, metadata={"axes": "ZYX", "unit": "pixel", "spacing": odd})
        assert read_info(tmp_path / "odd.tif").spacing == (1.0, 1.0, 1.0)


def test_a_print_resolution_in_dots_per_inch_is_no_calibration(tmp_path, rng):
    """A generic writer's 72 dpi (ResolutionUnit inch) is a print size: spacing 1, unit pixel,
    uncalibrated (it read as 1/72 per voxel, labelled pixel)."""
    tifffile.imwrite(tmp_path / "dpi.tif", _data((4, 6, 7), rng), resolution=(72.0, 72.0), resolutionunit="INCH",
                     metadata={"axes": "ZYX"})
    info = read_info(tmp_path / "dpi.tif")
    assert info.spacing == (1.0, 1.0, 1.0) and info.unit == "pixel" and not info.calibrated


def test_an_ome_tiff_without_a_z_size_warns(tmp_path, rng):
    ome = tmp_path / "noz.ome.tif"
    tifffile.imwrite(ome, _data((4, 6, 7), rng), ome=True,
                     metadata={"axes": "ZYX", "PhysicalSizeX": 0.5, "PhysicalSizeY": 0.5})
    with pytest.warns(NemoWarning, match="no z spacing"):
        info = read_info(ome)
    assert info.spacing == (0.5, 0.5, 0.5)


def test_compressed_tiffs_are_read(tmp_path, rng):
    """LZW and Zstd, as microscopes and Fiji write them (imagecodecs, a dependency)."""
    data = _data((4, 6, 7), rng)
    for compression in ("lzw", "zstd"):
        path = tmp_path / f"{compression}.tif"
        tifffile.imwrite(path, data, imagej=True, compression=compression,
                         resolution=(2.0, 2.0), metadata={"axes": "ZYX", "unit": "um", "spacing": 1.0})
        stack, info = read_stack(path)
        np.testing.assert_array_equal(stack, data)
        assert info.spacing == (1.0, 0.5, 0.5)


def test_a_compressed_tiff_without_its_codec_is_named_not_called_corrupt(tmp_path, rng, monkeypatch):
    """Without imagecodecs, tifffile cannot decode LZW or Zstd and says which package it needs; the
    file is fine, so the error names the codec and the fix, not a truncated file."""
    from tifffile.tifffile import COMPRESSION, CompressionCodec

    path = tmp_path / "zstd.tif"
    tifffile.imwrite(path, _data((4, 6, 7), rng), imagej=True, compression="zstd", resolution=(2.0, 2.0),
                     metadata={"axes": "ZYX", "unit": "um", "spacing": 1.0})

    def no_codec(self, key):  # what tifffile raises when the package is not installed
        raise KeyError(f"{COMPRESSION(key)!r} requires the 'imagecodecs' package")

    monkeypatch.setattr(CompressionCodec, "__getitem__", no_codec)
    with pytest.raises(NemoError, match=r"compressed with a codec that is not installed.*pip install imagecodecs"):
        read_stack(path)


def test_missing_dz_falls_back_to_dx_with_a_warning(tmp_path, rng):
    data = _data((3, 5, 5), rng)
    tifffile.imwrite(tmp_path / "nodz.tif", data, imagej=True, resolution=(2.0, 2.0),
                     metadata={"axes": "ZYX", "unit": "micron"})
    with pytest.warns(NemoWarning, match="no z spacing"):
        info = read_info(tmp_path / "nodz.tif")
    assert info.spacing == pytest.approx((0.5, 0.5, 0.5))
    with pytest.warns(NemoWarning, match="no z spacing"):
        _, info = read_stack(tmp_path / "nodz.tif")
    assert info.spacing == (0.5, 0.5, 0.5)
    # with a z spacing, no warning
    write_hyperstack(tmp_path / "ok.tif", data, (1.0, 0.5, 0.5), axes="ZYX")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read_stack(tmp_path / "ok.tif")


# ----------------------------------------------------------------------------- errors
def test_errors_name_the_problem(tmp_path, rng):
    with pytest.raises(NemoError, match="not found"):
        read_info(tmp_path / "missing.tif")
    with pytest.raises(NemoError, match="folder"):
        read_info(tmp_path)
    (tmp_path / "notes.tif").write_text("this is not an image\n")
    with pytest.raises(NemoError, match="not a readable TIFF"):
        read_stack(tmp_path / "notes.tif")
    tifffile.imwrite(tmp_path / "flat.tif", _data((6, 7), rng))
    with pytest.raises(NemoError, match="2-D"):
        read_stack(tmp_path / "flat.tif")
    write_hyperstack(tmp_path / "h.tif", _data((2, 3, 2, 4, 4), rng), SPACING)
    with pytest.raises(NemoError, match=r"t = 2 is out of range.*2 time points"):
        read_stack(tmp_path / "h.tif", t=2)
    with pytest.raises(NemoError, match=r"c = -1 is out of range.*2 channels"):
        read_stack(tmp_path / "h.tif", c=-1)
    with pytest.raises(NemoError, match="ImageJ hyperstacks need axes"):
        write_hyperstack(tmp_path / "bad.tif", _data((2, 3, 4, 4), rng), SPACING, axes="CZYX")


# ----------------------------------------------------------------------------- truncated files
def _plain(path, data):
    """A plain multi-page TIFF (no ImageJ/OME/shape metadata), the way many tools write one."""
    tifffile.imwrite(path, data, photometric="minisblack", metadata=None)


def _page_offset(path, index):
    with tifffile.TiffFile(path) as tif:
        return tif.pages[index].offset


def _mid_page(path, index):
    with tifffile.TiffFile(path) as tif:
        page = tif.pages[index]
        return page.dataoffsets[0] + page.databytecounts[0] // 2


def _half(path, index=None):
    return path.stat().st_size // 2


STACK = (94, 16, 16)  # the issue's file: 94 z slices
HYPER = (3, 5, 2, 16, 16)
# name: (write the intact file, its data shape, its axes, where to cut)
TRUNCATED = {
    "plain-page-boundary": (_plain, STACK, "ZYX", lambda p: _page_offset(p, 61)),  # was read as Z = 61
    "plain-mid-page": (_plain, STACK, "ZYX", lambda p: _mid_page(p, 40)),  # was a TiffFileError traceback
    "tifffile-page-boundary": (lambda p, d: tifffile.imwrite(p, d, photometric="minisblack"), STACK, "ZYX",
                               lambda p: _page_offset(p, 61)),
    "tifffile-mid-page": (lambda p, d: tifffile.imwrite(p, d, photometric="minisblack"), STACK, "ZYX",
                          lambda p: _mid_page(p, 40)),
    "imagej-hyperstack": (lambda p, d: write_hyperstack(p, d, SPACING), HYPER, "TZCYX", _half),  # was "2-D"
    "ome-tiff": (lambda p, d: write_hyperstack(p, d, SPACING, ome=True), HYPER, "TZCYX", _half),
    "zlib-imagej": (lambda p, d: write_hyperstack(p, d, SPACING, compression="zlib"), HYPER, "TZCYX", _half),
    "zlib-mid-page": (lambda p, d: write_hyperstack(p, d, SPACING, compression="zlib"), HYPER, "TZCYX",
                      lambda p: _mid_page(p, 17)),
    "zlib-ome": (lambda p, d: write_hyperstack(p, d, SPACING, ome=True, compression="zlib"), HYPER, "TZCYX",
                 _half),
}


def _write_intact(tmp_path, rng, name):
    write, shape, axes, cut = TRUNCATED[name]
    data = _data(shape, rng)
    path = tmp_path / f"{name}.tif"
    write(path, data)
    return path, data, axes, cut


def _truncate(path, n):
    out = path.with_name("cut-" + path.name)
    out.write_bytes(path.read_bytes()[:n])
    return out


@pytest.mark.parametrize("name", list(TRUNCATED))
def test_truncated_file_is_refused_not_read_short(tmp_path, rng, name):
    path, data, _, cut = _write_intact(tmp_path, rng, name)
    bad = _truncate(path, cut(path))
    before = bad.read_bytes()
    for read in (read_info, read_stack, lambda p: read_mask(p, 0, 0, data.shape[-3:])):
        with pytest.raises(NemoError, match=r"is truncated or corrupt: .*copy it again") as exc:
            read(bad)
        assert str(bad) in str(exc.value) and "\n" not in str(exc.value)
    assert bad.read_bytes() == before  # reading never touches the input


@pytest.mark.parametrize("name", list(TRUNCATED))
def test_intact_file_of_each_kind_still_reads_identically(tmp_path, rng, name):
    path, data, axes, _ = _write_intact(tmp_path, rng, name)
    before = path.read_bytes()
    sizes = dict(zip(axes, data.shape))
    info = read_info(path)
    assert info.shape == {a: sizes.get(a, 1) for a in "TCZYX"}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NemoWarning)  # the plain files are uncalibrated
        for t in range(sizes.get("T", 1)):
            for c in range(sizes.get("C", 1)):
                np.testing.assert_array_equal(read_stack(path, t, c)[0], _slice(data, axes, t, c))
    assert path.read_bytes() == before


def test_truncation_messages_name_what_is_missing(tmp_path, rng):
    path, *_ = _write_intact(tmp_path, rng, "imagej-hyperstack")
    with pytest.raises(NemoError, match=r"ImageJ header announces 30 images but the file holds only \d+ "
                                        r"\(file size \d+ bytes, the pixel data need \d+ bytes\)"):
        read_info(_truncate(path, _half(path)))
    path, *_ = _write_intact(tmp_path, rng, "tifffile-mid-page")
    with pytest.raises(NemoError, match=r"pages announce 94 images but the file holds only 40 "):
        read_info(_truncate(path, _mid_page(path, 40)))
    path, *_ = _write_intact(tmp_path, rng, "plain-page-boundary")
    with pytest.raises(NemoError, match=r"breaks off after 61 of them"):
        read_info(_truncate(path, _page_offset(path, 61)))


def test_corrupt_compressed_pixels_are_refused(tmp_path, rng):
    path, data, *_ = _write_intact(tmp_path, rng, "zlib-imagej")
    raw = bytearray(path.read_bytes())
    start = _mid_page(path, 3)  # page 3 = t 0, z 1, c 1
    raw[start:start + 64] = bytes(64)
    path.write_bytes(bytes(raw))
    assert read_info(path).shape["T"] == 3  # headers are intact
    with pytest.raises(NemoError, match=r"truncated or corrupt: reading its pixels failed"):
        read_stack(path, 0, 1)
    np.testing.assert_array_equal(read_stack(path, 1, 1)[0], data[1, :, 1])  # other pages still read


def test_empty_and_header_only_files(tmp_path, rng):
    path, *_ = _write_intact(tmp_path, rng, "imagej-hyperstack")
    (tmp_path / "empty.tif").write_bytes(b"")
    with pytest.raises(NemoError, match="is empty"):
        read_info(tmp_path / "empty.tif")
    with pytest.raises(NemoError, match="truncated or corrupt"):
        read_info(_truncate(path, 12))


@pytest.mark.parametrize("name", ["plain-page-boundary", "plain-mid-page", "imagej-hyperstack", "zlib-ome"])
def test_cli_info_on_truncated_file_is_one_error_line(tmp_path, rng, capsys, name):
    from nemo.cli import main

    path, _, _, cut = _write_intact(tmp_path, rng, name)
    bad = _truncate(path, cut(path))
    capsys.readouterr()
    assert main(["info", str(bad)]) == 2
    out, err = capsys.readouterr()
    assert "Traceback" not in err and out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("nemo info: error:") and "is truncated or corrupt: " in lines[0], err


def test_a_multi_file_ome_series_is_whole_not_truncated(tmp_path):
    """Micro-Manager / Bio-Formats split acquisitions: each page's data lies in its own file."""
    import uuid

    data = (np.random.default_rng(0).random((12, 32, 32)) * 200).astype(np.uint8)
    ua, ub = (f"urn:uuid:{uuid.uuid4()}" for _ in range(2))

    def xml(root):
        return (f'<?xml version="1.0" encoding="UTF-8"?><OME xmlns="http://www.openmicroscopy.org/Schemas/OME/'
                f'2016-06" UUID="{root}"><Image ID="Image:0"><Pixels ID="Pixels:0" DimensionOrder="XYZCT" '
                'Type="uint8" SizeX="32" SizeY="32" SizeZ="12" SizeC="1" SizeT="1" PhysicalSizeX="1" '
                'PhysicalSizeY="1" PhysicalSizeZ="2"><Channel ID="Channel:0:0" SamplesPerPixel="1"/>'
                f'<TiffData FirstZ="0" IFD="0" PlaneCount="2"><UUID FileName="a.ome.tif">{ua}</UUID></TiffData>'
                f'<TiffData FirstZ="2" IFD="0" PlaneCount="10"><UUID FileName="b.ome.tif">{ub}</UUID></TiffData>'
                '</Pixels></Image></OME>')

    tifffile.imwrite(tmp_path / "a.ome.tif", data[:2], description=xml(ua), metadata=None)
    tifffile.imwrite(tmp_path / "b.ome.tif", data[2:], description=xml(ub), metadata=None)
    stack, info = read_stack(tmp_path / "a.ome.tif")
    assert info.shape["Z"] == 12 and np.array_equal(stack, data)
    (tmp_path / "b.ome.tif").write_bytes((tmp_path / "b.ome.tif").read_bytes()[:3000])  # cut the second file
    with pytest.raises(NemoError, match="truncated or corrupt"):
        read_stack(tmp_path / "a.ome.tif")


# ------------------------------------------------------------------ masks from segmentation tools
@pytest.fixture
def segmentation(tmp_path):
    """A label image (labels 3 and 5) and a probability map that is 0.7 inside label 3."""
    labels = np.zeros((2, 6, 10, 10), np.uint16)  # (T, Z, Y, X)
    labels[:, 1:4, 1:5, 1:5] = 3
    labels[1, 2:5, 6:9, 6:9] = 5
    probability = np.where(labels == 3, 0.7, 0.2).astype(np.float32)
    write_hyperstack(tmp_path / "labels.tif", labels, (1, 1, 1), axes="TZYX")
    write_hyperstack(tmp_path / "prob.tif", probability, (1, 1, 1), axes="TZYX")
    return tmp_path, labels


def test_mask_from_a_label_image(segmentation):
    d, labels = segmentation
    shape = labels.shape[1:]
    np.testing.assert_array_equal(read_mask(d / "labels.tif", 1, 0, shape), labels[1] != 0)
    np.testing.assert_array_equal(read_mask(d / "labels.tif", 1, 0, shape, labels=[5]), labels[1] == 5)
    np.testing.assert_array_equal(read_mask(d / "labels.tif", 1, 0, shape, labels=[3, 5]), labels[1] > 0)
    with pytest.raises(NemoError, match=r"none of the labels \[5\]; labels present: \[3\]"):
        read_mask(d / "labels.tif", 0, 0, shape, labels=[5])
    with pytest.warns(NemoWarning, match=r"no voxel of label\(s\) \[5\] of mask_labels \[3, 5\]: meshing the others"):
        np.testing.assert_array_equal(read_mask(d / "labels.tif", 0, 0, shape, labels=[3, 5]), labels[0] == 3)


def test_the_masks_channel_picks_the_class_of_a_probability_map(tmp_path):
    """ilastik's map of one channel per class (0 background, 1 object): mask_channel 1 is the object
    whatever the image's channel; a channel the mask lacks is named."""
    ball = np.zeros((6, 10, 10), np.float32)
    ball[1:5, 2:8, 2:8] = 0.9
    write_hyperstack(tmp_path / "classes.tif", np.stack([1 - ball, ball], axis=1), (1, 1, 1), axes="ZCYX")
    np.testing.assert_array_equal(read_mask(tmp_path / "classes.tif", 0, 0, ball.shape, channel=1), ball > 0.5)
    np.testing.assert_array_equal(read_mask(tmp_path / "classes.tif", 0, 0, ball.shape), ball < 0.5)  # c = 0
    with pytest.raises(NemoError, match="mask_channel 2 is not a channel of the mask .* 2 channel"):
        read_mask(tmp_path / "classes.tif", 0, 0, ball.shape, channel=2)


def _saved_as(labels: np.ndarray, dtype: str) -> np.ndarray:
    """A label image as saved: integers, or floats with a NaN background (a label image after a float
    operation in Fiji or numpy)."""
    return labels if dtype == "uint16" else np.where(labels > 0, labels, np.nan).astype(dtype)


@pytest.mark.parametrize("dtype", ["uint16", "float32"])
def test_touching_labels_are_warned_about(tmp_path, dtype):
    """Two touching cells of a label image merge into one surface when every label is object: warned,
    naming the pair; a label selection, separate labels and a binary mask are not. A label image saved
    as float is a label image."""
    labels = np.zeros((6, 10, 16), np.uint16)
    labels[1:5, 2:8, 2:8], labels[1:5, 2:8, 8:14] = 1, 2  # touching along x
    write_hyperstack(tmp_path / "touch.tif", _saved_as(labels, dtype), (1, 1, 1), axes="ZYX")
    with pytest.warns(NemoWarning, match="labels touch \\(1–2\\).*mask_labels"):
        read_mask(tmp_path / "touch.tif", 0, 0, labels.shape)
    apart = labels.copy()
    apart[:, :, 8] = 0
    write_hyperstack(tmp_path / "apart.tif", apart, (1, 1, 1), axes="ZYX")
    write_hyperstack(tmp_path / "binary.tif", (labels > 0).astype(np.uint8), (1, 1, 1), axes="ZYX")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read_mask(tmp_path / "touch.tif", 0, 0, labels.shape, labels=[2])
        read_mask(tmp_path / "apart.tif", 0, 0, labels.shape)
        read_mask(tmp_path / "binary.tif", 0, 0, labels.shape)


@pytest.mark.parametrize("dtype", ["uint16", "float32"])
def test_large_touching_labels_are_returned_as_regions(tmp_path, dtype):
    """``with_regions``: a voxel inside each label holding ≥ 10 % of a group of touching labels in which
    two or more do (two touching droplets, and a small third one that touches them: not counted);
    none for the 40 cells of one tissue (each 2.5 % of it), separate labels, a label selection or
    labels kept apart (keep: all)."""
    z, y, x = np.indices((20, 24, 44))
    labels = np.zeros((20, 24, 44), np.uint16)
    labels[np.sqrt((x - 12) ** 2 + (y - 12) ** 2 + (z - 10) ** 2) <= 8] = 1
    labels[np.sqrt((x - 28) ** 2 + (y - 12) ** 2 + (z - 10) ** 2) <= 8] = 2  # touching 1 at x = 20
    labels[(np.abs(x - 12) <= 1) & (y >= 21) & (y <= 22) & (np.abs(z - 10) <= 1)] = 3  # small, on top of 1
    write_hyperstack(tmp_path / "drops.tif", _saved_as(labels, dtype), (1, 1, 1), axes="ZYX")
    with pytest.warns(NemoWarning, match="labels touch \\(1–2, 1–3\\)"):
        mask, voxels = read_mask(tmp_path / "drops.tif", 0, 0, labels.shape, with_regions=True)
    assert mask.sum() == (labels > 0).sum() and voxels.shape == (2, 3)
    assert sorted(labels[tuple(voxels.T)].tolist()) == [1, 2]  # one voxel inside each droplet
    np.testing.assert_allclose(sorted(voxels[:, 2]), [12, 28], atol=1)
    tissue = np.zeros((20, 24, 44), np.uint16)
    tissue[2:18, 2:22, 2:42] = 1 + (x[2:18, 2:22, 2:42] - 2) // 4 + 10 * ((y[2:18, 2:22, 2:42] - 2) // 5)  # 40 cells
    write_hyperstack(tmp_path / "tissue.tif", tissue, (1, 1, 1), axes="ZYX")
    with pytest.warns(NemoWarning, match="labels touch"):
        assert read_mask(tmp_path / "tissue.tif", 0, 0, labels.shape, with_regions=True)[1].shape == (0, 3)
    apart = np.where(np.abs(x - 20) <= 1, 0, labels).astype(np.uint16)
    write_hyperstack(tmp_path / "apart.tif", apart, (1, 1, 1), axes="ZYX")
    assert read_mask(tmp_path / "apart.tif", 0, 0, labels.shape, with_regions=True)[1].shape == (0, 3)
    for kwargs in ({"labels": [1, 2]}, {"apart": (1, 1, 1)}):
        assert read_mask(tmp_path / "drops.tif", 0, 0, labels.shape, with_regions=True, **kwargs)[1].shape == (0, 3)


@pytest.mark.parametrize("dtype", ["uint16", "float32"])
def test_touching_labels_are_kept_apart_with_keep_all(tmp_path, dtype):
    """``apart`` (mesh.keep: all): the voxels within reach of another label are left out, so labels 1
    and 2 mesh as two objects (at the default blur, 1 × 1 × 1 µm voxels: one voxel each side);
    nothing else changes and nothing is warned. A binary mask is read as before; a label image saved
    as float too."""
    from nemo import stages
    from nemo.io import label_gap
    from nemo.surface import default_mask_sigma

    reach = label_gap((1.0, 1.0, 1.0), default_mask_sigma((1.0, 1.0, 1.0)))
    assert reach == (1, 1, 1) and label_gap((2.0, 1.0, 1.0), 1.0) == (1, 2, 2) and label_gap((1, 1, 1), 3.0) == (5, 5, 5)

    labels = np.zeros((12, 16, 30), np.uint16)
    labels[2:10, 3:13, 3:15], labels[2:10, 3:13, 15:27] = 1, 2  # two boxes touching along x
    write_hyperstack(tmp_path / "touch.tif", _saved_as(labels, dtype), (1, 1, 1), axes="ZYX")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        mask = read_mask(tmp_path / "touch.tif", 0, 0, labels.shape, apart=reach)
    expected = labels > 0
    expected[2:10, 3:13, 14:16] = False  # the two faces that meet
    np.testing.assert_array_equal(mask, expected)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NemoWarning)
        _, p = stages.mesh(None, (1.0, 1.0, 1.0), {"split": "none", "keep": "all"}, mask=mask)
        _, merged = stages.mesh(None, (1.0, 1.0, 1.0), {"split": "none", "keep": "all"},
                                mask=read_mask(tmp_path / "touch.tif", 0, 0, labels.shape))
    assert p["n_objects"] == 2 and merged["n_objects"] == 1
    # with mask_labels, a selected label is not cut where it meets one left out
    np.testing.assert_array_equal(read_mask(tmp_path / "touch.tif", 0, 0, labels.shape, labels=[1], apart=reach),
                                  labels == 1)
    binary = (labels > 0).astype(np.uint8)
    write_hyperstack(tmp_path / "binary.tif", binary, (1, 1, 1), axes="ZYX")
    np.testing.assert_array_equal(read_mask(tmp_path / "binary.tif", 0, 0, labels.shape, apart=reach), binary > 0)


def test_an_unreadable_mask_is_named_as_the_mask(tmp_path):
    """A missing mask, or one whose axes cannot be read (a channel-last ilastik export saved as plain
    TIFF), is named as the mask: the reader's own message speaks of an image."""
    with pytest.raises(NemoError, match=r"^the mask \(.*nope.tif\): image file not found"):
        read_mask(tmp_path / "nope.tif", 0, 0, (5, 6, 7))
    tifffile.imwrite(tmp_path / "classes.tif", np.zeros((5, 6, 7, 2), np.float32))  # Z, Y, X, class
    with pytest.raises(NemoError, match=r"^the mask \(.*classes.tif\): image axes 'QQYX'"):
        read_mask(tmp_path / "classes.tif", 0, 0, (5, 6, 7))


def test_mask_from_a_probability_map(segmentation):
    d, labels = segmentation
    shape = labels.shape[1:]
    np.testing.assert_array_equal(read_mask(d / "prob.tif", 0, 0, shape), labels[0] == 3)  # default 0.5
    with pytest.raises(NemoError, match=r"selects every voxel \(all are above the threshold 0.1; the smallest "
                       r"value is 0.2\).*give mask_threshold"):
        read_mask(d / "prob.tif", 0, 0, shape, threshold=0.1)
    with pytest.raises(NemoError, match="is empty: no voxel is above the threshold 0.9"):
        read_mask(d / "prob.tif", 0, 0, shape, threshold=0.9)
    with pytest.raises(NemoError, match="floating-point values, not labels"):
        read_mask(d / "prob.tif", 0, 0, shape, labels=[1])


def test_probability_maps_on_another_scale_are_refused_with_the_fix(tmp_path, rng):
    """A map in 0..255 (float or uint8) read without a threshold is refused with the fix; a label
    image (also saved as float) is read as labels, and mask_threshold reads the maps."""
    z, y, x = np.meshgrid(*(np.arange(n) for n in (12, 20, 20)), indexing="ij")
    ball = 255 / (1 + np.exp(np.sqrt((z - 6) ** 2 + (y - 10) ** 2 + (x - 10) ** 2) - 6))
    inside = ball > 127.5
    for name, data in (("p8", np.clip(ball + rng.normal(0, 3, ball.shape), 0, 255).astype(np.uint8)),
                       ("pf", ball.astype(np.float32))):
        write_hyperstack(tmp_path / f"{name}.tif", data, (1, 1, 1), axes="ZYX")
        with pytest.raises(NemoError, match=r"values up to .*give mask_threshold \(e\.g\. half its range"):
            read_mask(tmp_path / f"{name}.tif", 0, 0, data.shape)
        got = read_mask(tmp_path / f"{name}.tif", 0, 0, data.shape, threshold=127.5)
        assert np.count_nonzero(got != inside) <= 0.02 * inside.sum(), name
    as_float = np.rint(np.clip(ball + rng.normal(0, 3, ball.shape), 0, 255)).astype(np.float32)  # whole numbers
    write_hyperstack(tmp_path / "p8f.tif", as_float, (1, 1, 1), axes="ZYX")
    with pytest.raises(NemoError, match=r"float image with values up to .*give mask_threshold"):
        read_mask(tmp_path / "p8f.tif", 0, 0, as_float.shape)
    for name, data in (("labels", np.where(inside, 7, 0).astype(np.uint16)),
                       ("float_labels", np.where(inside, 7.0, 0.0).astype(np.float32)),
                       ("nan_labels", np.where(inside, 7.0, np.nan).astype(np.float32))):
        write_hyperstack(tmp_path / f"{name}.tif", data, (1, 1, 1), axes="ZYX")
        np.testing.assert_array_equal(read_mask(tmp_path / f"{name}.tif", 0, 0, data.shape), inside)
    write_hyperstack(tmp_path / "all_nan.tif", np.full(ball.shape, np.nan, np.float32), (1, 1, 1), axes="ZYX")
    with pytest.raises(NemoError, match=r"all_nan.tif \(t = 0, c = 0\) is empty: every voxel is NaN"):
        read_mask(tmp_path / "all_nan.tif", 0, 0, ball.shape)
    masked = np.where(inside, 100 + rng.integers(0, 900, ball.shape), 0).astype(np.uint16)  # intensity, 0 outside
    write_hyperstack(tmp_path / "masked.tif", masked, (1, 1, 1), axes="ZYX")
    with pytest.raises(NemoError, match="mask_threshold: 0 if every nonzero voxel is object"):
        read_mask(tmp_path / "masked.tif", 0, 0, masked.shape)
    np.testing.assert_array_equal(read_mask(tmp_path / "masked.tif", 0, 0, masked.shape, threshold=0), inside)


def test_mask_options_need_a_mask(run_cli, segmentation):
    d, _ = segmentation
    code, _, err = run_cli("mesh", d / "labels.tif", "--mask-labels", "3", "-o", d / "m.ply")
    assert code == 2 and "give the mask file" in err
