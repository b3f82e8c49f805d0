"""``nemo track``: link the defects of a time-lapse into tracks (same charge only)."""

from __future__ import annotations

from nemo.cli.common import add_common, output_path, positive

HELP = "link defects frame to frame into tracks (laptrack; same-charge links only)"
DESCRIPTION = """\
Link the defects of all frames into tracks with laptrack (linear-assignment tracking):
a defect in one analysed frame is linked to a defect of the same rounded charge in the next
frame within --max-distance µm; --gap-frames N bridges up to N frames in which it was missed.
Tracking runs separately per channel 'c' and 'layer' when those columns exist.

The input holds the defects of every frame with a 't' column (and 'x', 'y', 'z',
'charge_rounded'), as the workflow's aggregation writes it. Output: one row per track
(track_id, c, layer, charge, charge_rounded, first_t, last_t, length, span, path_length,
mean_speed, mean_S); --linked also writes the input rows with their track_id.

example:
  nemo track results/demo/summary/defects_untracked.parquet -o tracks.parquet \\
      --linked defects.parquet --max-distance 15 --gap-frames 1"""


def add_arguments(parser) -> None:
    parser.add_argument("defects", help="Parquet table of the defects of all frames (column t)")
    add_common(parser, output_help="tracks table (.parquet), one row per track")
    parser.add_argument("--linked", metavar="FILE",
                        help="also write the defects with their track_id (.parquet)")
    parser.add_argument("--max-distance", type=positive(float), metavar="UM",
                        help="largest displacement between consecutive frames (µm; default: the "
                             "defects' suppression radius, column min_distance of the input)")
    parser.add_argument("--gap-frames", type=int, metavar="N",
                        help="frames a defect may be missed and still be linked (default 1; 0 = off)")
    parser.add_argument("--gap-max-distance", type=positive(float), metavar="UM",
                        help="largest displacement across a gap (default: --max-distance)")
    parser.add_argument("--frames", type=int, nargs="+", metavar="T",
                        help="all analysed time points, also those without defects (default: the t found)")


def _recorded_min_distances(defects) -> list:
    """The defects' suppression radius once per frame's layer and object (``t``, ``c``, ``layer``,
    ``object`` where present): every defect row repeats its frame's, and distinct values alone
    would weigh a rare radius as much as the usual one."""
    if "min_distance" not in defects:
        return []
    keys = [k for k in ("t", "c", "layer", "object") if k in defects]
    return defects.drop_duplicates(keys)["min_distance"].dropna().tolist()


def run(args) -> int:
    from nemo import stages
    from nemo._log import logger
    from nemo.cli.common import section_params
    from nemo.tables import read_table, write_table
    from nemo.track import link_defects, summarise_tracks

    out = output_path(args.output)
    linked_path = output_path(args.linked) if args.linked else None
    defects = read_table(args.defects, columns=("t", "x", "y", "z", "charge_rounded"))
    recorded = _recorded_min_distances(defects)
    params = stages.tracking_distance(section_params(args, "tracking"),
                                      [{"min_distance": float(v)} for v in recorded], n_defects=len(defects))
    linked = link_defects(
        defects, max_distance=params["max_distance"], gap_frames=params["gap_frames"],
        gap_max_distance=params["gap_max_distance"], frames=args.frames,
    )
    tracks = summarise_tracks(linked)
    if linked_path:
        write_table(linked, linked_path, unit="um", command="nemo track", parameters=params,
                    inputs=[str(args.defects)])
    write_table(tracks, out, unit="um", command="nemo track", parameters=params,
                inputs=[str(args.defects)])
    logger.info("%d defects linked into %d tracks", len(linked), len(tracks))
    print(f"{len(defects)} defects -> {len(tracks)} tracks")
    return 0
