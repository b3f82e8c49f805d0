"""``nemo view``: open NEMO results in napari (extra ``nemo-nematics[napari]``)."""

from __future__ import annotations

from nemo.cli.common import number, positive

HELP = "open results in napari: image, surfaces coloured by a field, directors, defects"
DESCRIPTION = """\
Open a NEMO results folder in napari: the (Z, Y, X) stack at physical scale, each surface
coloured by a field chosen in the "NEMO field" panel (intensity of a layer, S, H, K,
thickness, alignment c), raw and averaged directors as vectors, defects as points coloured by
charge with the charge as text, and a time slider when several time points exist.
RESULTS may be a frame folder, a dataset folder (results/DATASET) or the results root.
Needs napari: pip install 'nemo-nematics[napari]'.

examples:
  nemo view results/demo
  nemo view results --dataset demo --c 0 --layer a
  nemo view results/demo/t0/c0 --image data/vesicle.tif
  nemo view results/demo --screenshot view.png     # save a screenshot and exit"""


def add_arguments(parser) -> None:
    parser.add_argument("results", help="results folder (frame, dataset or root)")
    parser.add_argument("--dataset", metavar="D", help="dataset in a results root (default the first)")
    parser.add_argument("--t", type=int, metavar="T", help="only this time point (default all, with a slider)")
    parser.add_argument("--c", type=int, metavar="C", help="channel (default the first with results)")
    parser.add_argument("--layer", metavar="L", help="nematic layer to show (default all)")
    parser.add_argument("--image", metavar="TIFF", help="the hyperstack, if not found automatically")
    parser.add_argument("--spacing", type=number, nargs=3, metavar=("DZ", "DY", "DX"),
                        help="voxel size in µm, overriding the image calibration")
    parser.add_argument("--max-vectors", type=positive(int), default=2000, metavar="N",
                        help="about N director glyphs per layer and frame (default 2000)")
    parser.add_argument("--screenshot", metavar="PNG",
                        help="save a screenshot of the canvas and exit (needs a display, e.g. xvfb-run)")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output")


def run(args) -> int:
    from nemo.errors import NemoError

    try:
        import napari  # noqa: F401
    except ImportError:
        raise NemoError("napari is not installed: pip install 'nemo-nematics[napari]' "
                        "(or pip install 'napari[pyqt6]')") from None
    import os
    from pathlib import Path

    from nemo.napari.layers import open_viewer

    if not Path(args.results).exists():
        raise NemoError(f"results not found: {args.results}")
    if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise NemoError("no display to open napari on: run it on a desktop, or headless as "
                        "'xvfb-run nemo view RESULTS --screenshot out.png'")

    kwargs = dict(dataset=args.dataset, t=args.t, c=args.c, layer=args.layer, image=args.image,
                  spacing=args.spacing, max_vectors=args.max_vectors)
    viewer = open_viewer(args.results, show=True, **kwargs)
    if args.screenshot:
        from nemo.atomic import atomic_path

        with atomic_path(args.screenshot, keep_suffix=True) as tmp:
            viewer.screenshot(str(tmp), canvas_only=True)
        viewer.close()
        print(args.screenshot)
        return 0
    import napari

    napari.run()
    return 0
