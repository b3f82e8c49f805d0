"""The ``nemo`` command.

Each subcommand lives in its own module ``nemo/cli/<name>.py`` exposing

* ``HELP`` -- one line shown in ``nemo --help``;
* ``add_arguments(parser)`` -- its options (use :func:`nemo.cli.common.add_common` for the
  shared ``--t --c -o --spacing -v``);
* ``run(args) -> int`` -- the work, calling the library.

User errors are raised as :class:`nemo.errors.NemoError` and printed as one line
``nemo <command>: error: <message>`` with exit status 2; warnings are printed as
``nemo: warning: <message>``. Only NEMO's own warnings are shown (:class:`NemoWarning` and
warnings raised from NEMO's modules); the dependencies' (e.g. pydantic deprecations under
napari) are shown when ``NEMO_DEBUG`` is set or Python's ``-W`` / ``PYTHONWARNINGS`` asks.
"""

from __future__ import annotations

import argparse
import functools
import importlib
import os
import re
import sys
import warnings

from nemo import __version__
from nemo.errors import NemoError, NemoWarning

#: Subcommands in the order ``nemo --help`` lists them (module name = command name).
COMMANDS = (
    "info", "synth", "deconvolve", "mesh", "curvature", "thickness", "measure", "peel", "directors",
    "order", "align", "defects", "run", "track", "render", "view", "validate",
)

_EPILOG = """\
data flow: image (t, c) [-> deconvolve, with a PSF] -> mesh (PLY) -> layer (peel) -> directors -> order -> defects;
curvature/thickness/measure from meshes; align from two director tables.
Every step reads and writes files, so any step can be rerun alone.
validate: the validation protocol's steps (scores against a known truth; docs/validation.md).
Lengths are physical (the image's unit, usually µm); tables use physical x, y, z.
Run 'nemo COMMAND --help' for a command's options."""


#: Library argument names whose command-line flag is not ``--name-with-dashes``.
_FLAGS = {"n_samples": "--samples", "smooth_iter": "--smooth", "d_min": "DMIN", "d_max": "DMAX"}


#: Commands whose parameters come from the config file, not from flags of their own.
_CONFIG_COMMANDS = ("run",)


def as_flags(message: str, command: str | None = None) -> str:
    """The library names its arguments in backquotes (`pixel`); on the command line they are flags
    (``--pixel``), except for commands configured by a file (``nemo run``), where they are keys."""
    if command in _CONFIG_COMMANDS:
        return re.sub(r"`([a-z_]+)`", r"\1", str(message))
    return re.sub(r"`([a-z_]+)`", lambda m: _FLAGS.get(m.group(1), "--" + m.group(1).replace("_", "-")),
                  str(message))


def _show_warning(message, category, filename, lineno, file=None, line=None, command=None):  # noqa: ARG001
    print(f"nemo: warning: {as_flags(message, command)}", file=sys.stderr)


def _filter_warnings() -> None:
    """Warning filters for a command (call inside ``warnings.catch_warnings()``).

    NEMO's own warnings are always shown. The dependencies' warnings are hidden, unless
    ``NEMO_DEBUG`` is set (all shown once per place) or the user gave filters with ``python -W``
    or ``PYTHONWARNINGS`` (those apply as given).
    """
    if os.environ.get("NEMO_DEBUG"):
        warnings.simplefilter("default")
    elif not sys.warnoptions:
        warnings.simplefilter("ignore")
        warnings.filterwarnings("default", module=r"nemo(\.|$)")
    warnings.simplefilter("always", NemoWarning)


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The argument parser; with ``only``, just that subcommand (fast start-up: the other
    subcommand modules, and the heavy libraries they import, are not loaded)."""
    parser = argparse.ArgumentParser(
        prog="nemo",
        description="Nematic order and morphology of curved, multi-layered surfaces in 3D images.",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"nemo {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS if only is None else (only,):
        try:
            module = importlib.import_module(f"nemo.cli.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"nemo.cli.{name}":
                continue  # command not built yet in this checkout
            raise
        p = sub.add_parser(
            name, help=module.HELP, description=getattr(module, "DESCRIPTION", module.HELP),
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
        module.add_arguments(p)
        p.set_defaults(_run=module.run, _command=name, _parser=p)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``nemo`` console script."""
    from nemo.cli.common import psf_auto_option

    argv = psf_auto_option(sys.argv[1:] if argv is None else list(argv))
    command = next((a for a in argv if not a.startswith("-")), None)
    parser = build_parser(command if command in COMMANDS else None)
    args, unknown = parser.parse_known_args(argv)
    if unknown:  # said by the subcommand's parser: "nemo track: error: ..." with its usage line
        getattr(args, "_parser", parser).error(f"unrecognized arguments: {' '.join(unknown)}")
    if not getattr(args, "_run", None):
        parser.print_help()
        return 2
    from nemo import _log
    from nemo.cli.common import check_outputs_are_not_inputs

    _log.configure(getattr(args, "verbose", 0) + 1)
    try:
        check_outputs_are_not_inputs(args)
        with warnings.catch_warnings():
            _filter_warnings()
            warnings.showwarning = functools.partial(_show_warning, command=args._command)  # restored on exit
            return int(args._run(args) or 0)
    except NemoError as exc:
        print(f"nemo {args._command}: error: {as_flags(exc, args._command)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"nemo {args._command}: interrupted", file=sys.stderr)
        return 130
    except OSError as exc:  # the system refused a read or write: no bug of ours, say what and where
        where = f" {exc.filename}" if exc.filename else ""
        print(f"nemo {args._command}: error: cannot access{where} ({exc.strerror or exc}); check the path, "
              "its permissions and the free disk space", file=sys.stderr)
        return 2
    except MemoryError:
        print(f"nemo {args._command}: error: out of memory; use a machine with more memory, a coarser mesh "
              "step (mesh.step / --step), or a cropped image", file=sys.stderr)
        return 2
