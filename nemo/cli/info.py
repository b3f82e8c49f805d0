"""``nemo info``: describe a hyperstack without reading its pixels."""

from __future__ import annotations

from nemo import ome_zarr
from nemo.cli.common import add_common, print_json
from nemo.io import read_info

HELP = "axes, sizes, dtype, spacing and unit of a hyperstack"
DESCRIPTION = """\
Describe a TIFF hyperstack (ImageJ or OME) or an OME-Zarr image without reading its pixels.

example:
  nemo info vesicle.tif
  nemo info organoid.zarr       # also lists the resolution levels (read one as organoid.zarr/N)
  nemo info vesicle.tif --json   # {"axes": ..., "shape": {"T":..,"C":..,"Z":..,"Y":..,"X":..}, ...}"""


def add_arguments(parser) -> None:
    parser.add_argument("image", help="TIFF hyperstack, OME-TIFF or OME-Zarr folder (a level: FOLDER/N)")
    parser.add_argument("--json", action="store_true", help="print a JSON object")
    add_common(parser, output=False)


def run(args) -> int:
    info = read_info(args.image)
    if args.json:
        print_json(info.to_json())
        return 0
    s = info.shape
    dz, dy, dx = info.spacing
    print(f"file     {info.path}")
    print(f"axes     {info.axes} (as stored)")
    print(f"shape    T={s['T']} C={s['C']} Z={s['Z']} Y={s['Y']} X={s['X']}")
    print(f"dtype    {info.dtype}")
    print(f"spacing  dz={dz:g} dy={dy:g} dx={dx:g} {info.unit}" + ("" if info.calibrated else " (no calibration in file)"))
    if ome_zarr.is_zarr(args.image):
        for level in ome_zarr.levels(args.image):
            shape = " ".join(f"{a}={n}" for a, n in level["shape"].items())
            spacing = " ".join(f"{v:g}" for v in level["spacing"])
            print(f"level    {level['path']}: {shape}, spacing (dz dy dx) {spacing}")
    return 0
