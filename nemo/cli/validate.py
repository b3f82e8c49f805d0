"""``nemo validate``: the steps of the validation protocol (nemo.validation)."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from nemo.cli.common import positive
from nemo.errors import NemoError

HELP = "validation protocol steps: analytic shapes, scores against the truth, summary"
DESCRIPTION = """\
The steps of the validation protocol (docs/validation.md): analyse images whose answer is
known and score what NEMO finds against it. The workflow runs them for you when the config has
a `validation:` section:

  snakemake --cores 2 --configfile config/validation-ci.yaml     # the small variant, minutes

Each step also runs alone:

  shape        write an analytic solid (ellipsoid, torus, concentric shells) as a stack + truth
  score-shape  curvature and thickness of its reconstructed mesh against the exact values
  score        one analysed synthetic vesicle (nemo synth) against its ground truth
  aggregate    every score and Snakemake benchmark file into summary tables, markdown, plots

examples:
  nemo validate shape '{"kind": "ellipsoid", "axes": [30, 24, 18]}' -o ell.tif --truth ell.json
  nemo mesh ell.tif -o ell.ply --threshold 110 --keep largest --split none
  nemo validate score-shape ell.ply ell.json -o ell.score.json
  nemo synth v.tif --radius 60 --spacing 2 2 2 && nemo run v.tif -o out
  nemo validate score --truth v.tif --defects out/defects_fibres.parquet \\
      --directors out/directors_fibres.parquet --order out/order_fibres.parquet -o v.score.json
  nemo validate aggregate --scores v.score.json --shapes ell.score.json -o summary

Run 'nemo validate STEP --help' for a step's options."""

_SHAPE = """\
Write an analytic solid as a uint8 ImageJ hyperstack (ZYX) and its description (TRUTH.json:
the spec plus centre and the mid-intensity threshold at which the surface is exact). The edge
is an error function of the signed distance, so the 50 % level is the analytic surface.

SPEC (JSON): "kind": "ellipsoid" ("axes": [a, b, c] µm along x, y, z), "torus" ("major",
"minor" µm, axis z) or "shells" (the solid between the ellipsoids "inner" and "outer", [a, b, c]
each; equal axes = concentric spheres); optional "spacing" [dz, dy, dx] µm (default 1 1 1),
"blur" µm (default one lateral voxel), "margin" µm, "noise" (std, 0-255 scale), "seed",
"foreground" / "background" intensities (default 200 / 20).

example:
  nemo validate shape '{"kind": "shells", "inner": [25, 25, 25], "outer": [31, 31, 31]}' \\
      -o spheres.tif --truth spheres.json"""

_SCORE_SHAPE = """\
Score the mesh of an analytic shape (nemo mesh on the stack of 'nemo validate shape') against
the exact values: mean and Gaussian curvature fitted at each of the truth's radius_edges x the
mean edge length (error |est - exact| / RMS(exact) per vertex), and for shells the thickness
from the inner wall along its normals against the exact distance. Writes {"rows": [...]}, one
row per curvature radius.

example:
  nemo validate score-shape spheres.ply spheres.json -o spheres.score.json"""

_SCORE = """\
Score one analysed synthetic vesicle against its ground truth (nemo synth's TRUTH.json, or the
image it sits beside): defect detection, false positives, localisation and charge errors
(one-to-one matching within --match-radius), director angle errors (all, and in the ordered
region farther than --ordered-distance from every true defect), S in the ordered region and
the curvature error on the sphere. With --stage-files, the time and memory of the frame's jobs
(Snakemake benchmark files). Writes one JSON record: --case's fields plus the scores.

example:
  nemo validate score --truth v.tif --defects out/defects_fibres.parquet \\
      --directors out/directors_fibres.parquet --order out/order_fibres.parquet \\
      --curvature out/curvature_inner.parquet -o v.score.json"""

_AGGREGATE = """\
Collect the scores of 'nemo validate score' (--scores) and 'score-shape' (--shapes) and the
Snakemake benchmark files of the jobs (--stages, named .../GROUP/STAGE/JOB.tsv) into the folder
OUT: cases.parquet (one row per case), sweeps.parquet (mean per swept value), shapes.parquet,
stages.parquet (time and peak memory), validation.md (the tables) and plots/ (PNG).

example:
  nemo validate aggregate --scores cases/*/score.json --shapes shapes/*/score.json -o summary"""


def _step(sub, name: str, help: str, description: str) -> argparse.ArgumentParser:
    p = sub.add_parser(name, help=help, description=description,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv: debug)")
    return p


def add_arguments(parser) -> None:
    sub = parser.add_subparsers(dest="step", metavar="STEP", required=True)
    a = _step(sub, "shape", "write an analytic shape as a hyperstack + truth JSON", _SHAPE)
    a.add_argument("spec", metavar="SPEC", help="the shape as JSON (see above)")
    a.add_argument("-o", "--output", required=True, metavar="OUT.tif", help="output hyperstack (.tif)")
    a.add_argument("--truth", required=True, metavar="TRUTH.json", help="output description of the shape")
    a = _step(sub, "score-shape", "score curvature and thickness of a reconstructed shape", _SCORE_SHAPE)
    a.add_argument("mesh", metavar="MESH", help="the shape's mesh (PLY, from nemo mesh)")
    a.add_argument("truth", metavar="TRUTH.json", help="its description (nemo validate shape --truth)")
    a.add_argument("-o", "--output", required=True, metavar="SCORE.json", help="output scores")
    a = _step(sub, "score", "score one analysed vesicle against its truth", _SCORE)
    a.add_argument("--truth", required=True, metavar="FILE",
                   help="the ground truth (X.truth.json) or the image X.tif it was written beside")
    a.add_argument("--defects", required=True, metavar="TABLE", help="defects table (nemo defects)")
    a.add_argument("--directors", metavar="TABLE", help="raw directors table (nemo directors)")
    a.add_argument("--order", metavar="TABLE", help="averaged field (nemo order)")
    a.add_argument("--curvature", metavar="TABLE", help="curvature of the inner wall (nemo curvature)")
    a.add_argument("--stage-files", nargs="*", default=[], metavar="TSV",
                   help="Snakemake benchmark files (.tsv) of the frame's per-stage jobs (time, memory)")
    a.add_argument("--case", default="{}", metavar="JSON", help="case metadata copied into the record (JSON)")
    a.add_argument("--match-radius", type=positive(), metavar="UM",
                   help="defect matching radius in µm (default 0.15 x the vesicle radius)")
    a.add_argument("--ordered-distance", type=positive(), metavar="UM",
                   help="ordered region: farther than this from every true defect, µm (default 0.25 R)")
    a.add_argument("-o", "--output", required=True, metavar="SCORE.json", help="output record")
    a = _step(sub, "aggregate", "collect scores into summary tables and plots", _AGGREGATE)
    a.add_argument("--scores", nargs="*", default=[], metavar="JSON", help="vesicle scores (nemo validate score)")
    a.add_argument("--shapes", nargs="*", default=[], metavar="JSON",
                   help="shape scores (nemo validate score-shape)")
    a.add_argument("--stages", nargs="*", default=[], metavar="TSV", help="Snakemake benchmark files of the jobs")
    a.add_argument("-o", "--output", required=True, metavar="OUT", help="output folder")


def _json(text: str, what: str):
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise NemoError(f"{what} is not valid JSON ({exc})") from None


def _json_file(path: str | Path, what: str) -> dict:
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise NemoError(f"{what} not found: {path}") from None
    except (UnicodeDecodeError, IsADirectoryError):
        raise NemoError(f"{what} {path} is not a JSON file") from None
    obj = _json(text, f"{what} {path}")
    if not isinstance(obj, dict):
        raise NemoError(f"{what} {path} is not a JSON object")
    return obj


def _shape(args) -> None:
    from nemo import atomic
    from nemo.atomic import make_folder
    from nemo.io import write_hyperstack
    from nemo.validation import shape_volume

    spec = _json(args.spec, "the shape SPEC")
    if not isinstance(spec, dict):
        raise NemoError('the shape SPEC must be a JSON object, e.g. {"kind": "ellipsoid", "axes": [30, 24, 18]}')
    vol, truth = shape_volume(spec, rng=spec.get("seed", 0))
    for out in (args.output, args.truth):
        make_folder(Path(out).parent)
    write_hyperstack(args.output, vol, truth["spacing"], unit="um", axes="ZYX")
    atomic.write_json(args.truth, truth, indent=1)
    print(f"wrote {args.output}: {vol.shape[0]} x {vol.shape[1]} x {vol.shape[2]} voxels (Z, Y, X), "
          f"{truth['kind']}; truth {args.truth}")


def _score_shape(args) -> None:
    from nemo import atomic
    from nemo.validation import score_shape
    from nemo.validation.shapes import SHAPES

    truth = _json_file(args.truth, "shape truth")
    missing = [k for k in ("kind", "centre", "spacing") if k not in truth]
    if missing:
        raise NemoError(f"{args.truth} lacks {', '.join(missing)}: write it with 'nemo validate shape --truth'")
    if truth["kind"] not in SHAPES:
        raise NemoError(f"{args.truth} is the truth of a {truth['kind']!r}, not of an analytic shape "
                        f"({', '.join(SHAPES)}): give the --truth of 'nemo validate shape' (a vesicle's truth "
                        "goes to 'nemo validate score')")
    rows = score_shape(args.mesh, truth)
    # strict JSON: an undefined score (no noise: SNR; no fit) is null, not NaN
    rows = [{k: None if isinstance(v, float) and not math.isfinite(v) else v for k, v in row.items()} for row in rows]
    atomic.make_folder(Path(args.output).parent)
    atomic.write_json(args.output, {"rows": rows}, indent=1)


def _score(args) -> None:
    from nemo import atomic
    from nemo.synthetic import read_truth
    from nemo.tables import read_table
    from nemo.validation import score_vesicle, stage_record

    truth = read_truth(args.truth)
    case = _json(args.case, "--case")
    if not isinstance(case, dict):
        raise NemoError(f'--case must be a JSON object of the case\'s fields, e.g. {{"case": "snr-10-r1"}}; '
                        f"got {args.case!r}")
    xyz = ("x", "y", "z")
    defects = read_table(args.defects, kind="defects")
    directors = read_table(args.directors, kind="directors") if args.directors else None
    order = read_table(args.order, kind="order", columns=xyz) if args.order else None
    curvature = read_table(args.curvature, kind="curvature") if args.curvature else None
    sc = score_vesicle(truth, defects, directors, order, curvature, ordered_distance=args.ordered_distance,
                       match_radius=args.match_radius)
    sc.update(stage_record(args.stage_files, args.defects))
    noise = truth.get("noise") or {}
    psf = (truth.get("psf") or {}).get("sigma_zyx") or [truth.get("parameters", {}).get("blur", 1.0)] * 3
    sc.update(radius=truth["radius"], dz_dx=truth["spacing"][0] / truth["spacing"][2],
              noise=truth.get("parameters", {}).get("noise"), photons=noise.get("photons"),
              snr=noise.get("snr"), snr_wall=noise.get("snr_wall"), blur_z=psf[0], blur_xy=psf[2],
              open="field_of_view" in truth)
    atomic.make_folder(Path(args.output).parent)
    atomic.write_json(args.output, {**case, **sc}, indent=1)


def _aggregate(args) -> None:
    from nemo.atomic import make_folder
    from nemo.validation import aggregate

    make_folder(args.output)  # the files are checked by aggregate
    aggregate(args.scores, args.shapes, args.stages, args.output)
    print(f"wrote {args.output}/validation.md and the summary tables")


_STEPS = {"shape": _shape, "score-shape": _score_shape, "score": _score, "aggregate": _aggregate}


def run(args) -> int:
    _STEPS[args.step](args)
    return 0
