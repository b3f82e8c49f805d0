"""Options and helpers shared by the ``nemo`` subcommands."""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path

from nemo.atomic import make_folder
from nemo.errors import NemoError


def add_common(
    parser: argparse.ArgumentParser,
    frame: bool = False,
    output: bool = True,
    output_help: str = "output file",
    output_required: bool = True,
    deconvolved: bool = False,
) -> None:
    """Add the options every subcommand shares.

    ``--t/--c/--spacing/--psf`` only for commands that read an image (``frame=True``), and
    ``--deconvolved`` for those that deconvolve it (``deconvolved=True``: nemo mesh and peel).
    """
    if frame:
        parser.add_argument("--t", type=int, default=0, metavar="T", help="time point (0-based, default 0)")
        parser.add_argument("--c", type=int, default=0, metavar="C", help="channel (0-based, default 0)")
        parser.add_argument(
            "--spacing", type=number, nargs=3, metavar=("DZ", "DY", "DX"),
            help="voxel size in µm, overriding the file's calibration",
        )
        parser.add_argument(
            "--psf", type=non_negative, nargs=3, metavar=("SZ", "SY", "SX"),
            help="the microscope's PSF as Gaussian standard deviations in the image's unit, usually µm "
                 "(FWHM / 2.355): the image is deconvolved by it (Richardson-Lucy, 30 iterations) before "
                 "meshing and peeling (an automatic mesh level is taken on the image before); --psf auto "
                 "(the default; nemo run: the dataset's psf, auto unless set) estimates the PSF's blur along "
                 "z beyond the lateral from the image's "
                 "autocovariance and deconvolves that where there is one (an object facing every way: a "
                 "vesicle, an organoid; a flat sheet, a cut or z-elongated object, an isotropic PSF: not "
                 "deconvolved); --psf none deconvolves nothing; give the same to nemo mesh and nemo peel (or "
                 "deconvolve once with nemo deconvolve and give both --deconvolved)",
        )
        parser.add_argument("--psf-auto", dest="psf", action="store_const", const="auto", help=argparse.SUPPRESS)
        parser.add_argument("--psf-none", dest="psf", action="store_const", const="none", help=argparse.SUPPRESS)
        if deconvolved:
            parser.add_argument(
                "--deconvolved", metavar="FILE.tif",
                help="this frame deconvolved by --psf once, with nemo deconvolve: used instead of deconvolving "
                     "again (its frame, spacing and PSF must be this step's)",
            )
    if output:
        parser.add_argument("-o", "--output", required=output_required, metavar="FILE", help=output_help)
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv: debug)")


#: Largest magnitude of a number on the command line (lengths in the image's unit, counts):
#: beyond it a value is a mistake (a unit mix-up) and would overflow what it sizes. The config
#: schema bounds lengths the same way.
MAX_VALUE = 1e9


def number(text: str) -> float:
    """argparse type: a finite number of magnitude at most :data:`MAX_VALUE`."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value) or abs(value) > MAX_VALUE:
        raise argparse.ArgumentTypeError(f"must be a finite number between -{MAX_VALUE:g} and {MAX_VALUE:g}, "
                                         f"got {text}")
    return value


def positive(kind=float, minimum: float | None = None):
    """argparse type: a number in [``minimum``, :data:`MAX_VALUE`] (``kind`` float or int;
    ``minimum`` default 1e-9 for lengths, 1 for counts)."""
    minimum = (1 if kind is int else 1e-9) if minimum is None else minimum

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            what = "a whole number" if kind is int else "a number"
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
        if not value > 0:
            raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
        if not minimum <= value <= MAX_VALUE:
            raise argparse.ArgumentTypeError(f"must be between {minimum:g} and {MAX_VALUE:g}, got {text}")
        return value

    return parse


def non_negative(text: str) -> float:
    """argparse type: a number in [0, :data:`MAX_VALUE`] (0 switches a blur or a shift off)."""
    value = number(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be ≥ 0, got {text}")
    return value


def psf_auto_option(argv: list[str]) -> list[str]:
    """``--psf auto`` / ``--psf none`` (or ``--psf=auto``, ``--psf=none``) as the hidden ``--psf-auto`` /
    ``--psf-none``: ``--psf`` itself takes three numbers, so that it never swallows an image or mesh
    written after it."""
    words = ("auto", "none")
    out, i = [], 0
    while i < len(argv):
        if argv[i] == "--psf" and i + 1 < len(argv) and argv[i + 1] in words:
            out.append(f"--psf-{argv[i + 1]}")
            i += 2
            continue
        word = argv[i].removeprefix("--psf=")
        out.append(f"--psf-{word}" if argv[i].startswith("--psf=") and word in words else argv[i])
        i += 1
    return out


def step_psf(args) -> None:
    """``args.psf`` of nemo mesh and nemo peel resolved: the config's default (``auto``) when not given,
    None for ``none``, else three checked numbers (as ``datasets.NAME.psf`` is for nemo run)."""
    from nemo.config import dataset_default
    from nemo.psf import check_psf

    args.psf = check_psf(dataset_default("psf") if args.psf is None else args.psf, "--psf")


def seed(text: str) -> int:
    """argparse type: a random seed, an integer in [0, 2**32 - 1] (numpy's range)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if not 0 <= value < 2**32:
        raise argparse.ArgumentTypeError(f"must be between 0 and {2**32 - 1}, got {text}")
    return value


def output_path(path: str | Path, suffixes: tuple[str, ...] = (".parquet",)) -> Path:
    """Check an output path's suffix and create its folder.

    Raises
    ------
    NemoError
        Wrong suffix, an existing folder of that name, or a folder that cannot be created
        (a file in the way, no permission).
    """
    path = Path(path)
    if suffixes and path.suffix.lower() not in suffixes:
        raise NemoError(f"output {path} should end in {' or '.join(suffixes)}")
    if path.is_dir():
        raise NemoError(f"output {path} is a folder: give a file name ending in {' or '.join(suffixes)}")
    make_folder(path.parent)
    return path


#: Option names (argparse ``dest``) that name files a command writes.
OUTPUT_OPTIONS = ("output", "refined", "linked", "candidates")


def input_files(args: argparse.Namespace) -> list[str]:
    """Every argument that names an existing file and is not an output (:data:`OUTPUT_OPTIONS`)."""
    inputs = []
    for name, value in vars(args).items():
        if name in OUTPUT_OPTIONS or name.startswith("_"):
            continue
        for item in value if isinstance(value, list) else [value]:
            if not isinstance(item, str):
                continue
            # FILE or FILE:COLUMN (e.g. nemo peel --shift thickness.parquet:thickness)
            inputs += [path for path in (item, item.rpartition(":")[0]) if path and os.path.isfile(path)]
    return inputs


def refuse_to_overwrite(out: str | os.PathLike, inputs: list[str], flag: str = "-o") -> None:
    """Raise :class:`NemoError` when the output ``out`` is one of ``inputs`` (it would be replaced)."""
    if not os.path.exists(out):
        return
    same = next((i for i in inputs if os.path.samefile(i, out)), None)
    if same is not None:
        raise NemoError(
            f"the output {out} ({flag}) is the input {same}: writing it would destroy the input; "
            "choose another output file name"
        )


def check_outputs_are_not_inputs(args: argparse.Namespace) -> None:
    """Refuse a command whose output file is one of its input files (:func:`input_files`)."""
    inputs = input_files(args)
    for name in OUTPUT_OPTIONS:
        if getattr(args, name, None):
            refuse_to_overwrite(getattr(args, name), inputs, "-o" if name == "output" else f"--{name}")


def print_json(obj) -> None:
    json.dump(obj, sys.stdout, indent=2, default=str)
    sys.stdout.write("\n")


def mesh_and_table(mesh_path, table_path, kind: str):
    """The mesh and a table of ``kind`` computed on it (refused when made on another mesh).

    Shared by the commands that take ``MESH TABLE`` (directors, order).

    Returns
    -------
    mesh : trimesh.Trimesh
    table : DataFrame
    provenance : dict
        ``mesh``, ``n_vertices`` and ``unit`` for the output table (the mesh convention).
    """
    from nemo.mesh import load_mesh
    from nemo.tables import read_table

    mesh = load_mesh(mesh_path)
    n_vertices = len(mesh.vertices)
    table = read_table(table_path, kind=kind, n_vertices=n_vertices)
    provenance = dict(mesh=str(mesh_path), n_vertices=n_vertices, unit=getattr(mesh, "units", None) or "um")
    return mesh, table, provenance


def section_params(args: argparse.Namespace, name: str) -> dict:
    """The options of a step command that belong to config section ``name`` (None = default).

    Every key of the section is a long option of the same name (``patch_radius`` is
    ``--patch-radius``), so a rule's ``cli_opts(section)`` and a user's flags meet here.
    """
    from nemo.config import section_defaults

    return {key: getattr(args, key) for key in section_defaults(name) if hasattr(args, key)}


def add_mask_arguments(parser: argparse.ArgumentParser) -> None:
    """``--mask`` and the flags that select from it (``nemo mesh``, ``nemo run``)."""
    parser.add_argument("--mask", metavar="MASK",
                        help="segmentation used instead of the threshold (TIFF or OME-Zarr; same Z, Y, X "
                             "size as the image; its own T and C axes when it has them: the time point and "
                             "the channel meshed, else 0): a binary mask (nonzero = object), a label image or "
                             "a probability map")
    parser.add_argument("--mask-labels", type=int, nargs="+", metavar="LABEL",
                        help="labels of the object in a label image --mask (default: every nonzero label)")
    parser.add_argument("--mask-threshold", type=number, metavar="P",
                        help="object where the --mask value exceeds P (default 0.5 for a floating-point "
                             "probability map, else nonzero)")
    parser.add_argument("--mask-channel", type=int, metavar="C",
                        help="the --mask's channel to use (a probability map with a channel per class: the "
                             "object's class; default: --c when the mask has channels)")


def mask_options(args: argparse.Namespace) -> dict | None:
    """The ``--mask`` flags as a dataset's keys (``mask``, ``mask_labels``, ``mask_threshold``,
    ``mask_channel``), or None without ``--mask``; the selection flags need the mask."""
    if (args.mask_labels or args.mask_threshold is not None or args.mask_channel is not None) and not args.mask:
        raise NemoError("--mask-labels, --mask-threshold and --mask-channel select from a --mask: give the mask file")
    if not args.mask:
        return None
    return {"mask": args.mask, "mask_labels": args.mask_labels, "mask_threshold": args.mask_threshold,
            "mask_channel": args.mask_channel}
