"""``nemo peel``: project an intensity layer of an image onto a surface mesh."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pandas as pd

from nemo.cli.common import add_common, number, output_path, positive
from nemo.errors import NemoError, NemoWarning

HELP = "project an intensity layer (a depth range along the normals) onto a mesh"
DESCRIPTION = """\
Sample the image along each vertex normal at x = v + (DMIN + shift + τ) N, τ ∈ [0, DMAX − DMIN]
(physical units; anisotropic voxels handled exactly), and reduce the samples to one intensity
per vertex. Writes a layer table (vertex, intensity); NaN where the segment leaves the image.
The mesh must be in the image's physical space: same unit, and the spacing 'nemo mesh' recorded
in the PLY must equal the image's (after --spacing); otherwise peel stops with an error.

With --shift FIELDS.parquet:COLUMN the range moves by F × that per-vertex field (F from
--shift-fraction, default 1), e.g. 0.2 × the local thickness. With --profile the full depth
profile is also written to LAYER.profile.parquet in long format (vertex, depth, intensity;
depth = DMIN + τ without the shift).

examples:
  nemo peel vesicle.tif inner.ply -o layer.parquet --range 0 5
  nemo peel vesicle.tif inner.ply -o deep.parquet --range 6 11 --reduce max --interp cubic
  nemo peel hydra.tif basal.ply -o beta.parquet --range 0 4 --inward \\
      --shift thickness.parquet:thickness --shift-fraction 0.2"""


def add_arguments(parser) -> None:
    parser.add_argument("image", help="TIFF hyperstack, OME-TIFF or OME-Zarr folder (a level: FOLDER/N)")
    parser.add_argument("mesh", help="surface mesh (PLY/OBJ) in the image's physical coordinates")
    parser.add_argument("--range", type=number, nargs=2, default=[0.0, 5.0], metavar=("DMIN", "DMAX"),
                        help="depth range along the normal, in the mesh's unit (µm; negative = against it; "
                             "default 0 5)")
    parser.add_argument("--samples", type=positive(int), metavar="N",
                        help="samples over the range (default 11; at most one per 1/20 voxel)")
    parser.add_argument("--reduce", choices=("mean", "max"),
                        help="reduction over the samples (default mean)")
    parser.add_argument("--interp", choices=("linear", "cubic"),
                        help="interpolation (default linear)")
    parser.add_argument("--inward", action="store_true", default=None,
                        help="measure depth along the inward normal instead of the outward one")
    parser.add_argument("--shift", metavar="FIELDS.parquet:COLUMN",
                        help="per-vertex field of this mesh added (× --shift-fraction) to the range, "
                             "in the mesh's unit")
    parser.add_argument("--shift-fraction", type=number, metavar="F",
                        help="fraction of the --shift field to add (default 1)")
    parser.add_argument("--profile", action="store_true",
                        help="also write the depth profile to LAYER.profile.parquet")
    add_common(parser, frame=True, output_help="layer table (.parquet)", deconvolved=True)


def _read_shift(spec: str, n_vertices: int) -> tuple[np.ndarray, np.ndarray | None]:
    """The --shift field and, from a thickness table, its ``beyond_view`` (rays that left the view)."""
    from nemo.tables import field_on_vertices, read_table

    path, sep, column = spec.rpartition(":")
    if not sep or not path or not column:
        raise NemoError(f"--shift {spec!r}: write it as FIELDS.parquet:COLUMN")
    df = read_table(path, columns=("vertex", column), n_vertices=n_vertices)
    values = field_on_vertices(df, column, n_vertices, path, exact=True)
    beyond = field_on_vertices(df, "beyond_view", n_vertices, path) == 1.0 if "beyond_view" in df else None
    return values, beyond


def _check_same_psf(mesh, psf, mesh_path, c: int) -> None:
    """Warn when the mesh was made from this channel deconvolved with another PSF than ``psf`` (a mesh
    of another channel had that channel's PSF; ``"auto"`` matches a mesh whose PSF was estimated)."""
    from nemo.psf import is_auto, recorded_psf

    params = mesh.metadata.get("nemo_params") or {}
    if "deconvolution" not in params:  # another tool's mesh: nothing to compare
        return
    made = recorded_psf(params["deconvolution"] or {})
    given = psf if psf is None or is_auto(psf) else [float(v) for v in psf]
    if made != given and params.get("c", c) == c:
        said = "none" if made is None else made if isinstance(made, str) else " ".join(f"{v!r}" for v in made)
        has = "none" if given is None else "auto (the default)" if is_auto(given) else "another"
        warnings.warn(f"the mesh {mesh_path} was made with --psf {said}, this peel has {has}: give nemo peel the "
                      "same --psf", NemoWarning, stacklevel=2)


def profile_path(layer_path: str | Path) -> Path:
    """``LAYER.parquet`` → ``LAYER.profile.parquet``."""
    p = Path(layer_path)
    return p.with_name(p.stem + ".profile" + p.suffix)


def run(args) -> int:
    from nemo import stages
    from nemo._log import step
    from nemo.cli.common import step_psf
    from nemo.cli.deconvolve import deconvolved_for
    from nemo.io import read_stack
    from nemo.mesh import load_mesh
    from nemo.peel import check_mesh_image, warn_if_mesh_off_object
    from nemo.tables import write_table

    out = output_path(args.output)
    step_psf(args)
    dmin, dmax = args.range
    if dmax < dmin:
        raise NemoError(f"--range {dmin:g} {dmax:g}: DMIN must not exceed DMAX")
    mesh = load_mesh(args.mesh)
    shift, shift_out = _read_shift(args.shift, len(mesh.vertices)) if args.shift else (None, None)
    fraction = (1.0 if args.shift_fraction is None else args.shift_fraction) if args.shift else 0.0
    layer = {"range": [dmin, dmax], "samples": args.samples, "reduce": args.reduce, "interp": args.interp,
             "inward": args.inward, "shift": fraction}
    with step(f"reading {args.image} t={args.t} c={args.c}"):
        volume, info = read_stack(args.image, t=args.t, c=args.c, spacing=args.spacing)
    check_mesh_image(mesh, info.spacing, info.unit, mesh_name=f"the mesh {args.mesh}",
                     image_name=f"the image {args.image}")
    _check_same_psf(mesh, args.psf, args.mesh, args.c)
    if mesh.metadata.get("spacing") is None:  # made elsewhere: check its scale against the image
        warn_if_mesh_off_object(mesh, volume, info.spacing, mesh_name=f"the mesh {args.mesh}")
    deconvolved = deconvolved_for(args, volume, info.spacing)
    with step(f"peeling {len(mesh.vertices)} vertices in [{dmin:g}, {dmax:g}]"):
        result = stages.peel(volume, info.spacing, mesh, layer, shift=shift, return_profile=args.profile,
                             psf=args.psf, deconvolved=deconvolved, shift_beyond_view=shift_out)
    df, params = result[:2]
    prov = dict(
        command="peel", image=str(args.image), mesh=str(args.mesh), n_vertices=len(mesh.vertices),
        t=args.t, c=args.c, spacing=list(info.spacing), unit=info.unit, shift_field=args.shift,
        parameters=params,
    )
    write_table(df, out, **prov)
    intensity = df["intensity"].to_numpy()
    n = len(intensity)
    if args.profile:
        profile, depths = result[2], result[3]
        prof = pd.DataFrame({
            "vertex": np.repeat(np.arange(n, dtype=np.int64), len(depths)),
            "depth": np.tile(depths, n),
            "intensity": profile.ravel(),
        })
        write_table(prof, profile_path(out), **prov)
    finite = intensity[np.isfinite(intensity)]
    print(f"peeled {n} vertices: intensity mean {finite.mean():.4g}, range "
          f"[{finite.min():.4g}, {finite.max():.4g}], {n - finite.size} NaN -> {out}")
    return 0
