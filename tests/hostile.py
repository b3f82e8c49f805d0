"""A corpus of corrupt and hostile inputs for the ``nemo`` commands, built at test time.

:func:`build_corpus` writes every item into a folder (a few MB, a few seconds) and returns a
:class:`Corpus`: ``corpus["img.valid"]`` is the path of one item. The valid items (mesh,
tables) are made by the ``nemo`` commands themselves from a small synthetic vesicle (64³
voxels); the hostile ones are derived from them or written by hand.

Items by group (the name before the dot):

* ``img``: TIFF-ish inputs -- ``valid`` (synthetic vesicle, R = 20 µm), ``trunc_page`` (cut at a
  page boundary), ``trunc_mid`` (cut in the middle of a page), ``trunc_ifd`` (all pixels, the
  IFDs of the last pages cut), ``text`` (a text file named
  .tif), ``flat`` (a 2-D image), ``png`` (a PNG named .tif), ``empty`` (0 bytes), ``folder`` (a
  folder named x.tif), ``nan`` (float image with a NaN slab), ``huge`` (values up to 1e300),
  ``uncal`` (no calibration), ``two`` (two separate hollow spheres), ``zero`` (all zero),
  ``missing`` (does not exist);
* ``mesh``: ``whole``/``inner``/``outer`` (``nemo mesh`` of the valid image), ``half`` and
  ``nm`` (inner scaled by 0.5, and by 1000 with the unit nm), ``bowtie`` (two spheres sharing a
  vertex), ``dupface`` (inner with a duplicated face), ``cut`` (PLY cut inside its header),
  ``garbage`` (an OBJ of text garbage), ``points`` (a PLY point cloud), ``missing``;
* ``tab``: ``layer``, ``directors``, ``order``, ``defects``, ``curvature``, ``thickness`` (made
  by the commands on ``mesh.inner``), ``layer_outer``, ``directors_outer``, ``curvature_outer``
  (made on ``mesh.outer``: another mesh), ``directors_half`` (positions of another mesh with
  the same vertex count), ``wrongcols`` (a Parquet with other columns), ``csv`` (a CSV named
  .parquet), ``empty`` (0 bytes), ``defects_t`` (defects of two frames, column t),
  ``missing``;
* ``frame``/``frame_bad``: frame folders for ``nemo render`` (the valid files named as the
  workflow names them; the same with a cut mesh and a CSV order table), ``summary`` (a summary
  folder with tracked defects);
* ``cfg``: YAML configs for ``nemo run --config`` -- ``valid``, ``neg_seed``, ``radius0``,
  ``unknown``, ``types``, ``huge``, ``strnum``, ``nan``, ``notyaml``, ``list``;
* ``odd``: copies of the valid image under odd names (``space``, ``unicode``, ``subst``
  = ``$(touch pwned)``, ``semicolon``, ``dash`` = a leading dash) and ``mesh_space`` (the inner
  mesh in a folder and file with spaces);
* ``block``: a plain file (outputs under it cannot be created).
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import shutil
from pathlib import Path

import numpy as np

#: Small synthetic vesicle: R = 20 µm in a 64³ stack of 1 µm voxels (about 1.5 s).
SYNTH_ARGS = ("--radius", "20", "--size", "64", "--fibre-spacing", "2", "--fibre-length", "10",
              "--shell-thickness", "4", "--blur", "0.8", "--seed", "0")

#: Names of the odd-path copies of the valid image.
ODD_NAMES = {
    "space": "with space.tif",
    "unicode": "ünïcødé µm ✓.tif",
    "subst": "$(touch pwned).tif",
    "semicolon": "a;touch pwned2;b.tif",
    "dash": "-dash.tif",
}

#: Files whose existence after a command means a file name reached a shell.
PWNED = ("pwned", "pwned2")


class Corpus(dict):
    """Item name (``group.item``) -> Path, plus the folder and helpers."""

    def __init__(self, root: Path):
        super().__init__()
        self.root = root

    def add(self, name: str, path: Path) -> Path:
        self[name] = path
        return path

    def snapshot(self) -> dict[str, str]:
        """Relative path -> sha256 (``<dir>`` for folders) of everything in the corpus."""
        return snapshot(self.root, self.__dict__.setdefault("_hashes", {}))


def snapshot(root: Path, cache: dict | None = None) -> dict[str, str]:
    """Relative path -> sha256 (``<dir>`` for folders) of everything under ``root``.

    With ``cache``, a file whose size, modification time and inode are unchanged since the last
    call keeps its hash (every write or replacement changes them).
    """
    out = {}
    for p in sorted(root.rglob("*")):
        rel = str(p.relative_to(root))
        if p.is_dir():
            out[rel] = "<dir>"
            continue
        st = p.stat()
        key = (st.st_size, st.st_mtime_ns, st.st_ino, st.st_ctime_ns)
        if cache is not None and rel in cache and cache[rel][0] == key:
            out[rel] = cache[rel][1]
            continue
        out[rel] = hashlib.sha256(p.read_bytes()).hexdigest()
        if cache is not None:
            cache[rel] = (key, out[rel])
    return out


def restore(root: Path, pristine: Path) -> None:
    """Make ``root`` equal to its pristine copy again (after a command damaged it)."""
    shutil.rmtree(root)
    shutil.copytree(pristine, root, symlinks=True)


def nemo(*argv) -> None:
    """Run a ``nemo`` command in-process to build an item; fail loudly if it does not work."""
    from nemo.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main([str(a) for a in argv])
        except SystemExit as exc:  # argparse
            code = exc.code
    if code != 0:
        raise RuntimeError(f"building the corpus: nemo {' '.join(map(str, argv))} -> exit {code}\n"
                           f"{err.getvalue()}")


# --------------------------------------------------------------------------------------------- images

def _shell_image(shape=(64, 64, 64), centres=((32, 32, 32),), radius=10.0, width=2.5, amp=200.0):
    """Blurred hollow spheres (voxel units), uint8."""
    z, y, x = np.indices(shape, dtype=np.float32)
    img = np.zeros(shape, np.float32)
    for cz, cy, cx in centres:
        r = np.sqrt((z - cz) ** 2 + (y - cy) ** 2 + (x - cx) ** 2)
        img += amp * np.exp(-(((r - radius) / width) ** 2))
    return np.clip(img, 0, 255).astype(np.uint8)


def _png_bytes() -> bytes:
    """A valid 32 x 32 greyscale PNG (written by hand: no imaging library needed)."""
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    rows = b"".join(b"\x00" + bytes((x * 8 + y) % 256 for x in range(32)) for y in range(32))
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 32, 32, 8, 0, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(rows)) + chunk(b"IEND", b""))


def _images(c: Corpus) -> None:
    import tifffile

    from nemo.io import write_hyperstack

    d = c.root / "img"
    d.mkdir()
    valid = c.add("img.valid", d / "valid.tif")
    nemo("synth", valid, *SYNTH_ARGS)
    (d / "valid.truth.json").unlink()  # keep the image folder to images
    pixels = tifffile.imread(valid)  # (Z, Y, X) uint8
    assert pixels.shape == (64, 64, 64), pixels.shape
    raw = valid.read_bytes()
    with tifffile.TiffFile(valid) as tif:
        page = tif.pages[40]
        ifd = page.offset  # tifffile writes page 0's IFD first, the other IFDs after the pixels
        boundary = page.dataoffsets[0]  # pages 0-39 complete, nothing of page 40
        mid = page.dataoffsets[0] + page.databytecounts[0] // 2
    assert 0 < boundary < mid < len(raw) and 0 < ifd < len(raw), (boundary, mid, ifd, len(raw))
    c.add("img.trunc_page", d / "trunc_page.tif").write_bytes(raw[:boundary])
    c.add("img.trunc_mid", d / "trunc_mid.tif").write_bytes(raw[:mid])
    c.add("img.trunc_ifd", d / "trunc_ifd.tif").write_bytes(raw[:ifd])  # pixels whole, IFDs 40-63 cut
    c.add("img.text", d / "text.tif").write_text("This is not a TIFF file.\n" * 20)
    tifffile.imwrite(c.add("img.flat", d / "flat.tif"), pixels[32])
    c.add("img.png", d / "png.tif").write_bytes(_png_bytes())
    c.add("img.empty", d / "empty.tif").write_bytes(b"")
    c.add("img.folder", d / "folder.tif").mkdir()
    nan = pixels.astype(np.float32)
    nan[:, :, 28:36] = np.nan  # a NaN slab through the vesicle
    write_hyperstack(c.add("img.nan", d / "nan.tif"), nan, (1.0, 1.0, 1.0), axes="ZYX")
    huge = pixels.astype(np.float64) * (1e300 / 255.0)  # OME: ImageJ has no float64
    write_hyperstack(c.add("img.huge", d / "huge.tif"), huge, (1.0, 1.0, 1.0), axes="ZYX", ome=True)
    tifffile.imwrite(c.add("img.uncal", d / "uncal.tif"), pixels)  # no resolution, no unit
    two = _shell_image(centres=((32, 18, 18), (32, 46, 46)), radius=10.0)
    write_hyperstack(c.add("img.two", d / "two.tif"), two, (1.0, 1.0, 1.0), axes="ZYX")
    write_hyperstack(c.add("img.zero", d / "zero.tif"), np.zeros((64, 64, 64), np.uint8), (1.0, 1.0, 1.0),
                     axes="ZYX")
    c["img.missing"] = d / "missing.tif"
    _zarr_images(c, d, pixels)


def _zarr_images(c: Corpus, d: Path, pixels: np.ndarray) -> None:
    """OME-Zarr: the valid vesicle, a Zarr group without OME metadata, one with damaged chunks."""
    import zarr

    from nemo import ome_zarr

    ome_zarr.write(c.add("img.zarr", d / "valid.zarr"), pixels, (1.0, 1.0, 1.0), axes="ZYX", levels=2)
    zarr.open_group(str(c.add("img.zarr_plain", d / "plain.zarr")), mode="w").create_array("0", data=pixels)
    broken = c.add("img.zarr_chunks", d / "chunks.zarr")
    ome_zarr.write(broken, pixels, (1.0, 1.0, 1.0), axes="ZYX", chunks=(16, 64, 64))
    for chunk in (p for p in (broken / "0").iterdir() if p.is_file() and not p.name.startswith(".")):
        chunk.write_bytes(b"\x00garbage")


# --------------------------------------------------------------------------------------------- meshes

def _bowtie():
    """Two icospheres that share one vertex (a non-manifold vertex), in µm inside the image."""
    import trimesh

    a = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    va, fa = np.asarray(a.vertices), np.asarray(a.faces)
    p = va[0]
    vb = 2 * p - va  # point reflection through p: vertex 0 of B is p
    fb = fa[:, ::-1].copy()  # a reflection flips the winding; flip it back to outward
    keep = np.arange(1, len(vb))
    remap = np.empty(len(vb), int)
    remap[0] = 0
    remap[keep] = len(va) + np.arange(len(keep))
    vertices = np.vstack([va, vb[keep]]) * 8.0 + 32.0
    faces = np.vstack([fa, remap[fb]])
    return vertices, faces


def _meshes(c: Corpus) -> None:
    import trimesh

    from nemo.mesh import load_mesh, save_mesh

    d = c.root / "mesh"
    d.mkdir()
    whole = c.add("mesh.whole", d / "mesh.ply")
    nemo("mesh", c["img.valid"], "-o", whole)
    c.add("mesh.inner", d / "mesh.inner.ply")
    c.add("mesh.outer", d / "mesh.outer.ply")
    inner = load_mesh(c["mesh.inner"])
    spacing = inner.metadata.get("spacing")

    def scaled(name, factor, unit):
        m = trimesh.Trimesh(vertices=np.asarray(inner.vertices) * factor, faces=inner.faces, process=False)
        m.units = unit
        if spacing is not None:
            m.metadata["spacing"] = tuple(float(s) * (1000.0 if unit == "nm" else 1.0) for s in spacing)
        save_mesh(m, c.add(f"mesh.{name}", d / f"{name}.ply"))

    scaled("half", 0.5, "um")  # same unit, half the size: sits off the vesicle
    scaled("nm", 1000.0, "nm")  # the same surface in nanometres
    v, f = _bowtie()
    bow = trimesh.Trimesh(vertices=v, faces=f, process=False)
    bow.units = "um"
    save_mesh(bow, c.add("mesh.bowtie", d / "bowtie.ply"))
    dup = trimesh.Trimesh(vertices=inner.vertices, faces=np.vstack([inner.faces, inner.faces[:1]]), process=False)
    dup.units = "um"
    save_mesh(dup, c.add("mesh.dupface", d / "dupface.ply"))
    raw = c["mesh.inner"].read_bytes()
    header_end = raw.index(b"end_header")
    c.add("mesh.cut", d / "cut.ply").write_bytes(raw[: header_end // 2])
    c.add("mesh.garbage", d / "garbage.obj").write_text(
        "this is not an OBJ file\nv one two three\nf x y z\n\x00\x01 garbage ~~~ {}\n" * 5)
    pts = np.random.default_rng(0).uniform(20, 44, size=(200, 3))
    text = ("ply\nformat ascii 1.0\ncomment nemo unit um\nelement vertex 200\nproperty float x\n"
            "property float y\nproperty float z\nend_header\n"
            + "".join(f"{x:.4f} {y:.4f} {z:.4f}\n" for x, y, z in pts))
    c.add("mesh.points", d / "points.ply").write_text(text)
    c["mesh.missing"] = d / "missing.ply"


# --------------------------------------------------------------------------------------------- tables

def _tables(c: Corpus) -> None:
    import pandas as pd

    from nemo.tables import read_provenance, read_table, write_table

    d = c.root / "tab"
    d.mkdir()
    img, inner, outer = c["img.valid"], c["mesh.inner"], c["mesh.outer"]
    nemo("peel", img, inner, "-o", c.add("tab.layer", d / "layer.parquet"))
    nemo("directors", inner, c["tab.layer"], "-o", c.add("tab.directors", d / "directors.parquet"))
    nemo("order", inner, c["tab.directors"], "-o", c.add("tab.order", d / "order.parquet"))
    nemo("defects", inner, c["tab.order"], c["tab.directors"], "-o", c.add("tab.defects", d / "defects.parquet"))
    nemo("curvature", inner, "-o", c.add("tab.curvature", d / "curvature.parquet"))
    nemo("thickness", inner, outer, "-o", c.add("tab.thickness", d / "thickness.parquet"))
    # tables of another mesh
    nemo("peel", img, outer, "-o", c.add("tab.layer_outer", d / "layer_outer.parquet"))
    nemo("directors", outer, c["tab.layer_outer"], "-o", c.add("tab.directors_outer", d / "directors_outer.parquet"))
    nemo("curvature", outer, "-o", c.add("tab.curvature_outer", d / "curvature_outer.parquet"))
    # another mesh with the same vertex count (the half-size copy): positions do not match
    dirs = read_table(c["tab.directors"])
    prov = read_provenance(c["tab.directors"])
    prov.pop("version", None)
    half = dirs.copy()
    half[["x", "y", "z"]] = half[["x", "y", "z"]] * 0.5
    prov["mesh"] = str(c["mesh.half"])
    write_table(half, c.add("tab.directors_half", d / "directors_half.parquet"), **prov)
    pd.DataFrame({"a": [1, 2, 3], "b": [0.5, 1.5, 2.5]}).to_parquet(c.add("tab.wrongcols", d / "wrongcols.parquet"))
    c.add("tab.csv", d / "csv.parquet").write_text("vertex,intensity,x,y,z,t\n0,1.0,0,0,0,0\n1,2.0,1,1,1,0\n")
    c.add("tab.empty", d / "empty.parquet").write_bytes(b"")
    # defects of two frames (the workflow's aggregated table): frame 1 moved by 0.5 µm
    defects = read_table(c["tab.defects"])
    frames = []
    for t in (0, 1):
        f = defects.copy()
        f["t"] = t
        f["x"] = f["x"] + 0.5 * t
        if "min_distance" not in f:
            f["min_distance"] = 10.0
        frames.append(f)
    write_table(pd.concat(frames, ignore_index=True), c.add("tab.defects_t", d / "defects_t.parquet"),
                unit="um", command="test corpus")
    c["tab.missing"] = d / "missing.parquet"


def _folders(c: Corpus) -> None:
    """Frame folders for ``nemo render`` and a summary folder."""
    frame = c.add("frame", c.root / "frame")
    frame.mkdir()
    for item, name in [("mesh.whole", "mesh.ply"), ("mesh.inner", "mesh.inner.ply"),
                       ("mesh.outer", "mesh.outer.ply"), ("tab.layer", "layer_fibres.parquet"),
                       ("tab.directors", "directors_fibres.parquet"), ("tab.order", "order_fibres.parquet"),
                       ("tab.defects", "defects_fibres.parquet"), ("tab.curvature", "curvature_inner.parquet"),
                       ("tab.thickness", "thickness.parquet")]:
        shutil.copyfile(c[item], frame / name)
    bad = c.add("frame_bad", c.root / "frame_bad")
    shutil.copytree(frame, bad)
    shutil.copyfile(c["mesh.cut"], bad / "mesh.inner.ply")
    shutil.copyfile(c["tab.csv"], bad / "order_fibres.parquet")
    summary = c.add("summary", c.root / "summary")
    summary.mkdir()
    scratch = c.root / "scratch_tracks.parquet"
    nemo("track", c["tab.defects_t"], "-o", scratch, "--linked", summary / "defects.parquet")
    scratch.unlink()


# --------------------------------------------------------------------------------------------- configs

CONFIGS = {
    # a valid config that keeps `nemo run` short: no curvature, no refinement pass
    "valid": {"curvature": None, "defects": {"refine_directors": 0}, "layers": {"fibres": {"range": [0, 5]}}},
    "neg_seed": {"directors": {"seed": -1}},
    "radius0": {"order": {"radius": 0}},
    "unknown": {"mesh": {"stp": 2}, "nonsense": True},
    "types": {"mesh": {"smooth": "ten", "keep": 3}, "layers": {"fibres": {"range": "0-5"}}},
    "huge": {"curvature": None, "defects": {"refine_directors": 0}, "order": {"radius": 1e308},
             "directors": {"patch_radius": 1e308}},
    "strnum": {"order": {"radius": "15"}, "directors": {"seed": "0"}},
    "nan": {"order": {"radius": float("nan")}},
}


def _configs(c: Corpus) -> None:
    import yaml

    d = c.root / "cfg"
    d.mkdir()
    for name, cfg in CONFIGS.items():
        c.add(f"cfg.{name}", d / f"{name}.yaml").write_text(yaml.safe_dump(cfg))
    c.add("cfg.notyaml", d / "notyaml.yaml").write_text("mesh: [unclosed\n  : : :\n\t- x")
    c.add("cfg.list", d / "list.yaml").write_text("- mesh\n- order\n")
    c["cfg.missing"] = d / "missing.yaml"


def _odd(c: Corpus) -> None:
    d = c.root / "odd"
    d.mkdir()
    for key, name in ODD_NAMES.items():
        shutil.copyfile(c["img.valid"], c.add(f"odd.{key}", d / name))
    folder = d / "my meshes; $(touch pwned)"
    folder.mkdir()
    shutil.copyfile(c["mesh.inner"], c.add("odd.mesh_space", folder / "inner mesh ✓.ply"))
    c.add("block", c.root / "block").write_text("a plain file: no folder can be created under it\n")


def build_corpus(root: str | Path) -> Corpus:
    """Write the whole corpus into ``root`` (created) and return it."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    c = Corpus(root)
    _images(c)
    _meshes(c)
    _tables(c)
    _folders(c)
    _configs(c)
    _odd(c)
    (root / "corpus.json").write_text(json.dumps({k: str(v) for k, v in c.items()}, indent=1))
    return c


# --------------------------------------------------------------------------------------------- running

def where(exc: BaseException) -> str:
    """file:line of the deepest frame in nemo/ (else the deepest frame) of an exception."""
    import traceback

    frames = traceback.extract_tb(exc.__traceback__)
    ours = [f for f in frames if "/nemo/" in f.filename.replace("\\", "/") and "/tests/" not in f.filename
            and "/site-packages/" not in f.filename]
    f = (ours or frames)[-1]
    if ours:
        return f"nemo/{f.filename.replace(chr(92), '/').rsplit('/nemo/', 1)[-1]}:{f.lineno} in {f.name}"
    return f"{Path(f.filename).name}:{f.lineno} in {f.name}"


def child_main(argv: list[str], result_path: str, extra_memory: int) -> None:
    """Run ``nemo ARGV`` in a forked child and write {code, out, err} (or the uncaught
    exception) as JSON to ``result_path``; the address space is limited to what the child
    starts with plus ``extra_memory`` bytes (a runaway allocation is then a MemoryError)."""
    import resource
    import sys
    import traceback

    try:
        status = Path("/proc/self/status").read_text().splitlines()
        vm = next(int(line.split()[1]) * 1024 for line in status if line.startswith("VmSize:"))
        resource.setrlimit(resource.RLIMIT_AS, (vm + extra_memory, vm + extra_memory))
    except (OSError, StopIteration, ValueError):
        pass
    out, err = io.StringIO(), io.StringIO()
    res: dict = {}
    sys.stdout, sys.stderr = out, err
    try:
        from nemo.cli import main

        res["code"] = main(list(argv))
    except SystemExit as exc:
        res["code"] = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    except BaseException as exc:  # noqa: BLE001 - reported to the test
        res["exception"] = f"{type(exc).__name__} at {where(exc)}: {str(exc)[:500]}"
        res["traceback"] = "".join(traceback.format_exception(exc)[-6:])
    finally:
        sys.stdout, sys.stderr = sys.__stdout__, sys.__stderr__
    res["out"], res["err"] = out.getvalue(), err.getvalue()
    Path(result_path).write_text(json.dumps(res))
