"""nemo.ome_zarr: OME-Zarr (NGFF 0.4 / 0.5) images read like TIFF hyperstacks, lazily."""

from __future__ import annotations

import warnings

import numpy as np
import pandas as pd
import pytest

from nemo import ome_zarr
from nemo.errors import NemoError, NemoWarning
from nemo.io import read_info, read_mask, read_stack, write_hyperstack
from nemo.pipeline import run_frame
from nemo.synthetic import write_vesicle
from nemo.tables import read_table


@pytest.fixture(scope="module")
def movie():
    """A (T, C, Z, Y, X) movie with distinct values per time point and channel."""
    rng = np.random.default_rng(3)
    return rng.integers(0, 60000, (3, 2, 6, 20, 14)).astype(np.uint16)


@pytest.mark.parametrize("zarr_format", [2, 3])
def test_zarr_reads_like_the_same_tiff(movie, tmp_path, zarr_format):
    spacing = (2.5, 0.4, 0.4)
    zpath = ome_zarr.write(tmp_path / "m.zarr", movie, spacing, axes="TCZYX", zarr_format=zarr_format)
    tpath = tmp_path / "m.tif"
    write_hyperstack(tpath, movie.transpose(0, 2, 1, 3, 4), spacing)
    zi, ti = read_info(zpath), read_info(tpath)
    assert zi.shape == ti.shape == {"T": 3, "Z": 6, "C": 2, "Y": 20, "X": 14}
    assert zi.spacing == pytest.approx(ti.spacing) and zi.unit == ti.unit == "um" and zi.calibrated
    for t in range(3):
        for c in range(2):
            z_stack, _ = read_stack(zpath, t, c)
            t_stack, _ = read_stack(tpath, t, c)
            assert z_stack.dtype == np.uint16
            np.testing.assert_array_equal(z_stack, movie[t, c])
            np.testing.assert_array_equal(z_stack, t_stack)
    with pytest.raises(NemoError, match="t = 3 is out of range"):
        read_stack(zpath, 3, 0)


def test_a_level_folder_reads_that_resolution_with_its_spacing(movie, tmp_path):
    zpath = ome_zarr.write(tmp_path / "m.zarr", movie, (2.0, 0.5, 0.5), levels=3)
    info = read_info(zpath / "2")
    assert info.spacing == pytest.approx((2.0, 2.0, 2.0))
    assert (info.shape["Y"], info.shape["X"]) == (5, 4)
    stack, _ = read_stack(zpath / "2", 1, 1)
    np.testing.assert_array_equal(stack, movie[1, 1, :, ::4, ::4])
    assert [lv["spacing"][2] for lv in ome_zarr.levels(zpath)] == [0.5, 1.0, 2.0]
    with pytest.raises(NemoError, match="not found"):
        read_info(zpath / "7")


def test_axes_in_any_subset_and_units_are_converted(tmp_path):
    vol = np.arange(4 * 5 * 6, dtype=np.float32).reshape(4, 5, 6)
    zpath = ome_zarr.write(tmp_path / "v.zarr", vol, (500.0, 100.0, 100.0), axes="ZYX", unit="nanometer")
    info = read_info(zpath)
    assert info.spacing == pytest.approx((0.5, 0.1, 0.1)) and info.unit == "um"
    assert info.shape == {"T": 1, "Z": 4, "C": 1, "Y": 5, "X": 6}
    np.testing.assert_array_equal(read_stack(zpath)[0], vol)


def test_only_the_requested_stack_is_read(movie, tmp_path):
    """Corrupt every chunk of t = 1: t = 0 still reads (its chunks alone are touched), t = 1 fails
    with a message naming the file, not a codec traceback."""
    zpath = ome_zarr.write(tmp_path / "m.zarr", movie, (1.0, 1.0, 1.0), chunks=(1, 1, 6, 20, 14))
    chunks = [p for p in (zpath / "0").rglob("*") if p.is_file() and p.name.startswith("1.")]
    assert len(chunks) == 2  # one per channel of t = 1 (Zarr format 2 keys "t.c.z.y.x")
    for p in chunks:
        p.write_bytes(b"garbage")
    np.testing.assert_array_equal(read_stack(zpath, 0, 1)[0], movie[0, 1])
    with pytest.raises(NemoError, match="m.zarr"):
        read_stack(zpath, 1, 0)


@pytest.mark.parametrize("zarr_format", [2, 3])
def test_absent_chunks_are_warned_and_an_absent_stack_refused(movie, tmp_path, zarr_format):
    """Zarr reads an absent chunk as the fill value, silently: an interrupted copy would be
    analysed as a dark stack. Some chunks absent: a warning naming how many; all of a (t, c)
    stack absent: an error; the other stacks read as before."""
    zpath = ome_zarr.write(tmp_path / "m.zarr", movie, (1.0, 1.0, 1.0), chunks=(1, 1, 3, 20, 14),
                           zarr_format=zarr_format)
    stored = sorted(p for p in (zpath / "0").rglob("*") if p.is_file() and not p.name.startswith((".", "zarr")))
    assert len(stored) == 3 * 2 * 2  # t, c, two z-chunks

    def chunk(t, c, z):
        name = {2: f"{t}.{c}.{z}.0.0", 3: f"c/{t}/{c}/{z}/0/0"}[zarr_format]
        return zpath / "0" / name

    chunk(1, 0, 1).unlink()
    with pytest.warns(NemoWarning, match="1 of 2 Zarr chunks of t = 1, c = 0 are not stored"):
        stack, _ = read_stack(zpath, 1, 0)
    np.testing.assert_array_equal(stack[:3], movie[1, 0, :3])
    assert (stack[3:] == 0).all()
    chunk(2, 1, 0).unlink()
    chunk(2, 1, 1).unlink()
    with pytest.raises(NemoError, match="none of the 2 Zarr chunks of t = 2, c = 1 is stored"):
        read_stack(zpath, 2, 1)
    np.testing.assert_array_equal(read_stack(zpath, 2, 0)[0], movie[2, 0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a mask may leave its background chunks unwritten
        assert not read_stack(zpath, 2, 1, sparse=True)[0].any()


def test_folders_that_are_not_ome_zarr_are_refused(tmp_path):
    import zarr

    with pytest.raises(NemoError, match="not an OME-Zarr image"):
        read_info(tmp_path)
    zarr.open_group(str(tmp_path / "plain.zarr"), mode="w").create_array("0", data=np.zeros((2, 3, 4)))
    with pytest.raises(NemoError, match="without OME-NGFF 'multiscales'"):
        read_info(tmp_path / "plain.zarr")
    zpath = ome_zarr.write(tmp_path / "yx.zarr", np.zeros((5, 6), np.uint8), (1, 1, 1), axes="YX")
    with pytest.raises(NemoError, match="2-D image"):
        read_info(zpath)


def _edit_metadata(zpath, change):
    """Rewrite an NGFF 0.4 image's ``.zattrs`` multiscale with ``change(ms)``."""
    import json

    attrs = json.loads((zpath / ".zattrs").read_text())
    change(attrs["multiscales"][0])
    (zpath / ".zattrs").write_text(json.dumps(attrs))
    return zpath


@pytest.mark.parametrize("change, message", [
    (lambda ms: ms["datasets"][0].update(coordinateTransformations=[{"type": "scale", "scale": [2, 2, 2]}]),
     "has 3 values for 5 axes"),
    (lambda ms: ms.update(datasets=[]), "lists no resolution level"),
    (lambda ms: ms["datasets"][0].update(path="9"), "names resolution level '9' but the folder has no such array"),
    (lambda ms: ms["axes"][0].update(name="when", type="space"), "axis 'when' is none of t, c, z, y, x"),
], ids=["scale length", "no datasets", "missing level", "unknown axis"])
def test_broken_ome_metadata_is_named(tmp_path, change, message):
    zpath = ome_zarr.write(tmp_path / "v.zarr", np.zeros((1, 1, 4, 5, 6), np.uint8), (2, 1, 1))
    with pytest.raises(NemoError, match=message):
        read_info(_edit_metadata(zpath, change))


def test_ome_zarr_without_a_scale_is_uncalibrated_and_named_axes_are_read(tmp_path):
    def no_scale(ms):
        ms["datasets"][0].pop("coordinateTransformations")
        ms["axes"][0]["name"], ms["axes"][1]["name"] = "time", "channel"

    zpath = _edit_metadata(ome_zarr.write(tmp_path / "v.zarr", np.ones((1, 1, 4, 5, 6), np.uint8), (2, 1, 1)),
                           no_scale)
    info = read_info(zpath)
    assert info.axes == "TCZYX" and not info.calibrated and info.unit == "pixel"
    with pytest.warns(NemoWarning, match="no spatial calibration"):
        read_stack(zpath)
    array = tmp_path / "plain.zarr"
    import zarr

    zarr.open_array(str(array), mode="w", shape=(2, 3, 4), dtype="u1", zarr_format=2)
    with pytest.raises(NemoError, match="plain Zarr array without OME-NGFF metadata"):
        read_info(array)


def test_a_zarr_mask_selects_labels(tmp_path):
    labels = np.zeros((5, 8, 8), np.uint16)
    labels[1:3, 1:4, 1:4] = 7
    labels[2:4, 5:7, 5:7] = 9
    zpath = ome_zarr.write(tmp_path / "labels.zarr", labels, (1, 1, 1), axes="ZYX")
    np.testing.assert_array_equal(read_mask(zpath, 0, 0, labels.shape, labels=[9]), labels == 9)


def test_nemo_run_gives_identical_results_from_tiff_and_zarr(tmp_path):
    """The same vesicle as ImageJ TIFF and as OME-Zarr: every table of `nemo run` identical."""
    tif = tmp_path / "ves.tif"
    write_vesicle(tif, radius=30.0, spacing=(2.0, 2.0, 2.0), fibre_spacing=3.0, seed=2)
    stack, info = read_stack(tif)
    zpath = ome_zarr.write(tmp_path / "ves.zarr", stack, info.spacing, axes="ZYX")
    cfg = {"mesh": {"step": 1}, "curvature": {"samples": 300}}
    runs = {name: run_frame(path, tmp_path / f"out_{name}", cfg) for name, path in
            (("tif", tif), ("zarr", zpath))}
    assert runs["tif"]["files"] == runs["zarr"]["files"]
    tables = [f for f in runs["tif"]["files"] if f.endswith(".parquet")]
    assert any(f.startswith("defects") for f in tables)
    for name in tables:
        a = read_table(tmp_path / "out_tif" / name)
        b = read_table(tmp_path / "out_zarr" / name)
        pd.testing.assert_frame_equal(a, b, check_exact=True)
