"""``nemo synth``: the paper's synthetic nematic vesicle with known defects."""

from __future__ import annotations

import argparse

from nemo.cli.common import add_common, number, positive, seed
from nemo.errors import NemoError

HELP = "generate a synthetic nematic vesicle (TZCYX hyperstack + ground-truth JSON)"
DESCRIPTION = """\
Generate the paper's synthetic vesicle (method note §8): a sphere of radius R carrying a
tangential film of fibres that follow an analytic nematic field with known defects (default
4 x +1/2 at the vertices of a regular tetrahedron), in a shell of constant background, blurred
by a Gaussian PSF (isotropic, or elongated along z as in a confocal), scaled to 0-255 (uint8),
with optional shot (--photons) and Gaussian (--noise) noise. Writes an ImageJ TZCYX hyperstack
with calibration and the ground truth OUT.truth.json (radius, centre, spacing, layer
depths/channels, defect positions in physical x, y, z per frame and layer, charges, PSF, noise
and SNR, parameters).

Defects: --preset tetrahedron (4 x +1/2), five-one (5 x +1/2 + 1 x -1/2), two-plus-one
(2 x +1), or --defects "x,y,z:charge;..." (directions from the centre; charges multiples of
1/2 that sum to 2).

SNR (recorded in the truth as noise.snr): (fibre peak - shell) / noise std at the shell level,
the noise std being sqrt(noise^2 + 255 * shell / photons) on the 0-255 scale.

examples:
  nemo synth vesicle.tif                                   # the paper's R = 200 µm, 450^3 vesicle
  nemo synth small.tif --radius 60 --spacing 2 1 1 --noise 10 --rotate-random 3
  nemo synth confocal.tif --radius 80 --spacing 2.5 1 1 --blur 2.5 1 1 --photons 70 --noise 15
  nemo synth open.tif --radius 80 --cut-top 40               # cut by the top of the stack
  nemo synth two.tif --radius 100 --second-layer-depth 9 --second-layer-rotation 90
  nemo synth movie.tif --radius 100 --frames 5 --frame-rotation 6 --channels 2 \\
      --second-layer-depth 9 --second-layer-channel 1
  nemo synth minus.tif --radius 80 --defects "0,0,1:-1/2;1,0,0:1/2;0,1,0:1/2;-1,0,0:1/2;0,-1,0:1/2;0,0,-1:1/2\""""


def _nonneg(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not value >= 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text}")
    return value


def add_arguments(parser) -> None:
    parser.add_argument("output", metavar="OUT.tif", help="output hyperstack (.tif)")
    g = parser.add_argument_group("geometry")
    g.add_argument("--radius", type=positive(), default=200.0, metavar="UM",
                   help="inner radius R of the vesicle in µm (default 200)")
    g.add_argument("--spacing", type=number, nargs=3, default=(1.0, 1.0, 1.0), metavar=("DZ", "DY", "DX"),
                   help="voxel size in µm (default 1 1 1; anisotropic allowed)")
    g.add_argument("--size", type=int, nargs="+", metavar="N",
                   help="volume size in voxels: N, or NZ NY NX (default: fits R + shell + margin)")
    g.add_argument("--shell-thickness", type=_nonneg, default=10.0, metavar="UM",
                   help="thickness of the constant-background shell outside R (default 10)")
    d = parser.add_argument_group("defects")
    x = d.add_mutually_exclusive_group()
    x.add_argument("--preset", choices=("tetrahedron", "five-one", "two-plus-one"),
                   help="named defect set (default tetrahedron: 4 x +1/2)")
    x.add_argument("--defects", metavar="SPEC",
                   help='defects as "x,y,z:charge;..." (directions from the centre, Σ charge = 2)')
    d.add_argument("--rotate-random", type=seed, metavar="SEED",
                   help="rotate the defect set by a uniformly random rotation drawn with SEED")
    f = parser.add_argument_group("fibres and image")
    f.add_argument("--fibre-spacing", type=positive(), default=5.0, metavar="UM",
                   help="mean distance between neighbouring fibres in µm (default 5)")
    f.add_argument("--fibre-length", type=positive(), metavar="UM",
                   help="fibre length in µm (default R/2: 100 for the paper's vesicle)")
    f.add_argument("--background", type=_nonneg, default=0.25, metavar="F",
                   help="shell background as a fraction of 255 (default 0.25)")
    f.add_argument("--fibre-intensity", type=_nonneg, default=0.6, metavar="F",
                   help="peak of an isolated fibre as a fraction of 255 (default 0.6)")
    f.add_argument("--blur", type=_nonneg, nargs="+", default=[1.0], metavar="UM",
                   help="Gaussian PSF sigma in µm: one value, or three SZ SY SX for a confocal-like "
                        "PSF elongated along z, e.g. 2.5 1 1 (default 1)")
    f.add_argument("--blur-z", type=_nonneg, metavar="UM",
                   help="PSF sigma along z in µm (default: as --blur); --blur 1 --blur-z 2.5 = --blur 2.5 1 1")
    f.add_argument("--photons", type=positive(), metavar="N",
                   help="shot noise: Poisson noise with N photons at the 255 level, before --noise "
                        "(variance 255 I / N at intensity I; default none)")
    f.add_argument("--noise", type=_nonneg, default=0.0, metavar="STD",
                   help="additive Gaussian noise std on the 0-255 scale (default 0)")
    f.add_argument("--cut-top", type=number, metavar="UM",
                   help="end the stack this many µm above the centre: the vesicle is cut open by the top "
                        "of the field of view (default: the whole vesicle)")
    f.add_argument("--layer-depth", type=_nonneg, default=3.0, metavar="UM",
                   help="depth of the fibre layer outside R in µm (default 3, inside a [0, 5] peel)")
    f.add_argument("--second-layer-depth", type=_nonneg, metavar="UM",
                   help="add a second fibre layer at this depth (µm)")
    f.add_argument("--second-layer-rotation", type=number, default=90.0, metavar="DEG",
                   help="director rotation of the second layer in degrees (default 90 = orthogonal)")
    f.add_argument("--second-layer-channel", type=int, default=0, metavar="C",
                   help="channel of the second layer (default 0 = same as the first)")
    t = parser.add_argument_group("time and channels")
    t.add_argument("--frames", type=positive(int), default=1, metavar="T", help="number of frames (default 1)")
    t.add_argument("--frame-rotation", type=number, default=0.0, metavar="DEG",
                   help="rotation of the defects/texture per frame in degrees (default 0)")
    t.add_argument("--frame-axis", type=number, nargs=3, default=(0.0, 1.0, 0.0), metavar=("X", "Y", "Z"),
                   help="axis of the per-frame rotation (default 0 1 0)")
    t.add_argument("--channels", type=positive(int), metavar="C",
                   help="number of channels (default: as many as the layers use)")
    parser.add_argument("--seed", type=seed, default=0, help="random seed for fibres and noise (default 0)")
    add_common(parser, output=False)


def run(args) -> int:
    from nemo.synthetic import parse_defects, truth_path, write_vesicle

    if not args.output.lower().endswith((".tif", ".tiff")):
        raise NemoError(f"output {args.output} should end in .tif")
    if args.size is not None and len(args.size) not in (1, 3):
        raise NemoError("--size takes one number N or three numbers NZ NY NX")
    if len(args.blur) not in (1, 3):
        raise NemoError("--blur takes one sigma or three (SZ SY SX) in µm")
    blur = args.blur[0] if len(args.blur) == 1 else tuple(args.blur)
    if args.blur_z is not None:
        sz, sy, sx = (blur,) * 3 if len(args.blur) == 1 else blur
        blur = (args.blur_z, sy, sx)
    kw = {}
    if args.defects:
        kw["defects"], kw["charges"] = parse_defects(args.defects)
    elif args.preset:
        kw["defects"] = args.preset
    truth = write_vesicle(
        args.output,
        radius=args.radius, spacing=tuple(args.spacing),
        size=None if args.size is None else (args.size[0] if len(args.size) == 1 else tuple(args.size)),
        shell_thickness=args.shell_thickness, rotate=args.rotate_random,
        fibre_spacing=args.fibre_spacing, fibre_length=args.fibre_length,
        background=args.background, fibre_intensity=args.fibre_intensity, blur=blur,
        noise=args.noise, photons=args.photons, cut_top=args.cut_top, layer_depth=args.layer_depth,
        second_layer_depth=args.second_layer_depth, second_layer_rotation=args.second_layer_rotation,
        second_layer_channel=args.second_layer_channel, frames=args.frames,
        frame_rotation=args.frame_rotation, frame_axis=tuple(args.frame_axis),
        channels=args.channels, seed=args.seed, **kw,
    )
    s = truth["shape"]
    print(f"wrote {args.output}: T={s['T']} Z={s['Z']} C={s['C']} Y={s['Y']} X={s['X']} uint8, "
          f"spacing {truth['spacing']} µm, R = {truth['radius']:g} µm, centre "
          f"({', '.join(f'{v:g}' for v in truth['centre'])})")
    n_def = sum(1 for r in truth["defects"] if r["t"] == 0 and r["layer"] == 0)
    nz = truth["noise"]
    if nz["snr"] is not None:
        # shot noise alone leaves the empty inside noise-free: the shell's SNR there is infinite (None)
        wall = "inf" if nz["snr_wall"] is None else f"{nz['snr_wall']:.2f}"
        print(f"SNR {nz['snr']:.2f} (fibres on the shell), {wall} (shell on the inside); "
              f"noise std {nz['noise_std_shell']:.2f} at the shell level")
    if "field_of_view" in truth:
        vis = sum(1 for r in truth["defects"] if r["t"] == 0 and r["layer"] == 0 and r["in_view"])
        print(f"open: the stack ends at z = {truth['field_of_view']['z_max']:g} µm; {vis} of {n_def} "
              "defects in view")
    print(f"ground truth: {truth_path(args.output)} "
          f"({len(truth['layers'])} layer(s), {n_def} defects per layer and frame)")
    return 0
