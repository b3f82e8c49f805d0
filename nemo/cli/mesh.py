"""``nemo mesh``: reconstruct a surface mesh from one (t, c) stack of a hyperstack."""

from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path

import numpy as np

from nemo import atomic
from nemo.cli.common import (
    add_common,
    add_mask_arguments,
    input_files,
    mask_options,
    non_negative,
    number,
    output_path,
    positive,
    refuse_to_overwrite,
)
from nemo.errors import NemoError, NemoWarning

HELP = "reconstruct a surface mesh (PLY) from an image: blur, threshold, marching cubes"
DESCRIPTION = """\
Reconstruct the surface of the bright object in one (t, c) stack as a triangle mesh with
vertices in physical x, y, z (µm) and outward normals (method note §2): Gaussian blur
(--sigma in µm), threshold (Yen by default; the surface sits half-way between the object and
background intensities) or a binary --mask, marching cubes every --step voxels, vertices
snapped onto the cubic-spline iso-surface (no terraces between coarse z planes), Taubin
smoothing, largest connected component. An object cut by the edge of the image gives an open
surface whose rim lies on the border (--border open, the default); --border closed keeps the
flat cap that closes it along the border planes.

A hollow object (e.g. a vesicle's fibre shell) has two walls: its inner wall is a separate
surface facing the centre. MESH.inner.ply and MESH.outer.ply are written next to MESH.ply (the
whole); both have normals pointing away from the centre, so the inner wall is the cavity's
surface with outward normals and peeling outward from it samples the shell. --split auto (the
default) splits an object with two walls by its centre, and face by face one surface whose two
sides face towards and away from its centre when it is a thin sheet round a cavity (a shell
torn where its wall is thinner than the blur, a cup); an object with one wall (a droplet, a filled cell, a
torus) is not split: its inner and outer files are the whole surface and it has no thickness
(the log says which it found). --split centre / axis always split, face by face (also a thick
sheet whose two sides are one connected surface, which auto counts as one wall and warns
about); --split none writes MESH.ply only. --fit-sphere fits a sphere to every written
mesh and stores it in MESH.sphere.json.

examples:
  nemo mesh droplet.tif -o droplet.ply
  nemo mesh vesicle.tif -o mesh.ply --split centre --fit-sphere
  nemo mesh embryo.tif --t 3 --c 1 -o embryo.ply --sigma 2 --threshold otsu --step 1
  nemo mesh stack.tif --mask mask.tif -o mesh.ply --keep all
  nemo mesh organoid.zarr --mask cellpose_labels.tif --mask-labels 3 -o organoid.ply
  nemo mesh embryo.zarr/1 --mask probabilities.tif --mask-threshold 0.6 -o embryo.ply   # level 1
  nemo mesh embryo.tif --from-mesh blender_surface.obj --mesh-unit um -o embryo.ply"""


def _threshold(text: str):
    from nemo.surface import parse_threshold  # one parser for the CLI and the library

    try:
        return parse_threshold(text)
    except NemoError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _nonneg_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text}")
    return value


def add_arguments(parser) -> None:
    parser.add_argument("image", help="TIFF hyperstack, OME-TIFF or OME-Zarr folder")
    add_common(parser, frame=True, output_help="output mesh (.ply or .obj)", deconvolved=True)
    parser.add_argument("--sigma", type=non_negative, default=None, metavar="UM",
                        help="Gaussian blur sigma in the image unit (default: noise-aware, at least half the "
                             "sampling distance --step × (dx + dy)/4, enough for a blurred SNR of 20; 0 = none)")
    parser.add_argument("--refine", action=argparse.BooleanOptionalAction, default=None,
                        help="move the vertices to the sub-voxel edge along their normals (default: off; "
                             "a --mask has no intensity edge: ignored there, with a warning)")
    parser.add_argument("--refine-sigma", type=non_negative, default=None, metavar="UM",
                        help="blur of the image the refinement reads (default: as much as the noise needs)")
    parser.add_argument("--refine-to", choices=("level", "steepest"), default=None,
                        help="edge the refinement moves to: the iso-level crossing (default) or the steepest "
                             "point of the intensity profile between background and plateau (thin, noisy or "
                             "z-blurred walls without bright texture next to the edge; needs the half level: "
                             "with --edge threshold or no background it refines to the level, with a warning)")
    parser.add_argument("--threshold", type=_threshold, default=None, metavar="yen|otsu|VALUE",
                        help="automatic threshold or an intensity iso-level (default yen)")
    parser.add_argument("--edge", choices=("half", "threshold", "profile"), default=None,
                        help="with yen/otsu: surface half-way between object and background intensity "
                             "(default, the true edge of a blurred object; checked against the walls' fitted "
                             "profiles, and moved to their level when plain walls read a small offset, part of the "
                             "way near the limits: noise lowers the histogram's plateau), at the threshold itself, or "
                             "'profile': at the half level of blurred boxes fitted to the walls' intensity "
                             "along the normals (noisy or z-blurred walls)")
    add_mask_arguments(parser)
    parser.add_argument("--from-mesh", metavar="SURFACE",
                        help="use this surface (PLY, OBJ or STL made in MeshLab, Blender, ilastik ...) instead "
                             "of meshing the image: it is checked against the image (unit, extent, manifold) "
                             "and split and written like a reconstructed one")
    parser.add_argument("--mesh-unit", metavar="UNIT",
                        help="unit of the --from-mesh coordinates: um, nm, mm ... or pixel (voxel indices x = "
                             "column, y = row, z = plane); needed unless the file names it (NEMO's PLY)")
    parser.add_argument("--border", choices=("open", "closed"), default=None,
                        help="an object cut by the edge of the image: open = drop the flat cap along the "
                             "border and keep an open surface (default); closed = keep the capped surface")
    parser.add_argument("--step", type=positive(int), default=None, metavar="N",
                        help="marching-cubes step in voxels (default 1; 2 for stacks above 64 M voxels)")
    parser.add_argument("--smooth", type=_nonneg_int, default=None, metavar="ITER",
                        help="Taubin smoothing iterations (default 10; 0 = none)")
    parser.add_argument("--keep", choices=("largest", "all"), default=None,
                        help="several objects in the image: analyse the largest (default) or all, each labelled "
                             "(vertex field 'object', 0 = the largest) and split about its own centre")
    parser.add_argument("--split", choices=("auto", "centre", "center", "axis", "none"), default=None,
                        help="also write MESH.inner.ply and MESH.outer.ply, split by the sign of n·(x - centre) "
                             "or n·axis; auto (default): by the centre when the object has two walls, else both "
                             "are the whole surface; none = MESH.ply only")
    parser.add_argument("--axis", type=number, nargs=3, metavar=("X", "Y", "Z"),
                        help="reference axis for --split axis")
    parser.add_argument("--centre", type=number, nargs=3, metavar=("X", "Y", "Z"),
                        help="reference point (µm) for --split centre or auto (default: the surface centroid)")
    parser.add_argument("--fit-sphere", action="store_true", default=None,
                        help="fit a sphere to each mesh; print it and write MESH.sphere.json")


def _sibling(path: Path, tag: str) -> Path:
    return path.with_name(f"{path.stem}.{tag}{path.suffix}")


def _check_side_outputs(paths: dict, inputs: list[str]) -> None:
    """Refuse to write a wall over an input, and warn about walls of an earlier run that this
    one does not replace."""
    for path in paths.values():
        refuse_to_overwrite(path, inputs, "-o, a wall")
    out = paths["whole"]
    stale = [str(_sibling(out, tag)) for tag in ("inner", "outer") if tag not in paths and _sibling(out, tag).exists()]
    if stale:
        warnings.warn(f"{' and '.join(stale)}: left from an earlier run, not walls of this (unsplit) mesh; "
                      "delete them", NemoWarning, stacklevel=2)


def _describe(name: str, mesh) -> str:
    return f"{name}: {len(mesh.vertices)} vertices, {len(mesh.faces)} faces, area {mesh.area:.6g} {mesh.units}²"


def run(args) -> int:
    from nemo import stages
    from nemo._log import logger
    from nemo.cli.common import section_params, step_psf
    from nemo.cli.deconvolve import deconvolved_for
    from nemo.io import read_mask, read_stack
    from nemo.mesh import save_mesh
    from nemo.surface import fit_sphere

    start = time.perf_counter()
    out = output_path(args.output, (".ply", ".obj"))
    step_psf(args)
    if args.split == "center":
        args.split = "centre"
    volume, info = read_stack(args.image, args.t, args.c, spacing=args.spacing)
    logger.info("read %s t=%d c=%d: %s %s, spacing %s %s", args.image, args.t, args.c,
                "x".join(map(str, volume.shape)), volume.dtype, tuple(info.spacing), info.unit)
    mask_options(args)  # checks the selection flags
    mask, mask_regions = read_mask(args.mask, args.t, args.c, volume.shape, labels=args.mask_labels,
                                   threshold=args.mask_threshold, channel=args.mask_channel,
                                   apart=stages.mask_label_gap(volume.shape, info.spacing, section_params(args, "mesh")),
                                   with_regions=True) if args.mask else (None, None)
    if args.from_mesh:
        if mask is not None or args.deconvolved:
            raise NemoError(f"--from-mesh replaces the meshing of the image: drop "
                            f"{'--mask' if mask is not None else '--deconvolved'}")
        meshes, params = stages.import_mesh(args.from_mesh, volume, info.spacing, section_params(args, "mesh"),
                                            unit=info.unit, mesh_unit=args.mesh_unit, centre=args.centre)
    else:
        if args.mesh_unit:
            raise NemoError("--mesh-unit is the unit of a --from-mesh surface: give the surface too")
        deconvolved = None if mask is not None else deconvolved_for(args, volume, info.spacing)  # a mask: unused
        meshes, params = stages.mesh(volume, info.spacing, section_params(args, "mesh"), mask=mask,
                                     unit=info.unit, centre=args.centre, psf=args.psf, deconvolved=deconvolved,
                                     mask_regions=mask_regions)
    del volume, mask
    params.update(t=args.t, c=args.c)  # the frame meshed (nemo peel compares its PSF on the same channel)
    paths = {name: out if name == "whole" else _sibling(out, name) for name in meshes}
    _check_side_outputs(paths, input_files(args))
    spheres = {}
    stages.stamp_walls(meshes, params)  # again, with the frame's t and c
    for name, mesh in meshes.items():
        path = paths[name]
        save_mesh(mesh, path)
        line = _describe(name, mesh) + f" -> {path}"
        if params["fit_sphere"]:
            centre, radius = fit_sphere(mesh)
            radii = np.linalg.norm(np.asarray(mesh.vertices) - centre, axis=1)
            spheres[name] = {"file": str(path), "centre": [float(v) for v in centre], "radius": radius,
                             "rms_residual": float(np.sqrt(np.mean((radii - radius) ** 2))), "unit": mesh.units}
            line += (f"\n  sphere: centre ({centre[0]:.4g}, {centre[1]:.4g}, {centre[2]:.4g}) "
                     f"radius {radius:.5g} {mesh.units} (rms residual {spheres[name]['rms_residual']:.3g})")
        print(line)
    if params["fit_sphere"]:
        sidecar = out.with_name(f"{out.stem}.sphere.json")
        atomic.write_json(sidecar, spheres)
        print(f"sphere fit -> {sidecar}")
    if args.from_mesh:
        how = f"from {args.from_mesh} ({params['mesh_unit']}, extent ratio {params['extent_ratio'] or float('nan'):.3g})"
    else:
        how = f"step {params['step']} voxels, sigma {params['sigma']:.4g}, iso-level {params['level']:.4g}"
    print(f"{how}; done in {time.perf_counter() - start:.2f} s")
    return 0

