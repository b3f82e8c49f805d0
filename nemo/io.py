"""Lazy reading and writing of microscopy hyperstacks.

Images are ImageJ hyperstacks, OME-TIFF files or OME-Zarr folders (:mod:`nemo.ome_zarr`) with
any subset of the axes T, Z, C, Y, X. Only the (Z, Y, X) stack of one time point and channel is
ever read: tifffile exposes a TIFF file as a chunked zarr store (one chunk per page), and an
OME-Zarr image is read chunk by chunk, so a 10 GB file costs one stack of memory.

Spacing is returned as ``(dz, dy, dx)`` in micrometres whenever the unit is known; an
uncalibrated file gives spacing 1 with unit ``"pixel"`` and a :class:`~nemo.errors.NemoWarning`.
"""

from __future__ import annotations

import json
import logging
import math
import operator
import os
import re
import struct
import threading
import warnings
import xml.etree.ElementTree as ET
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import tifffile

from nemo._log import logger, pretty_unit
from nemo.atomic import atomic_path
from nemo.errors import NemoError, NemoWarning

AXES = "TZCYX"
_UNIT_TO_UM = {
    "um": 1.0, "µm": 1.0, "μm": 1.0, "micron": 1.0, "microns": 1.0, "micrometer": 1.0,
    "micrometre": 1.0, "\\u00b5m": 1.0, "nm": 1e-3, "nanometer": 1e-3, "nanometre": 1e-3,
    "mm": 1e3, "millimeter": 1e3, "millimetre": 1e3, "cm": 1e4, "m": 1e6, "meter": 1e6,
}


@dataclass
class ImageInfo:
    """What a hyperstack holds, without reading its pixels.

    Attributes
    ----------
    path : str
        The file.
    axes : str
        Axes as stored in the file, e.g. ``"TZCYX"`` (tifffile's letters; ``I``/``Q`` are
        read as Z, ``S`` as C).
    shape : dict[str, int]
        Sizes of ``T, C, Z, Y, X``; absent axes have size 1.
    dtype : str
        Pixel type.
    spacing : tuple[float, float, float]
        ``(dz, dy, dx)`` in ``unit``.
    unit : str
        ``"um"`` when the file's unit was recognised, else the file's unit or ``"pixel"``.
    calibrated : bool
        False when the spacing is a default of 1 because the file had no calibration.
    """

    path: str
    axes: str
    shape: dict[str, int]
    dtype: str
    spacing: tuple[float, float, float]
    unit: str
    calibrated: bool = True
    _normalised_axes: str = field(default="", repr=False)
    _described: dict | None = field(default=None, repr=False)  # OME-Zarr metadata, read once

    def to_json(self) -> dict:
        """The public description: ``axes``, ``shape``, ``dtype``, ``spacing``, ``unit``."""
        d = asdict(self)
        d.pop("_normalised_axes")
        d.pop("_described")
        d["spacing"] = list(self.spacing)
        return d


def unit_scale(unit: str | None) -> float | None:
    """Micrometres per ``unit`` (None for an unknown unit or None)."""
    if unit is None:
        return None
    return _UNIT_TO_UM.get(unit.strip().lower().replace("\\u00b5", "µ"))


def _normalise_axes(axes: str) -> str:
    """Map tifffile's axis letters onto T, Z, C, Y, X."""
    out = []
    for a in axes:
        if a in "IQ" and "Z" not in axes and "Z" not in out:
            a = "Z"
        elif a == "S" and "C" not in axes and "C" not in out:
            a = "C"
        out.append(a)
    extra = [a for a in out if a not in AXES]
    if extra or len(set(out)) != len(out):
        raise NemoError(
            f"image axes {axes!r} cannot be read as a T, Z, C, Y, X hyperstack "
            f"(unsupported axes {''.join(extra) or 'repeated'}); re-save it from Fiji as a hyperstack"
        )
    if "Y" not in out or "X" not in out:
        raise NemoError(f"image axes {axes!r} have no Y and X: this is not an image stack")
    return "".join(out)


def _ome_spacing(ome_xml: str) -> tuple[list[float | None], list[str | None]]:
    root = ET.fromstring(ome_xml)
    pixels = next((el for el in root.iter() if el.tag.endswith("Pixels")), None)
    if pixels is None:
        return [None, None, None], [None, None, None]
    vals, units = [], []
    for ax in "ZYX":
        v = pixels.get(f"PhysicalSize{ax}")
        vals.append(float(v) if v is not None else None)
        units.append(pixels.get(f"PhysicalSize{ax}Unit", "µm") if v is not None else None)
    return vals, units


def _calibration(vals: list[float | None], units: list[str | None]) -> tuple[tuple[float, float, float], str, bool]:
    """Spacing, unit and calibrated flag from per-axis (Z, Y, X) sizes and units (OME metadata).

    Recognised units are converted to µm; an unknown unit is kept as given; no unit at all
    keeps the sizes (their ratios still matter) with unit ``"pixel"``, uncalibrated.
    """
    dz = vals[0] if vals[0] is not None else vals[2]
    if vals[0] is None:
        warnings.warn("the file has no z spacing (OME PhysicalSizeZ): assuming dz = dx; set it with `spacing` if "
                      "wrong", NemoWarning, stacklevel=4)
    if not any(units):
        return (float(dz), float(vals[1]), float(vals[2])), "pixel", False
    scales = [unit_scale(u) if u else None for u in units]
    if all(s is not None for s, v in zip(scales, vals) if v is not None):
        dz = vals[0] * scales[0] if vals[0] is not None else vals[2] * scales[2]
        return (dz, vals[1] * scales[1], vals[2] * scales[2]), "um", True
    return (dz, vals[1], vals[2]), next(u for u in units if u), True


def _positive(value) -> float | None:
    """``value`` as a float where it is a finite positive number, else None."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        return None
    return number if math.isfinite(number) and number > 0 else None


def _spacing_from_tiff(tif: tifffile.TiffFile) -> tuple[tuple[float, float, float], str, bool]:
    """Return (spacing in µm or raw units, unit, calibrated)."""
    if tif.is_ome and tif.ome_metadata:
        vals, units = _ome_spacing(tif.ome_metadata)
        if vals[1] is not None and vals[2] is not None:
            return _calibration(vals, units)
    page = tif.pages.first
    ij = tif.imagej_metadata or {}
    xres = page.tags.get("XResolution")
    yres = page.tags.get("YResolution")

    def _res(tag) -> float | None:
        if tag is None:
            return None
        num, den = tag.value
        return den / num if num else None

    dx, dy = _res(xres), _res(yres)
    dz = ij.get("spacing")
    unit = ij.get("unit")
    if isinstance(unit, str) and unit.strip().lower() in ("pixel", "pixels", "px", ""):
        unit = None  # ImageJ's way of saying "not calibrated"
    if unit is None:
        runit = page.tags.get("ResolutionUnit")
        code = int(runit.value) if runit is not None else 1
        unit = {3: "cm", 2: None}.get(code)  # 2 = inch: not a microscopy unit
        if code == 1:
            unit = None
        if code == 2:  # dots per inch (72 from a generic writer): a print size, not the voxels' size
            dx = dy = None
    has_xy = dx is not None and dy is not None and not (dx == 1.0 and dy == 1.0 and unit is None)
    if not has_xy and (dz is None or unit is None):
        # ImageJ's "pixel" unit with a voxel depth: the z step in pixels (its ratio still matters, as for OME)
        z_pixels = _positive(dz) if dx in (None, 1.0) and dy in (None, 1.0) else None
        return (z_pixels or 1.0, 1.0, 1.0), "pixel", False
    dx = dx if dx is not None else 1.0
    dy = dy if dy is not None else dx
    if dz is None:
        warnings.warn(
            "the file has no z spacing: assuming dz = dx; set it with `spacing` if wrong",
            NemoWarning, stacklevel=3,
        )
    dz = float(dz) if dz is not None else dx
    scale = unit_scale(unit)
    if scale is None:
        return (dz, dy, dx), (unit or "pixel"), unit is not None
    return (dz * scale, dy * scale, dx * scale), "um", True


_FIX = ("the file was cut off or damaged (incomplete copy or download, full disk): copy it again "
        "from the source, or re-save it from Fiji")
# tifffile's log messages that mean offsets in the file point nowhere: a cut or damaged file
_BROKEN_LOG = re.compile(
    r"invalid (page |next page |offset to (first )?page)|corrupted tag list|circular reference|"
    r"missing (data offset|data ByteCounts|ByteCounts)"
)
# tifffile's messages about metadata it ignored and replaced (checked by _check_intact): kept quiet
_QUIET_LOG = re.compile(r"corrupted file")


class _BrokenFileLog(logging.Filter):
    """Collect (and keep off stderr) tifffile's complaints about a broken file, in this thread."""

    def __init__(self) -> None:
        super().__init__()
        self.messages: list[str] = []
        self._thread = threading.get_ident()

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        if record.thread != self._thread:
            return True
        if _BROKEN_LOG.search(message):
            self.messages.append(re.sub(r"^<[^>]*>\s*", "", message))  # drop tifffile's object repr
            return False
        return not _QUIET_LOG.search(message)


@contextmanager
def _catch_broken_file_log() -> Iterator[_BrokenFileLog]:
    """Catch tifffile's messages about broken offsets logged while the block runs."""
    catcher = _BrokenFileLog()
    log = logging.getLogger("tifffile")
    log.addFilter(catcher)
    try:
        yield catcher
    finally:
        log.removeFilter(catcher)


def _truncated(path: str | os.PathLike, detail: str) -> NemoError:
    return NemoError(f"{path} is truncated or corrupt: {detail}; {_FIX}")


def _page_end(page: tifffile.TiffPage | tifffile.TiffFrame) -> int:
    """The byte just past the last pixel data of a page, from its header."""
    offsets, counts = page.dataoffsets, page.databytecounts
    if len(offsets) == 1:
        return offsets[0] + counts[0]
    return max(map(operator.add, offsets, counts), default=0)


def _images(series: tifffile.TiffPageSeries) -> int:
    """The number of pages (2-D images) the series' shape spans."""
    return series.size // max(series.keyframe.size, 1)


def _held(tif: tifffile.TiffFile, series: tifffile.TiffPageSeries, size: int) -> tuple[int, int | None]:
    """(complete images the file holds, bytes the series' pixel data need or None), headers only."""
    page = tif.pages.first
    if series.kind in ("generic", "uniform") and tif.is_imagej:  # tifffile rejected the ImageJ header
        held = max(0, size - page.dataoffsets[0]) // max(page.nbytes, 1) if page.compression == 1 else len(tif.pages)
        return held, None
    if series.dataoffset is not None:  # contiguous uncompressed data (ImageJ, tifffile)
        per = max(series.nbytes // max(_images(series), 1), 1)
        return max(0, size - series.dataoffset) // per, int(series.dataoffset + series.nbytes)
    pages = [p for p in series._pages if p is not None]  # parsed headers; iterating the series reads IFDs
    # a multi-file series (OME, Micro-Manager) keeps each page's data in its own file
    own = [p.parent.filehandle.size if p.parent is not tif else size for p in pages]
    ends = [_page_end(p) for p in pages]
    held = sum(end <= limit for end, limit in zip(ends, own))
    return held, (max(ends, default=0) if all(p.parent is tif for p in pages) else None)


def _imagej_images(tif: tifffile.TiffFile) -> int | None:
    """The number of pages (2-D images) an ImageJ header announces, None if not ImageJ.

    Counted the way tifffile does: channels stored as samples of one page count once.
    """
    ij = tif.imagej_metadata if tif.is_imagej else None
    try:
        frames, slices, channels, images = (int(ij.get(k) or 1) for k in ("frames", "slices", "channels", "images"))
    except (AttributeError, TypeError, ValueError):  # no ImageJ header, or one tifffile ignores too
        return None
    shaped = tif.pages.first.shaped
    samples = channels == 1 or shaped[0] == channels or (images == frames * slices and shaped[4] == channels)
    n = frames * slices * (1 if samples else channels)
    return images if n == 1 else n


def _check_intact(tif: tifffile.TiffFile, path: str | os.PathLike, log: list[str]) -> None:
    """Raise a NemoError if the headers of ``tif`` announce more than the file holds (header reads only).

    The images announced (by the ImageJ header, else by the series tifffile built) are compared
    with the images whose pixel data (offsets + byte counts) lie inside the file; then tifffile's
    own complaints about invalid offsets (a list of pages running past the end of the file).
    """
    size = tif.filehandle.size
    series = tif.series[0]
    announced = _imagej_images(tif)
    header = "ImageJ header" if announced is not None else "pages"
    if announced is None or series.kind == "ome":
        announced = _images(series)
    held, need = _held(tif, series, size)
    if held < announced or (tif.is_imagej and series.kind in ("generic", "uniform")):
        if need is None and tif.pages.first.compression == 1:
            need = tif.pages.first.dataoffsets[0] + announced * tif.pages.first.nbytes
        needs = f", the pixel data need {need} bytes" if need and need > size else ""
        raise _truncated(path, f"its {header} announce{'s' if header != 'pages' else ''} {announced} images "
                               f"but the file holds only {min(held, announced - 1)} "
                               f"(file size {size} bytes{needs})")
    if log:
        raise _truncated(path, f"its list of images breaks off after {len(tif.pages)} of them "
                               f"(file size {size} bytes; tifffile: {log[0]})")


def _has_tiff_magic(path: Path) -> bool:
    """Whether the file starts like a TIFF or BigTIFF file."""
    with open(path, "rb") as fh:
        return fh.read(4) in (b"II*\0", b"MM\0*", b"II+\0", b"MM\0+")


def _open_tiff(path: str | os.PathLike) -> tifffile.TiffFile:
    """Open a TIFF file whose headers are intact, with its series parsed."""
    path = Path(path)
    if not path.exists():
        raise NemoError(f"image file not found: {path}")
    if path.is_dir():
        raise NemoError(f"{path} is a folder but not an OME-Zarr image (no .zattrs, .zgroup or zarr.json "
                        "in it): give a TIFF file or an OME-Zarr folder")
    if path.stat().st_size == 0:
        raise NemoError(f"{path} is empty (0 bytes); {_FIX}")
    with _catch_broken_file_log() as log:
        try:
            tif = tifffile.TiffFile(path)
        except (tifffile.TiffFileError, ValueError, OSError, struct.error) as exc:
            if log.messages or _has_tiff_magic(path):  # a TIFF whose first page is cut off or broken
                raise _truncated(path, f"its first image header cannot be read ({(log.messages or [exc])[0]})") from None
            raise NemoError(
                f"{path} is not a readable TIFF file ({exc}); NEMO reads ImageJ hyperstacks and OME-TIFF"
            ) from None
        try:
            try:
                if not tif.series:
                    raise _truncated(path, "it holds no image that tifffile can read")
            except (tifffile.TiffFileError, ValueError, OSError) as exc:
                raise _truncated(path, f"its image headers cannot be parsed ({exc})") from None
            _check_intact(tif, path, log.messages)
        except BaseException:
            tif.close()
            raise
    return tif


def _info_from_tiff(tif: tifffile.TiffFile, path: str) -> ImageInfo:
    series = tif.series[0]
    axes = _normalise_axes(series.axes)
    sizes = dict(zip(axes, series.shape))
    if "Z" not in sizes:
        raise NemoError(
            f"{path} is a 2-D image (axes {series.axes!r}); NEMO needs a 3-D stack with a Z axis"
        )
    spacing, unit, calibrated = _spacing_from_tiff(tif)
    return ImageInfo(
        path=str(path),
        axes=series.axes,
        shape={a: int(sizes.get(a, 1)) for a in AXES},
        dtype=str(series.dtype),
        spacing=tuple(float(s) for s in spacing),
        unit=unit,
        calibrated=calibrated,
        _normalised_axes=axes,
    )


def _info_from_zarr(path: str | os.PathLike) -> ImageInfo:
    """The :class:`ImageInfo` of an OME-Zarr image (the level its path selects)."""
    from nemo import ome_zarr

    d = ome_zarr.describe(path)
    axes = _normalise_axes(d["axes"])
    if "Z" not in axes:
        raise NemoError(f"{path} is a 2-D image (axes {d['axes']!r}); NEMO needs a 3-D stack with a Z axis")
    spacing, unit, calibrated = _calibration(list(d["spacing"]), d["units"])
    return ImageInfo(path=str(path), axes=d["axes"], shape={a: int(d["shape"].get(a, 1)) for a in AXES},
                     dtype=d["dtype"], spacing=spacing, unit=unit, calibrated=calibrated,
                     _normalised_axes=axes, _described=d)


def read_info(path: str | os.PathLike) -> ImageInfo:
    """Describe a hyperstack (axes, sizes, dtype, spacing, unit) without reading pixels.

    ``path`` is a TIFF file or an OME-Zarr folder (its level 0, or the level folder given,
    e.g. ``image.zarr/1``).

    Raises
    ------
    NemoError
        If the file is missing, not a TIFF, has no Z axis, or is truncated or corrupt (its
        headers announce more images or pixel data than the file holds; checked from the
        headers only).
    """
    from nemo import ome_zarr

    if ome_zarr.is_zarr(path):
        return _info_from_zarr(path)
    with _open_tiff(path) as tif:
        return _info_from_tiff(tif, str(path))


def check_spacing(spacing) -> tuple[float, float, float]:
    try:
        dz, dy, dx = (float(s) for s in spacing)
    except (TypeError, ValueError):
        raise NemoError(f"spacing must be three numbers DZ DY DX, got {spacing!r}") from None
    if not all(np.isfinite(s) and s > 0 for s in (dz, dy, dx)):
        raise NemoError(f"spacing must be three positive numbers DZ DY DX, got {spacing!r}")
    return dz, dy, dx


def read_stack(
    path: str | os.PathLike,
    t: int = 0,
    c: int = 0,
    spacing: tuple[float, float, float] | None = None,
    sparse: bool = False,
) -> tuple[np.ndarray, ImageInfo]:
    """Read the (Z, Y, X) stack of time point ``t`` and channel ``c``, and nothing else.

    Parameters
    ----------
    path : path-like
        ImageJ hyperstack or OME-TIFF.
    t, c : int
        Time point and channel (0-based).
    spacing : (dz, dy, dx), optional
        Overrides the file's calibration (same unit as the rest of the analysis, µm).
    sparse : bool
        The image may leave chunks of an OME-Zarr unwritten (a mask, mostly background): no
        warning for them. An image warns, and a stack none of whose chunks is stored is refused.

    Returns
    -------
    stack : ndarray, shape (Z, Y, X)
        The pixels, in the file's dtype.
    info : ImageInfo
        The file's description, with ``spacing`` overridden when given.

    Raises
    ------
    NemoError
        As :func:`read_info`; also when ``t``/``c`` are out of range, or when the pixels cannot
        be read or decoded (a truncated or corrupt file), never a shorter stack.
    """
    from nemo import ome_zarr

    if ome_zarr.is_zarr(path):
        info = _info_from_zarr(path)
        axes = info._normalised_axes
        _check_index(info, path, t, c)
        data = ome_zarr.read(path, {a: int(i) for a, i in (("T", t), ("C", c)) if a in axes},
                             described=info._described, sparse=sparse)
    else:
        with _open_tiff(path) as tif:
            info = _info_from_tiff(tif, str(path))
            axes = info._normalised_axes
            _check_index(info, path, t, c)
            data = _read_pixels(tif.series[0], _key(axes, t, c), path)
    kept = [a for a in axes if a not in "TC"]
    data = np.transpose(data, [kept.index(a) for a in "ZYX"])
    if spacing is not None:
        info.spacing = check_spacing(spacing)
        info.unit = "um"
        info.calibrated = True
    elif not info.calibrated:
        warnings.warn(
            f"{path} has no spatial calibration: using spacing {list(info.spacing)} with unit 'pixel'. "
            "Set it with `spacing` (dz, dy, dx).",
            NemoWarning,
            stacklevel=2,
        )
    return data, info


def _key(axes: str, t: int, c: int) -> tuple:
    """The index of time point ``t`` and channel ``c`` into an array with ``axes``."""
    return tuple({"T": int(t), "C": int(c)}.get(a, slice(None)) for a in axes)


def _check_index(info: ImageInfo, path, t: int, c: int) -> None:
    """Refuse a time point or channel the image does not have."""
    for name, index in (("t", t), ("c", c)):
        size = info.shape[name.upper()]
        if not isinstance(index, (int, np.integer)) or not 0 <= index < size:
            raise NemoError(
                f"{name} = {index} is out of range: {path} has {size} "
                f"{'time point' if name == 't' else 'channel'}{'s' if size != 1 else ''} "
                f"(valid: 0 to {size - 1})"
            )


def _read_pixels(series: tifffile.TiffPageSeries, key: tuple, path: str | os.PathLike) -> np.ndarray:
    """Read ``series[key]`` through tifffile's zarr store; a failed read becomes a NemoError."""
    import zarr  # only to read pixels (0.2 s to import; the workflow's parse reads headers only)

    with _catch_broken_file_log() as log:
        store = series.aszarr(level=0)
        try:
            arr = zarr.open(store, mode="r")
            if isinstance(arr, zarr.Group):  # multiscale store: level 0 is "0"
                arr = arr["0"]
            data = np.asarray(arr[key])
        except (tifffile.TiffFileError, ValueError, OSError, EOFError, zlib.error, KeyError, RuntimeError) as exc:
            if "imagecodecs" in str(exc):  # a compression whose codec is not installed: the file is fine
                raise NemoError(f"{path} is compressed with a codec that is not installed ({exc}): install it "
                                "(pip install imagecodecs), or re-save the file uncompressed") from None
            raise _truncated(path, f"reading its pixels failed ({exc})") from None
        finally:
            store.close()
    if log.messages:
        raise _truncated(path, f"reading its pixels failed (tifffile: {log.messages[0]})")
    return data


def read_mask(path: str | os.PathLike, t: int, c: int, shape: tuple[int, ...],
              labels: list[int] | None = None, threshold: float | None = None,
              channel: int | None = None, apart: tuple[int, int, int] | None = None,
              with_regions: bool = False) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """The object mask for time point ``t``, channel ``c`` of an image, from a segmentation.

    The mask is a TIFF or OME-Zarr image with its own T and C axes (then ``t``/``c`` select
    from them) or none. It may be

    * a binary mask (nonzero = object);
    * a label image (Cellpose, StarDist, ilastik object export; also saved as float: whole
      numbers, NaN background): ``labels`` selects the objects; without it every nonzero label
      is object;
    * a probability map (ilastik pixel classification, float values in [0, 1]): object where
      the value exceeds ``threshold`` (0.5 for a float image without a threshold). A map on
      another scale (floats beyond 1, or integers that vary from voxel to voxel as no label
      image does) needs ``threshold``: read without one it is refused, with that fix.

    ``channel`` picks the mask's channel (a probability map with one channel per class: the
    object's class); None takes ``c`` when the mask has channels, else its only one.

    ``apart`` (``mesh.keep: all``; :func:`label_gap`, half-widths in voxels along z, y, x) keeps
    the labels of a label image apart: the voxels that have another label within that reach are
    left out, so touching nuclei or cells of a Cellpose or StarDist segmentation stay separate
    objects after the mask's blur (each loses a thin layer where they meet; without it every
    touching label merges into one surface, which is warned).

    ``with_regions`` also returns a voxel inside each large label that touching labels merge with
    (:func:`_merged_label_voxels`: two touching droplets, not the many cells of one tissue), for
    the mesh step to count per object as it counts an image's separate bright regions.

    Returns
    -------
    ndarray of bool, shape (Z, Y, X) = ``shape``
        The mask; with ``with_regions`` also an int array (n, 3) of voxel indices (z, y, x).

    Raises
    ------
    NemoError
        A mask of another (Z, Y, X) size than the image, a truncated or corrupt mask file,
        labels absent from the frame, a probability map on another scale without ``threshold``,
        or a mask that selects nothing.
    """
    try:
        info = read_info(path)
    except NemoError as err:  # the reader speaks of an image: say that it is the mask
        raise NemoError(f"the mask ({path}): {err}") from None
    mt = t if info.shape["T"] > 1 else 0
    mc = c if info.shape["C"] > 1 else 0
    if channel is not None:
        if not 0 <= int(channel) < info.shape["C"]:
            raise NemoError(f"mask_channel {channel} is not a channel of the mask {path}, which has "
                            f"{info.shape['C']} channel(s) (0 to {info.shape['C'] - 1})")
        mc = int(channel)
    data, _ = read_stack(path, mt, mc, spacing=(1.0, 1.0, 1.0), sparse=True)  # its calibration is irrelevant
    if data.shape != tuple(shape):
        raise NemoError(
            f"the mask {path} has shape (Z, Y, X) = {data.shape} but the image stack has {tuple(shape)}; "
            "give a mask of the same size"
        )
    name = f"the mask {path} (t = {mt}, c = {mc})"
    data = _float_labels(data) if threshold is None else data
    apart = apart if apart is not None and _is_label_image(data) and threshold is None else None
    mask, touching = _select_object(data, labels, threshold, name, warn_touch=apart is None)
    if apart is not None and _varying(data) is None:
        _cut_where_labels_meet(data, mask, name, apart)
        if not mask.any():
            raise NemoError(f"{name}: no voxel is left once the labels are kept apart (mesh.keep: all): every "
                            "object voxel touches another label; give mask_threshold if it is a probability map")
    return (mask, _merged_label_voxels(data, touching)) if with_regions else mask


#: A label that touching labels merge with counts as an object of its own (:func:`_merged_label_voxels`)
#: when it holds at least this share of their voxels (as :data:`nemo.surface.OBJECT_MIN_AREA` for surfaces).
MERGED_LABEL_SHARE = 0.1


def _merged_label_voxels(data: np.ndarray, touching: set[tuple[int, int]]) -> np.ndarray:
    """A point (z, y, x, voxel indices) inside each label that holds at least :data:`MERGED_LABEL_SHARE`
    of a group of touching labels (connected through ``touching``, pairs of labels) in which two or
    more do: objects meshed as one (two touching droplets), not the cells of one tissue (each a
    small share of it). The label's centroid (a C-shaped label's may lie outside it, and go
    uncounted); (0, 3) when there is none. Two passes plane by plane: no full-size temporaries,
    whatever the labels' values."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    if not touching:
        return np.empty((0, 3), dtype=np.int64)
    a, b = np.array(sorted(touching), dtype=np.int64).T
    ids = np.unique(np.r_[a, b])
    links = coo_matrix((np.ones(len(a)), (np.searchsorted(ids, a), np.searchsorted(ids, b))), shape=(len(ids),) * 2)
    group = connected_components(links, directed=False)[1]
    sizes = np.zeros(len(ids))
    for plane in data:  # plane by plane, only the touching labels' voxels counted (any value, negative too)
        index = _label_index(plane.ravel(), ids)
        sizes += np.bincount(index[index >= 0], minlength=len(ids))
    large = sizes >= MERGED_LABEL_SHARE * np.bincount(group, weights=sizes)[group]
    chosen = ids[large & (np.bincount(group[large], minlength=group.max() + 1)[group] >= 2)]
    if not len(chosen):
        return np.empty((0, 3), dtype=np.int64)
    sums = np.zeros((len(chosen), 4))  # Σz, Σy, Σx, count
    for z, plane in enumerate(data):  # the chosen labels' centroids
        index = _label_index(plane.ravel(), chosen)
        at = np.flatnonzero(index >= 0)
        if at.size:
            y, x = np.divmod(at, plane.shape[1])
            for column, values in enumerate((np.full(at.size, z), y, x, np.ones(at.size))):
                sums[:, column] += np.bincount(index[at], weights=values, minlength=len(chosen))
    return np.rint(sums[:, :3] / sums[:, 3:]).astype(np.int64)


def _label_index(values: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """The position of each value in the sorted ``ids``, −1 where it is not one of them."""
    index = np.searchsorted(ids, values).clip(max=len(ids) - 1)
    return np.where(ids[index] == values, index, -1)


def label_gap(spacing, sigma: float) -> tuple[int, int, int]:
    """Half-widths (voxels along z, y, x) of the cut between touching labels (:func:`read_mask`'s
    ``apart``) for a mask blurred by ``sigma`` (physical): each label loses what lies within
    1.35 σ of another. Two labels then end at least 1.35 σ apart, where the blurred halves of both
    sum to less than the 0.5 level (2 Φ(−0.675) = 0.5), also where they only nearly touched (a
    reach of half that on each side leaves such near misses one voxel apart, and the blur joins
    them: two touching nuclei of a review stayed one object). Where they touch over a face, each
    loses that layer (two balls R 9 µm at 2 × 1 × 1 µm: −6.8 %)."""
    return tuple(max(1, int(np.ceil(1.35 * float(sigma) / float(d) - 1e-9))) for d in spacing)


def _varying(data: np.ndarray) -> float | None:
    """The fraction of neighbouring nonzero voxels (along x, in a sample of whole rows) whose values
    differ, when it exceeds a half over more than 16 values: integers that vary like a probability
    map saved as integers (a label image is constant within each label); else None."""
    rows = np.nan_to_num(data[:: max(1, data.shape[0] // 16), :: max(1, data.shape[1] // 256)])  # NaN: background
    left, right = rows[:, :, :-1], rows[:, :, 1:]
    inside = (left != 0) & (right != 0)
    varies = np.count_nonzero(inside & (left != right)) / max(1, np.count_nonzero(inside))
    return float(varies) if varies > 0.5 and np.unique(rows).size > 16 else None


def _check_not_probabilities(data: np.ndarray, name: str) -> bool:
    """Refuse a mask read without a threshold that is a probability map on another scale: float
    values beyond 1 that are not whole numbers (cut at 0.5 they would keep nearly every nonzero
    voxel), or integers that vary from voxel to voxel inside the object (a label image is constant
    within each label; read as labels, every nonzero voxel would be object: a fat or boxy surface
    that passes no check). Returns whether the mask is a probability map in [0, 1] (float).

    Raises
    ------
    NemoError
        Such a map, with the fix (``mask_threshold``).
    """
    if np.issubdtype(data.dtype, np.floating) and not np.isfinite(data).any():
        raise NemoError(f"{name} is empty: every voxel is NaN or infinite. Check the file and the frame")
    top = float(np.nanmax(data))
    fix = (f"give mask_threshold (e.g. half its range, {0.5 * top:.4g}; `--mask-threshold` for nemo mesh and "
           "nemo run), or mask_threshold: 0 if every nonzero voxel is object (an intensity image masked to 0 "
           "outside the object)")
    if np.issubdtype(data.dtype, np.floating):
        if top > 1.0 and (not _whole_numbers(data) or _varying(data) is not None):
            raise NemoError(f"{name} is a float image with values up to {top:.4g}, not a probability map in "
                            f"[0, 1] (which is cut at 0.5) nor a label image: {fix}")
        return top <= 1.0
    varies = _varying(data)
    if varies is not None:
        raise NemoError(f"{name} varies between neighbouring nonzero voxels ({100 * varies:.0f} % of them, values "
                        f"up to {top:.4g}): a probability map or an intensity image saved as integers, not a label "
                        f"image or a binary mask: {fix}")
    return False


def _whole_numbers(data: np.ndarray) -> bool:
    """Whether a float image holds whole numbers only (a label image saved as float), on a sample of planes."""
    rows = data[:: max(1, data.shape[0] // 16)]
    finite = rows[np.isfinite(rows)]
    return bool(np.all(finite == np.round(finite)))


def _warn_if_labels_touch(data: np.ndarray, name: str) -> set[tuple[int, int]]:
    """Warn when labels of an integer label image touch: every nonzero label is object, so touching
    objects (Cellpose cells, packed nuclei) merge into one surface. Returns the touching pairs."""
    if np.issubdtype(data.dtype, np.floating) or data.dtype == bool:
        return set()
    pairs: set[tuple[int, int]] = set()

    def add(lo: np.ndarray, hi: np.ndarray) -> None:
        touch = (lo != hi) & (lo != 0) & (hi != 0)
        if touch.any():
            pairs.update(zip(np.minimum(lo[touch], hi[touch]).tolist(), np.maximum(lo[touch], hi[touch]).tolist()))

    for z in range(len(data)):  # plane by plane: a large label image needs no full-size temporaries
        plane = data[z]
        add(plane[:-1], plane[1:])
        add(plane[:, :-1], plane[:, 1:])
        if z + 1 < len(data):
            add(plane, data[z + 1])
    if pairs:
        shown = ", ".join(f"{a}–{b}" for a, b in sorted(pairs)[:5]) + (" …" if len(pairs) > 5 else "")
        warnings.warn(f"{name}: labels touch ({shown}): with every nonzero label as object they are meshed as one "
                      "surface; give mask_labels to select one object, or mesh.keep: all to keep every label apart",
                      NemoWarning, stacklevel=4)
    return pairs


def _float_labels(data: np.ndarray) -> np.ndarray:
    """A label image saved as float (whole numbers that are constant within each label; NaN
    background) as the integer label image it is, so that ``labels``, the touch warning and the cut
    between touching labels treat it as one; any other image unchanged. float32 holds whole numbers
    exactly up to 2**24 only, so int32 is wide enough."""
    if not np.issubdtype(data.dtype, np.floating) or not np.isfinite(data).any():
        return data
    top = float(np.nanmax(np.abs(data)))
    if top > 2**31 - 1 or not _whole_numbers(data) or _varying(data) is not None:
        return data
    return np.nan_to_num(data, nan=0.0, posinf=0.0, neginf=0.0).astype(np.int32)


def _is_label_image(data: np.ndarray) -> bool:
    """An integer image of more than one nonzero value (a label image, not a binary mask)."""
    return not (np.issubdtype(data.dtype, np.floating) or data.dtype == bool) and int(data.max()) > 1


def _cut_where_labels_meet(data: np.ndarray, mask: np.ndarray, name: str, reach: tuple[int, int, int],
                           slab: int = 32) -> None:
    """Leave out of ``mask`` (in place) the voxels that have a voxel of another nonzero label within
    ``reach`` (half-widths along z, y, x), so that touching labels stay separate objects after the
    mask's blur (see :func:`read_mask`'s ``apart``). Slab by slab of ``slab`` planes (with their
    halo): no full-size temporaries."""
    from scipy import ndimage as ndi

    size = tuple(2 * int(r) + 1 for r in reach)
    big = int(data.max()) + 1  # above every label (int64's own maximum overflows scipy's filter)
    cut = 0
    for z0 in range(0, len(data), slab):  # a loop over slabs of planes
        lo_z, hi_z = max(0, z0 - reach[0]), min(len(data), z0 + slab + reach[0])
        block = np.where(mask[lo_z:hi_z], data[lo_z:hi_z], 0).astype(np.int64)  # the selected labels only
        larger = ndi.maximum_filter(block, size=size, mode="nearest") > block
        smaller = ndi.minimum_filter(np.where(block == 0, big, block), size=size, mode="nearest") < block
        meets = ((block != 0) & (larger | smaller))[z0 - lo_z:z0 - lo_z + min(slab, len(data) - z0)]
        cut += int(np.count_nonzero(mask[z0:z0 + slab] & meets))
        mask[z0:z0 + slab] &= ~meets
    if cut:
        logger.info("%s: %d voxels within %s voxels of another label left out, so that touching labels stay "
                    "separate objects", name, cut, "×".join(map(str, reach)))


def _select_object(data: np.ndarray, labels: list[int] | None, threshold: float | None,
                   name: str, warn_touch: bool = True) -> tuple[np.ndarray, set[tuple[int, int]]]:
    """Object voxels of a binary mask, label image or probability map (see :func:`read_mask`), and the
    labels that touch where every nonzero label is object (pairs; checked with ``warn_touch``)."""
    if labels:
        if np.issubdtype(data.dtype, np.floating):
            raise NemoError(f"{name} holds floating-point values, not labels: drop mask_labels "
                            "(a probability map takes mask_threshold)")
        mask = np.isin(data, labels)
        if not mask.any():
            present = np.unique(data[data != 0])
            raise NemoError(f"{name} has none of the labels {list(labels)}; labels present: "
                            f"{present[:20].tolist()}{' …' if present.size > 20 else ''}")
        absent = sorted(set(int(v) for v in labels) - set(np.unique(data[mask]).astype(int).tolist()))
        if absent:  # one label of several given is not in this frame: the object is only the others
            warnings.warn(f"{name} has no voxel of label(s) {absent} of mask_labels {list(labels)}: meshing the "
                          "others only (a label of another frame, or mistyped?)", NemoWarning, stacklevel=3)
        return mask, set()
    touching: set[tuple[int, int]] = set()
    if threshold is None:
        if _check_not_probabilities(data, name):
            threshold = 0.5
        elif warn_touch:
            touching = _warn_if_labels_touch(data, name)
    mask = data > threshold if threshold is not None else (data != 0) & ~np.isnan(data)  # NaN: no object
    if mask.all():
        rule = f"above the threshold {threshold}" if threshold is not None else "nonzero"
        raise NemoError(f"{name} selects every voxel (all are {rule}; the smallest value is {data.min():.4g}): no "
                        "object boundary. If its background is not 0, give mask_threshold or mask_labels")
    if not mask.any():
        rule = f"above the threshold {threshold}" if threshold is not None else "nonzero"
        raise NemoError(f"{name} is empty: no voxel is {rule}. Check the file and the frame, or lower "
                        "the threshold (`--mask-threshold`, config `mask_threshold`)")
    return mask, touching


def write_hyperstack(
    path: str | os.PathLike,
    data: np.ndarray,
    spacing: tuple[float, float, float],
    unit: str = "um",
    axes: str = "TZCYX",
    ome: bool = False,
    compression: str | None = None,
    metadata: dict | None = None,
) -> None:
    """Write an ImageJ hyperstack (or OME-TIFF) with calibration, atomically.

    Parameters
    ----------
    path : path-like
        Output ``.tif``.
    data : ndarray
        Pixels with the axes named in ``axes`` (a subset of T, Z, C, Y, X in that order for
        ImageJ; any order for OME).
    spacing : (dz, dy, dx)
        Voxel size in ``unit``.
    unit : str
        Physical unit, ``"um"`` by default.
    ome : bool
        Write OME-TIFF instead of an ImageJ hyperstack.
    compression : str, optional
        e.g. ``"zlib"``; ``None`` writes uncompressed pages.
    metadata : dict, optional
        Extra key/values stored in the ImageJ ``Info`` string as JSON.
    """
    dz, dy, dx = check_spacing(spacing)
    path = Path(path)
    if not ome and not re.fullmatch("T?Z?C?YX", axes):
        raise NemoError(f"ImageJ hyperstacks need axes in the order TZCYX, got {axes!r}")
    with atomic_path(path) as tmp:
        if ome:
            ome_unit = pretty_unit(unit)
            tifffile.imwrite(
                tmp, data, ome=True, photometric="minisblack", compression=compression,
                metadata={
                    "axes": axes, "PhysicalSizeX": dx, "PhysicalSizeY": dy, "PhysicalSizeZ": dz,
                    "PhysicalSizeXUnit": ome_unit, "PhysicalSizeYUnit": ome_unit, "PhysicalSizeZUnit": ome_unit,
                },
            )
        else:
            ij_unit = "micron" if unit in ("um", "µm", "μm", "micron") else unit  # ImageJ metadata is ASCII
            md = {"axes": axes, "spacing": dz, "unit": ij_unit}
            if metadata:
                md["Info"] = json.dumps(metadata)
            tifffile.imwrite(
                tmp, data, imagej=True, resolution=(1.0 / dx, 1.0 / dy),
                metadata=md, compression=compression,
            )

