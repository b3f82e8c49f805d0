"""OME-Zarr (OME-NGFF 0.4 and 0.5) images: read one (t, c) stack lazily, write test data.

An OME-Zarr image is a folder: a Zarr group whose ``multiscales`` metadata names the axes
(any of t, c, z, y, x), their physical unit and, per resolution level, the array's path and
its ``scale``. NEMO reads the group's level 0, or the level whose array folder is given
(``image.zarr/1``), so any path a command accepts can pick a resolution level. Only the chunks
of the requested (t, c) stack are read.

The metadata is two small JSON documents; it is parsed here rather than with ``ome-zarr-py``,
which would add a network stack (aiohttp, requests) to read two keys.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np

from nemo.errors import NemoError, NemoWarning

#: Files that mark a folder as a Zarr group or array (format 2 and 3).
_ZARR_MARKERS = (".zattrs", ".zgroup", ".zarray", "zarr.json")


def is_zarr(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a Zarr folder (a group or an array, Zarr format 2 or 3)."""
    p = Path(path)
    return p.is_dir() and any((p / m).is_file() for m in _ZARR_MARKERS)


def _open_group(path: Path):
    import zarr

    try:
        return zarr.open_group(str(path), mode="r")
    except (ValueError, OSError, KeyError, TypeError) as exc:  # zarr's errors (and bad JSON) derive from these
        raise NemoError(f"{path} is not a readable Zarr group ({exc})") from None


def _multiscale(attrs: dict, path: Path) -> dict:
    """The first ``multiscales`` entry of a group's attributes (NGFF 0.5 nests them in ``ome``)."""
    scales = attrs.get("ome", attrs).get("multiscales")
    if not scales:
        raise NemoError(f"{path} is a Zarr folder without OME-NGFF 'multiscales' metadata: NEMO reads "
                        "OME-Zarr images (write one with ome-zarr-py, bioformats2raw or napari)")
    return scales[0]


def locate(path: str | os.PathLike) -> tuple[Path, str]:
    """The multiscale group and the dataset path of the level to read.

    A path to the group reads level 0 (the first dataset); a path to one of its level arrays
    (``image.zarr/2``) reads that level.
    """
    p = Path(path)
    if ((p / ".zarray").is_file() or _is_array_v3(p)) and not is_zarr(p.parent):
        raise NemoError(f"{p} is a plain Zarr array without OME-NGFF metadata (axes, physical sizes): NEMO reads "
                        "OME-Zarr images (write one with ome-zarr-py, bioformats2raw or napari)")
    if not (p / ".zarray").is_file() and not _is_array_v3(p):
        attrs = dict(_open_group(p).attrs)
        if attrs.get("ome", attrs).get("multiscales") or not is_zarr(p.parent):
            return p, _datasets(_multiscale(attrs, p), p)[0]["path"]
    parent = _open_group(p.parent)
    levels = [d["path"] for d in _datasets(_multiscale(dict(parent.attrs), p.parent), p.parent)]
    if p.name not in levels:
        raise NemoError(f"{p} is not a resolution level of the OME-Zarr image {p.parent} "
                        f"(levels: {', '.join(levels)})")
    return p.parent, p.name


def _is_array_v3(p: Path) -> bool:
    import json

    meta = p / "zarr.json"
    return meta.is_file() and json.loads(meta.read_text()).get("node_type") == "array"


def _scale(ms: dict, level: str, path: Path) -> list[float] | None:
    """The level's physical size per axis (its scale times the multiscale's own, if any); None
    when neither gives one (an uncalibrated image)."""
    dataset = next(d for d in ms["datasets"] if d["path"] == level)
    scale, found = np.ones(len(ms["axes"])), False
    for transforms in (dataset.get("coordinateTransformations", []),
                       ms.get("coordinateTransformations", [])):
        for tr in transforms:
            if tr.get("type") == "scale":
                factor = np.asarray(tr.get("scale"), dtype=float).ravel()
                if factor.shape != scale.shape:
                    raise NemoError(f"{path}: the 'scale' of level {level} has {factor.size} values for "
                                    f"{scale.size} axes; fix the OME-Zarr metadata (.zattrs / zarr.json)")
                scale, found = scale * factor, True
    return scale.tolist() if found else None


def _datasets(ms: dict, path: Path) -> list[dict]:
    """The multiscale's resolution levels, each with a ``path`` (checked)."""
    datasets = ms.get("datasets")
    if not isinstance(datasets, list) or not datasets or not all(isinstance(d, dict) and "path" in d
                                                                 for d in datasets):
        raise NemoError(f"{path}: the OME-Zarr 'multiscales' metadata lists no resolution level ('datasets' "
                        "with a 'path' each); fix the metadata or export the image again")
    return datasets


def describe(path: str | os.PathLike) -> dict:
    """Axes, shape, dtype, spacing and unit of an OME-Zarr image, without reading pixels.

    Returns
    -------
    dict
        ``axes`` (upper-case letters, e.g. ``"TCZYX"``), ``shape`` (per letter), ``dtype``,
        ``spacing`` ``(dz, dy, dx)`` in ``unit``, ``units`` (the Z, Y, X axes' units or None),
        ``group`` and ``level`` (the array read).
    """
    group_path, level = locate(path)
    group = _open_group(group_path)
    ms = _multiscale(dict(group.attrs), group_path)
    letters = _letters(ms, group_path)
    array = _level_array(group, level, group_path)
    if len(letters) != array.ndim:
        raise NemoError(f"{group_path}: the metadata names {len(letters)} axes ({letters}) but level "
                        f"{level} has {array.ndim} dimensions")
    factors = _scale(ms, level, group_path)
    scale = dict(zip(letters, factors or []))
    # no scale: the sizes are unknown, whatever unit the axes name
    units = {letter: a.get("unit") for letter, a in zip(letters, ms["axes"]) if isinstance(a, dict) and factors is not None}
    return {"axes": letters, "shape": dict(zip(letters, array.shape)), "dtype": str(array.dtype),
            "spacing": tuple(float(scale.get(a, 1.0)) for a in "ZYX"),
            "units": [units.get(a) for a in "ZYX"], "group": group_path, "level": level}


def _letters(ms: dict, path: Path) -> str:
    """One letter per axis (T, C, Z, Y, X): single-letter names as they are, ``time`` and
    ``channel`` axes (by name or NGFF ``type``) as T and C."""
    named, out = {"time": "T", "channel": "C"}, []
    for a in ms.get("axes") or []:
        name = str(a.get("name", "") if isinstance(a, dict) else a)
        kind = a.get("type") if isinstance(a, dict) else None
        letter = name.upper() if len(name) == 1 else named.get(name.lower()) or named.get(kind)
        if letter is None or letter not in "TCZYX":
            raise NemoError(f"{path}: OME-Zarr axis {name!r} is none of t, c, z, y, x (nor a 'time' or "
                            "'channel' axis); fix the metadata's 'axes'")
        out.append(letter)
    return "".join(out)


def _level_array(group, level: str, path: Path):
    """The array of one resolution level (a NemoError when the metadata names a missing one)."""
    try:
        return group[level]
    except (KeyError, ValueError, OSError) as exc:
        raise NemoError(f"{path}: the metadata names resolution level {level!r} but the folder has no such "
                        f"array ({exc}); copy the image again or fix the metadata") from None


def levels(path: str | os.PathLike) -> list[dict]:
    """Every resolution level of an OME-Zarr image: ``path`` (the folder to give), ``shape``
    (per axis letter) and ``spacing`` ``(dz, dy, dx)`` in the metadata's unit."""
    group_path, _ = locate(path)
    group = _open_group(group_path)
    ms = _multiscale(dict(group.attrs), group_path)
    letters = _letters(ms, group_path)
    out = []
    for d in _datasets(ms, group_path):
        scale = dict(zip(letters, _scale(ms, d["path"], group_path) or []))
        out.append({"path": str(group_path / d["path"]),
                    "shape": dict(zip(letters, _level_array(group, d["path"], group_path).shape)),
                    "spacing": tuple(float(scale.get(a, 1.0)) for a in "ZYX")})
    return out


def read(path: str | os.PathLike, key: dict[str, int], described: dict | None = None,
         sparse: bool = False) -> np.ndarray:
    """The pixels of one (t, c) selection, in the stored axis order without T and C.

    Parameters
    ----------
    path : path-like
        The OME-Zarr group or one of its level arrays.
    key : dict
        Index per axis letter to select (``{"T": 2, "C": 0}``); other axes are read whole.
    described : dict, optional
        :func:`describe`'s answer for ``path`` when the caller has it (the metadata is not read again).
    sparse : bool
        Chunks may be absent (a mask: writers skip those equal to the fill value): no check.
        Otherwise absent chunks of the selection warn, and a selection none of whose chunks is
        stored is refused (they would read as the fill value, silently).
    """
    d = described or describe(path)
    array = _open_group(d["group"])[d["level"]]
    index = tuple(key.get(a, slice(None)) for a in d["axes"])
    if not sparse:
        _check_chunks_stored(array, index, Path(d["group"]) / d["level"], key)
    try:
        return np.asarray(array[index])
    except (OSError, ValueError, KeyError, RuntimeError) as exc:
        raise NemoError(f"reading the pixels of {path} failed ({exc}): the Zarr chunks may be "
                        "missing or damaged; copy the image again") from None


def _check_chunks_stored(array, index: tuple, folder: Path, key: dict[str, int]) -> None:
    """Warn when chunks of the selection are absent from a local store (they read as the fill
    value, silently); refuse when all of them are. Zarr writers may skip a chunk equal to the
    fill value, so a few absent chunks can be legitimate; a whole stack cannot be analysed."""
    if not folder.is_dir():  # not a local folder (a remote store): zarr reports what it cannot read
        return
    grid = array.shards or array.chunks  # the stored unit: a shard holds several chunks
    ranges = [range(i // g, i // g + 1) if isinstance(i, int) else range(-(-n // g))
              for i, g, n in zip(index, grid, array.shape)]
    coords = np.stack(np.meshgrid(*[np.asarray(r) for r in ranges], indexing="ij"), -1).reshape(-1, len(grid))
    absent = sum(not (folder / array.metadata.encode_chunk_key(tuple(int(c) for c in xyz))).is_file()
                 for xyz in coords)  # one stat per chunk of one stack: tens to thousands, not per pixel
    where = ", ".join(f"{a.lower()} = {v}" for a, v in key.items()) or "the image"
    if absent == len(coords):
        raise NemoError(f"none of the {len(coords)} Zarr chunks of {where} is stored in {folder}: the stack "
                        f"would read as the fill value {array.fill_value} everywhere; the copy is incomplete "
                        "(copy the image again) or that time point / channel was never written")
    if absent:
        warnings.warn(f"{absent} of {len(coords)} Zarr chunks of {where} are not stored in {folder}: they read "
                      f"as the fill value {array.fill_value}. Writers skip chunks equal to it; if that is not "
                      "why, the copy is incomplete: copy the image again", NemoWarning, stacklevel=3)


def write(path: str | os.PathLike, data: np.ndarray, spacing: tuple[float, float, float],
          axes: str = "TCZYX", unit: str = "micrometer", levels: int = 1,
          chunks: tuple[int, ...] | None = None, zarr_format: int = 2) -> Path:
    """Write an OME-Zarr image (NGFF 0.4 for Zarr format 2, 0.5 for format 3), atomically.

    Parameters
    ----------
    data : ndarray
        Pixels with the axes in ``axes`` (a subset of T, C, Z, Y, X in that order).
    spacing : (dz, dy, dx)
        Voxel size in ``unit`` at level 0.
    levels : int
        Resolution levels; level k is level 0 down-sampled by 2^k in Y and X (every 2^k-th
        pixel: enough for tests and previews).
    chunks : tuple, optional
        Chunk shape; default one (Z, Y, X) stack per chunk.
    """
    import shutil

    final = Path(path)
    # a folder, not a file (nemo.atomic.atomic_path): written beside the target, then renamed
    tmp = final.with_name(f".{final.name}.partial{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        _write_group(tmp, data, spacing, axes.upper(), unit, levels, chunks, zarr_format, final.stem)
        if final.exists():
            shutil.rmtree(final)
        os.replace(tmp, final)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return final


def _write_group(path: Path, data, spacing, axes: str, unit: str, levels: int, chunks, zarr_format: int,
                 name: str) -> None:
    """The body of :func:`write`, into ``path``."""
    import zarr

    dz, dy, dx = spacing
    size = {"Z": dz, "Y": dy, "X": dx}
    kind = {"T": "time", "C": "channel"}
    meta_axes = [{"name": a.lower(), "type": kind.get(a, "space"),
                  **({"unit": unit} if a in "ZYX" else {})} for a in axes]
    root = zarr.open_group(str(path), mode="w", zarr_format=zarr_format)
    datasets = []
    for k in range(levels):
        step = tuple(2**k if a in "YX" else 1 for a in axes)
        level = data[tuple(slice(None, None, s) for s in step)]
        default = tuple(n if a in "ZYX" else 1 for a, n in zip(axes, level.shape))
        root.create_array(str(k), data=level, chunks=chunks or default)
        scale = [size.get(a, 1.0) * s for a, s in zip(axes, step)]
        datasets.append({"path": str(k), "coordinateTransformations": [{"type": "scale", "scale": scale}]})
    ms = {"version": "0.4" if zarr_format == 2 else "0.5", "axes": meta_axes, "datasets": datasets,
          "name": name}
    if zarr_format == 2:
        root.attrs["multiscales"] = [ms]
    else:
        ms.pop("version")
        root.attrs["ome"] = {"version": "0.5", "multiscales": [ms]}
