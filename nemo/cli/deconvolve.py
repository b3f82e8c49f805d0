"""``nemo deconvolve``: one channel of one time point deconvolved by the PSF, for nemo mesh and peel."""

from __future__ import annotations

import warnings

from nemo.cli.common import add_common, output_path
from nemo.errors import NemoError, NemoWarning

HELP = "deconvolve one frame by the PSF once, for nemo mesh and nemo peel (--deconvolved)"
DESCRIPTION = """\
Deconvolve the stack of time point --t and channel --c by the microscope's PSF (--psf, Gaussian
standard deviations in the image's unit: Richardson-Lucy, 30 iterations, as nemo mesh and nemo
peel do with --psf) and write it as a float32 TIFF that records the PSF, the frame, the spacing
and the stack's shape. nemo mesh and nemo peel take it with --deconvolved FILE (and the same
image, --t, --c, --spacing and --psf, which they check) instead of deconvolving again: the
workflow deconvolves each frame once this way, as nemo run does in memory. --psf auto (the
default, as for nemo mesh, peel and run) estimates the PSF's z blur beyond the lateral from the
image. When the PSF is below a quarter of a voxel on every axis, or auto finds no z blur worth
undoing, nothing is deconvolved, and the file holds only that record (and why).

examples:
  nemo deconvolve stack.tif --t 0 --c 1 -o deconvolved.tif      # --psf auto
  nemo deconvolve stack.tif --t 0 --c 1 --psf 2.5 0.8 0.8 -o deconvolved.tif
  nemo mesh stack.tif --t 0 --c 1 --psf 2.5 0.8 0.8 --deconvolved deconvolved.tif -o mesh.ply
  nemo peel stack.tif mesh.inner.ply --t 0 --c 1 --psf 2.5 0.8 0.8 --deconvolved deconvolved.tif \\
      -o layer.parquet --range 0 4"""


def add_arguments(parser) -> None:
    parser.add_argument("image", help="TIFF hyperstack, OME-TIFF or OME-Zarr folder (a level: FOLDER/N)")
    add_common(parser, frame=True, output_help="the deconvolved stack (.tif)")


def run(args) -> int:
    from nemo._log import step
    from nemo.cli.common import check_outputs_are_not_inputs, step_psf
    from nemo.io import read_stack
    from nemo.psf import deconvolve, is_auto, write_deconvolved

    step_psf(args)
    if args.psf is None:
        raise NemoError("--psf none: nothing to deconvolve; give the PSF: --psf SZ SY SX (Gaussian standard "
                        "deviations, µm), or --psf auto (its z blur estimated from the image, the default)")
    out = output_path(args.output, (".tif", ".tiff"))
    check_outputs_are_not_inputs(args)
    with step(f"reading {args.image} t={args.t} c={args.c}"):
        volume, info = read_stack(args.image, t=args.t, c=args.c, spacing=args.spacing)
    auto = is_auto(args.psf)
    if info.unit == "pixel" and not auto:
        warnings.warn("the image has no calibration (unit pixel): the psf is read in pixels; give --spacing "
                      "to give the psf in µm", NemoWarning, stacklevel=2)
    said = ("its z blur estimated from the image, where there is one" if auto
            else f"the PSF σ {' '.join(f'{v:g}' for v in args.psf)}")
    with step(f"deconvolving {'x'.join(map(str, volume.shape))} voxels by {said} "
              "(Richardson-Lucy, about 1.5 s per million voxels)"):
        sharp, record = deconvolve(volume, info.spacing, args.psf)
    write_deconvolved(out, sharp, record, volume, info.spacing, args.t, args.c, args.image)
    print(f"deconvolved t={args.t} c={args.c} {psf_note(record)} -> {out}")
    return 0


def psf_note(record: dict) -> str:
    """What :func:`nemo.psf.deconvolve`'s record says was done, in a few words."""
    estimated = " (estimated: psf auto)" if record.get("estimated") else ""
    if record["iterations"]:
        return (f"by σ {' '.join(f'{v:g}' for v in record['psf'])}{estimated}, "
                f"{record['iterations']} Richardson-Lucy iterations")
    if record.get("estimated") and not record["psf"]:
        return f"not deconvolved: psf auto: {(record.get('estimate') or {}).get('reason')}"
    return "nothing to deconvolve"


def deconvolved_for(args, volume, spacing):
    """The ``--deconvolved`` file of nemo mesh / peel, checked against this step's frame and PSF
    (:func:`nemo.psf.read_deconvolved`), or None when not given."""
    from nemo.psf import read_deconvolved

    if not getattr(args, "deconvolved", None):
        return None
    if args.psf is None:
        raise NemoError(f"--deconvolved {args.deconvolved} with --psf none: drop one (a deconvolved frame is used "
                        "only with the --psf it was made with)")
    return read_deconvolved(args.deconvolved, volume, spacing, args.psf, args.t, args.c)
