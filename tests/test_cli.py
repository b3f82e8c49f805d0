"""Every ``nemo`` command over a corpus of corrupt and hostile inputs (tests/hostile.py).

The contract (nemo/cli/__init__.py): a command either succeeds (exit 0, and its outputs read
back with nemo.tables.read_table / nemo.mesh.load_mesh / nemo.io.read_info) or stops with exit
status 2 and one short paragraph on stderr starting ``nemo COMMAND: error:``. Never a traceback
or another uncaught exception, never exit 1, and no byte of any input file changes.

Each case names the command and the corpus items it uses (``peel:img.nan+mesh.inner``), so a
failure says which input broke which command. ``expect`` is ``ok`` (must succeed: valid
inputs), ``error`` (must be refused: broken inputs, outputs that would replace inputs), ``warn``
(refused, or done with a ``nemo: warning:`` saying what was left out: ``nemo render`` shows what
it can) or ``any`` (either is fine as long as the contract holds).

The last part runs the step commands with option values drawn by Hypothesis (negative, zero,
NaN, infinite, huge, strings) in forked children with a time and memory limit.
"""

from __future__ import annotations

import faulthandler
import json
import os
import re
import shutil
import subprocess
import sys
import traceback
import warnings
from dataclasses import dataclass
from pathlib import Path

import hostile
import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from nemo.cli import main as nemo_main
from nemo.errors import NemoWarning

ROOT = Path(__file__).resolve().parents[1]
NEMO = Path(sys.executable).with_name("nemo")

#: An in-process command running longer than this is a hang: dump the stacks and stop.
HANG_S = 240


# ============================================================================ corpus fixture

@pytest.fixture(scope="session")
def corpus(tmp_path_factory):
    """The hostile corpus (built once), its pristine copy and the baseline hashes."""
    root = tmp_path_factory.mktemp("corpus")
    c = hostile.build_corpus(root / "c")
    pristine = root / "pristine"
    shutil.copytree(c.root, pristine, symlinks=True)
    c.pristine = pristine
    c.baseline = c.snapshot()
    return c


# ============================================================================ the contract

def error_paragraph(command: str, err: str) -> str:
    """The error message of a refused command, checked: one short paragraph starting
    ``nemo COMMAND: error:`` (argparse's usage block and ``nemo:`` progress/warning lines aside).
    Returns it; raises AssertionError saying what is wrong."""
    body, in_usage = [], False
    for line in err.splitlines():
        if line.startswith("usage: "):
            in_usage = True
            continue
        if in_usage and line.startswith(" "):
            continue
        in_usage = False
        if line.startswith("nemo: ") and not line.startswith("nemo: error:"):
            continue  # progress and warnings
        body.append(line)
    while body and not body[0].strip():
        body.pop(0)
    while body and not body[-1].strip():
        body.pop()
    assert body, f"exit 2 without an error message; stderr:\n{err}"
    assert body[0].startswith(f"nemo {command}: error: "), f"the message does not start 'nemo {command}: " \
                                                            f"error:':\n{err}"
    assert all(line.strip() for line in body), f"more than one paragraph on stderr:\n{err}"
    text = "\n".join(body)
    assert len(body) <= 12 and len(text) <= 1500, f"not a short paragraph ({len(body)} lines, {len(text)} " \
                                                   f"characters):\n{err}"
    return text


def check_output(kind: str, path: Path, stdout: str = "") -> None:
    """An output of a successful command reads back."""
    from nemo.io import read_info, read_stack
    from nemo.mesh import load_mesh
    from nemo.tables import read_table

    if kind == "stdout-json":
        json.loads(stdout)
        return
    if kind == "stdout-yaml":
        import yaml

        assert isinstance(yaml.safe_load(stdout), dict)
        return
    assert path.exists(), f"output {path} was not written"
    if kind == "mesh":
        load_mesh(path)
    elif kind.startswith("table"):
        read_table(path, kind=kind.partition(":")[2] or None)
    elif kind == "tif":
        info = read_info(path)
        read_stack(path, t=0, c=0)
        assert info.shape["Z"] >= 1
    elif kind == "json":
        json.loads(path.read_text())
    elif kind == "deconvolved":
        import tifffile

        with tifffile.TiffFile(path) as tif:
            assert json.loads(tif.pages[0].description)["format"] == "nemo-deconvolved/1"
    elif kind == "run":
        assert path.is_dir()
        json.loads((path / "summary.json").read_text())
        assert list(path.glob("mesh*.ply")), f"{path} holds no mesh"
        for p in path.rglob("*.parquet"):
            read_table(p)
        for p in path.rglob("*.ply"):
            load_mesh(p)
    elif kind == "figs":
        assert path.is_dir()
        manifest = json.loads((path / "figures.json").read_text())
        assert manifest, "figures.json lists no figure"
        for name in manifest:
            png = path / name
            assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", f"{png} is not a PNG"
    else:
        raise ValueError(kind)


@dataclass
class Case:
    """One command line over corpus items.

    ``argv`` holds ``{group.item}`` (a corpus path), ``{out}`` (the test's output folder) and
    ``{dot:group.item}`` (the same path spelt .../folder/./name).
    """

    id: str
    argv: tuple
    expect: str = "any"  # ok | error | any | warn (exit 2, or exit 0 with a 'nemo: warning:' line)
    outputs: tuple = ()  # (template, kind, required)
    check: object = None  # callable(corpus, out_dir, case_id) run after exit 0
    warns: tuple = ()  # with expect="warn": file names a 'nemo: warning:' line must name on exit 0


_FIELD = re.compile(r"\{(dot:)?([a-z_]+(?:\.[a-z_]+)?)\}")


def fill(template: str, corpus, out: Path) -> str:
    def sub(m):
        key = m.group(2)
        p = Path(out) if key == "out" else corpus[key]
        return f"{p.parent}{os.sep}.{os.sep}{p.name}" if m.group(1) else str(p)

    return _FIELD.sub(sub, template)


def invoke(argv: list[str], capsys, case_id: str) -> tuple[int, str, str]:
    """``nemo ARGV`` in-process: (exit code, stdout, stderr); an uncaught exception fails the
    test naming the case, the exception and where it was raised."""
    faulthandler.dump_traceback_later(HANG_S, exit=True, file=sys.__stderr__)
    try:
        code = nemo_main(argv)
    except SystemExit as exc:  # argparse refused the command line
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    except KeyboardInterrupt:
        raise
    except BaseException as exc:  # noqa: BLE001 - the point of the test
        out, err = capsys.readouterr()
        tb = "".join(traceback.format_exception(exc)[-8:])
        pytest.fail(f"[{case_id}] uncaught {type(exc).__name__} at {hostile.where(exc)}: {exc}\n"
                    f"argv: {argv}\nstderr:\n{err[-1500:]}\n{tb}", pytrace=False)
    finally:
        faulthandler.cancel_dump_traceback_later()
    out, err = capsys.readouterr()
    return code, out, err


def corpus_intact(corpus, case_id: str, *extra_dirs: Path) -> None:
    """No corpus file changed, vanished or appeared; no file name reached a shell."""
    now = corpus.snapshot()
    changed = sorted(k for k in corpus.baseline if now.get(k) != corpus.baseline[k])
    added = sorted(set(now) - set(corpus.baseline))
    pwned = [str(d / n) for d in (corpus.root, Path.cwd(), *extra_dirs) for n in hostile.PWNED if (d / n).exists()]
    if changed or added:
        hostile.restore(corpus.root, corpus.pristine)  # the next cases get the corpus back
    assert not pwned, f"[{case_id}] a file name was run by a shell: {pwned}"
    assert not changed, f"[{case_id}] input files were changed or removed: {changed}"
    assert not added, f"[{case_id}] files were written into the input folders: {added}"


def run_case(case: Case, corpus, tmp_path: Path, capsys, monkeypatch) -> tuple[int, str, str]:
    monkeypatch.chdir(tmp_path)  # a shell that ran `touch pwned` would leave it here
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    argv = [fill(str(a), corpus, out_dir) for a in case.argv]
    command = argv[0]
    code, out, err = invoke(argv, capsys, case.id)
    try:
        assert code in (0, 2), f"[{case.id}] exit {code} (only 0 or 2 are allowed)\nstderr:\n{err[-2000:]}"
        assert "Traceback" not in err and "Traceback" not in out, f"[{case.id}] traceback printed:\n{err[-2000:]}"
        if case.expect == "ok":
            assert code == 0, f"[{case.id}] a valid command failed (exit {code}):\n{err[-1500:]}"
        elif case.expect == "warn" and code == 0:
            warned = [line for line in err.splitlines() if line.startswith("nemo: warning:")]
            silent = [name for name in case.warns if not any(name in line for line in warned)]
            assert not silent, f"[{case.id}] {', '.join(silent)} used or left out without a warning (exit 0); " \
                               f"stderr:\n{err[-800:]}"
        elif case.expect == "error":
            assert code == 2, f"[{case.id}] a broken input was accepted (exit 0); stdout:\n{out[-800:]}\n" \
                              f"stderr:\n{err[-800:]}"
        if code == 2:
            try:
                error_paragraph(command, err)
            except AssertionError as exc:
                raise AssertionError(f"[{case.id}] {exc}") from None
        else:
            for template, kind, required in case.outputs:
                path = Path(fill(template, corpus, out_dir))
                if not required and not path.exists():
                    continue
                try:
                    check_output(kind, path, out)
                except Exception as exc:  # noqa: BLE001
                    raise AssertionError(f"[{case.id}] exit 0 but the output {path.name} ({kind}) does not read "
                                         f"back: {type(exc).__name__}: {exc}") from None
            if case.check is not None:
                case.check(corpus, out_dir, case.id)
    finally:
        corpus_intact(corpus, case.id, tmp_path)
    return code, out, err


# ============================================================================ the cases

CASES: list[Case] = []


def case(id, *argv, expect="any", outputs=(), check=None, warns=()):
    CASES.append(Case(id, tuple(argv), expect, tuple(outputs), check, tuple(warns)))


def _out(template, kind, required=True):
    return (template, kind, required)


BROKEN_IMAGES = ("trunc_page", "trunc_mid", "text", "flat", "png", "empty", "folder", "missing")
#: Images whose pixels are read: what a command must do with them.
PIXELS = {"valid": "ok", "uncal": "ok", "trunc_ifd": "any", "nan": "any", "huge": "any", "two": "any",
          "zero": "error", **{k: "error" for k in BROKEN_IMAGES}}
BROKEN_MESHES = ("bowtie", "dupface", "cut", "garbage", "points", "missing")

# ---------------------------------------------------------------------------- info
for name, expect in PIXELS.items():
    header_only = "ok" if name in ("nan", "huge", "two", "zero") else expect  # info reads no pixels
    case(f"info:img.{name}", "info", f"{{img.{name}}}", expect=header_only)
case("info:img.valid --json", "info", "{img.valid}", "--json", expect="ok", outputs=[_out("", "stdout-json")])
for key in hostile.ODD_NAMES:
    if key != "dash":
        case(f"info:odd.{key}", "info", f"{{odd.{key}}}", expect="ok")
case("info:odd.dash (as an option)", "info", "-dash.tif")
case("info:odd.dash (after --)", "info", "--", "{odd.dash}", expect="ok")
case("info:odd.dash (./-dash.tif)", "info", "{dot:odd.dash}", expect="ok")

# ---------------------------------------------------------------------------- synth
SMALL = hostile.SYNTH_ARGS
SYNTH_OUT = [_out("{out}/s.tif", "tif"), _out("{out}/s.truth.json", "json")]
case("synth:small", "synth", "{out}/s.tif", *SMALL, expect="ok", outputs=SYNTH_OUT)
case("synth:out with spaces+unicode+$()", "synth", "{out}/my vesicle ✓ $(touch pwned);x.tif", *SMALL, expect="ok",
     outputs=[_out("{out}/my vesicle ✓ $(touch pwned);x.tif", "tif")])
for label, opts in {
    "--seed -1": ["--seed", "-1"], "--radius 0": ["--radius", "0"], "--radius -5": ["--radius", "-5"],
    "--radius nan": ["--radius", "nan"], "--radius inf": ["--radius", "inf"],
    "--radius 1e308": ["--radius", "1e308"], "--size 4": ["--size", "4"], "--size 0": ["--size", "0"],
    "--size 100000": ["--size", "100000"], "--spacing 0 1 1": ["--spacing", "0", "1", "1"],
    "--spacing nan 1 1": ["--spacing", "nan", "1", "1"], "--frames 0": ["--frames", "0"],
    "--defects garbage": ["--defects", "garbage"], "--defects sum!=2": ["--defects", "0,0,1:1/2"],
    "--defects 0,0,0:2": ["--defects", "0,0,0:2"], "--fibre-spacing 0": ["--fibre-spacing", "0"],
    "--blur nan": ["--blur", "nan"], "--channels 0": ["--channels", "0"],
}.items():
    case(f"synth:{label}", "synth", "{out}/s.tif", *SMALL, *opts, expect="error")
for label, opts in {"--noise -1": ["--noise", "-1"], "--blur 1e308": ["--blur", "1e308"],
                    "--fibre-spacing 1e-9": ["--fibre-spacing", "1e-9"], "--frames 2": ["--frames", "2"],
                    "--background 2": ["--background", "2"], "--fibre-intensity -1": ["--fibre-intensity", "-1"],
                    # shot noise alone: the shell's SNR on the empty inside is infinite (its print crashed)
                    "--photons 70 (no Gaussian noise)": ["--photons", "70"]}.items():
    case(f"synth:{label}", "synth", "{out}/s.tif", *SMALL, *opts, outputs=SYNTH_OUT)
case("synth:out under a file", "synth", "{block}/s.tif", *SMALL, expect="error")
case("synth:out is a folder", "synth", "{out}", *SMALL, expect="error")
case("synth:out .png", "synth", "{out}/s.png", *SMALL, expect="error")

# ---------------------------------------------------------------------------- mesh
MESH_OUT = [_out("{out}/m.ply", "mesh"), _out("{out}/m.inner.ply", "mesh", False),
            _out("{out}/m.outer.ply", "mesh", False)]
for name, expect in PIXELS.items():
    case(f"mesh:img.{name}", "mesh", f"{{img.{name}}}", "-o", "{out}/m.ply", expect=expect, outputs=MESH_OUT)
case("mesh:img.valid --fit-sphere --split none", "mesh", "{img.valid}", "-o", "{out}/m.ply", "--fit-sphere",
     "--split", "none", expect="ok", outputs=[_out("{out}/m.ply", "mesh"), _out("{out}/m.sphere.json", "json")])
for name in ("text", "flat", "zero", "png", "empty", "trunc_mid"):
    case(f"mesh:--mask img.{name}", "mesh", "{img.valid}", "--mask", f"{{img.{name}}}", "-o", "{out}/m.ply",
         expect="error")
case("mesh:--mask img.valid", "mesh", "{img.valid}", "--mask", "{img.valid}", "-o", "{out}/m.ply", outputs=MESH_OUT)
# ---------------------------------------------------------------------------- deconvolve (and --deconvolved)
for name, expect in PIXELS.items():
    case(f"deconvolve:img.{name}", "deconvolve", f"{{img.{name}}}", "--psf", "2", "1", "1", "-o", "{out}/d.tif",
         expect="ok" if name == "zero" else expect,  # a blank frame deconvolves (its mesh is refused)
         outputs=[_out("{out}/d.tif", "deconvolved")])
case("deconvolve:no --psf (auto)", "deconvolve", "{img.valid}", "-o", "{out}/d.tif", expect="ok",
     outputs=[_out("{out}/d.tif", "deconvolved")])
case("deconvolve:--psf none", "deconvolve", "{img.valid}", "--psf", "none", "-o", "{out}/d.tif", expect="error")
case("deconvolve:out .parquet", "deconvolve", "{img.valid}", "--psf", "2", "1", "1", "-o", "{out}/d.parquet",
     expect="error")
case("deconvolve:out = the input image", "deconvolve", "{img.valid}", "--psf", "2", "1", "1", "-o", "{img.valid}",
     expect="error")
case("deconvolve:--t 5", "deconvolve", "{img.valid}", "--psf", "2", "1", "1", "-o", "{out}/d.tif", "--t", "5",
     expect="error")
for label, opts in {"img.valid (not ours)": ["--deconvolved", "{img.valid}", "--psf", "2", "1", "1"],
                    "tab.layer": ["--deconvolved", "{tab.layer}", "--psf", "2", "1", "1"],
                    "missing": ["--deconvolved", "{tab.missing}", "--psf", "2", "1", "1"],
                    "no --psf": ["--deconvolved", "{img.valid}"],
                    "--psf none": ["--deconvolved", "{img.valid}", "--psf", "none"]}.items():
    case(f"mesh:--deconvolved {label}", "mesh", "{img.valid}", "-o", "{out}/m.ply", *opts, expect="error")
    case(f"peel:--deconvolved {label}", "peel", "{img.valid}", "{mesh.inner}", "-o", "{out}/l.parquet", *opts,
         expect="error")
case("mesh:--from-mesh mesh.whole --deconvolved", "mesh", "{img.valid}", "--from-mesh", "{mesh.whole}", "--psf", "2",
     "1", "1", "--deconvolved", "{img.valid}", "-o", "{out}/m.ply", expect="error")
case("deconvolve:--psf auto", "deconvolve", "{img.valid}", "--psf", "auto", "-o", "{out}/d.tif", expect="ok",
     outputs=[_out("{out}/d.tif", "deconvolved")])
case("mesh:--psf 2 1 1", "mesh", "{img.valid}", "-o", "{out}/m.ply", "--psf", "2", "1", "1", expect="ok", outputs=MESH_OUT)
for label, opts in {"--psf -1 1 1": ["--psf", "-1", "1", "1"], "--psf 1e9 1 1": ["--psf", "1e9", "1", "1"],
                    "--psf nan 1 1": ["--psf", "nan", "1", "1"],
                    "--psf 1 1": ["--psf", "1", "1"], "--psf auto 1": ["--psf", "auto", "1"],
                    "--psf automatic": ["--psf", "automatic"]}.items():
    case(f"mesh:{label}", "mesh", "{img.valid}", "-o", "{out}/m.ply", *opts, expect="error")
case("mesh:--mask img.valid --mask-labels 99", "mesh", "{img.valid}", "--mask", "{img.valid}", "--mask-labels", "99",
     "-o", "{out}/m.ply", expect="error")
case("mesh:--mask img.valid --mask-threshold 1e9", "mesh", "{img.valid}", "--mask", "{img.valid}",
     "--mask-threshold", "1e9", "-o", "{out}/m.ply", expect="error")
# OME-Zarr images: read like the TIFF (level 0 or a level folder); a plain Zarr group or damaged chunks refused
for name, expect in {"zarr": "ok", "zarr_plain": "error", "zarr_chunks": "error"}.items():
    case(f"mesh:img.{name}", "mesh", f"{{img.{name}}}", "-o", "{out}/m.ply", expect=expect, outputs=MESH_OUT)
    case(f"info:img.{name}", "info", f"{{img.{name}}}", expect="ok" if name != "zarr_plain" else "error")
case("mesh:img.zarr level 1", "mesh", "{img.zarr}/1", "-o", "{out}/m.ply", "--split", "none", expect="ok",
     outputs=[_out("{out}/m.ply", "mesh")])
# user surfaces (--from-mesh): NEMO's and unit-named PLYs are read in their unit; broken ones, a mesh off the
# object (half size) and a foreign unit without --mesh-unit are refused
for name, expect in {"whole": "ok", "nm": "ok", "half": "error", **{k: "error" for k in BROKEN_MESHES}}.items():
    split = ["--split", "none"] if name != "whole" else []  # the others are one wall
    case(f"mesh:--from-mesh mesh.{name}", "mesh", "{img.valid}", "--from-mesh", f"{{mesh.{name}}}", *split, "-o",
         "{out}/m.ply", expect=expect, outputs=MESH_OUT)
case("mesh:--from-mesh mesh.nm --mesh-unit um", "mesh", "{img.valid}", "--from-mesh", "{mesh.nm}", "--mesh-unit",
     "um", "-o", "{out}/m.ply", expect="error")
for label, opts in {"--spacing 1 1 nan": ["--spacing", "1", "1", "nan"], "--spacing 1 1 inf": ["--spacing", "1", "1", "inf"],
                    "--spacing -1 1 1": ["--spacing", "-1", "1", "1"], "--threshold nan": ["--threshold", "nan"],
                    "--threshold 1e308": ["--threshold", "1e308"], "--step 1000": ["--step", "1000"],
                    "--sigma nan": ["--sigma", "nan"], "--sigma -1": ["--sigma", "-1"], "--t 1": ["--t", "1"],
                    "--c -1": ["--c", "-1"], "--split axis (no --axis)": ["--split", "axis"],
                    "--split axis --axis 0 0 0": ["--split", "axis", "--axis", "0", "0", "0"],
                    "--centre nan 0 0": ["--centre", "nan", "0", "0"]}.items():
    case(f"mesh:{label}", "mesh", "{img.valid}", "-o", "{out}/m.ply", *opts, expect="error")
for label, opts in {"--sigma 1e308": ["--sigma", "1e308"], "--sigma 0": ["--sigma", "0"],
                    "--centre 1e308 0 0": ["--centre", "1e308", "0", "0"], "--step 3": ["--step", "3"]}.items():
    case(f"mesh:{label}", "mesh", "{img.valid}", "-o", "{out}/m.ply", *opts, outputs=MESH_OUT)
case("mesh:odd names in and out", "mesh", "{odd.subst}", "-o", "{out}/out put ✓/$(touch pwned);m.ply", expect="ok",
     outputs=[_out("{out}/out put ✓/$(touch pwned);m.ply", "mesh")])
case("mesh:odd.unicode", "mesh", "{odd.unicode}", "-o", "{out}/m.ply", expect="ok", outputs=MESH_OUT)
case("mesh:out under a file", "mesh", "{img.valid}", "-o", "{block}/m.ply", expect="error")
case("mesh:out is a folder", "mesh", "{img.valid}", "-o", "{out}", expect="error")
case("mesh:out .vtk", "mesh", "{img.valid}", "-o", "{out}/m.vtk", expect="error")

# ---------------------------------------------------------------------------- curvature
GOOD_MESHES = {"whole": "ok", "inner": "ok", "outer": "ok", "half": "ok", "nm": "ok"}
MESHES = {**GOOD_MESHES, **{k: "error" for k in BROKEN_MESHES}}
CURV_OUT = [_out("{out}/c.parquet", "table:curvature")]
for name, expect in MESHES.items():
    fast = [] if name == "inner" else ["--samples", "2000"]  # the defaults: on the inner mesh
    case(f"curvature:mesh.{name}", "curvature", f"{{mesh.{name}}}", "-o", "{out}/c.parquet", *fast, expect=expect,
         outputs=CURV_OUT)
case("curvature:odd.mesh_space", "curvature", "{odd.mesh_space}", "-o", "{out}/c d ✓.parquet", expect="ok",
     outputs=[_out("{out}/c d ✓.parquet", "table:curvature")])
for label, opts in {"--radius 0": ["--radius", "0"], "--radius -1": ["--radius", "-1"], "--radius nan": ["--radius", "nan"],
                    "--seed -1": ["--seed", "-1"], "--samples 0": ["--samples", "0"], "--fraction 2": ["--fraction", "2"],
                    "--k-interp 0": ["--k-interp", "0"], "--seed 1.5": ["--seed", "1.5"],
                    "--local-fraction 3": ["--local-fraction", "3"], "--local-fraction -1": ["--local-fraction", "-1"],
                    "--local-fraction nan": ["--local-fraction", "nan"]}.items():
    case(f"curvature:{label}", "curvature", "{mesh.inner}", "-o", "{out}/c.parquet", *opts, expect="error")
case("curvature:--no-adaptive --local-fraction 0", "curvature", "{mesh.inner}", "-o", "{out}/c.parquet", "--no-adaptive",
     "--local-fraction", "0", outputs=CURV_OUT)
for label, opts in {"--radius inf": ["--radius", "inf"], "--radius 1e308": ["--radius", "1e308"],
                    "--radius 1e-308": ["--radius", "1e-308"], "--samples 1e9": ["--samples", "1000000000"],
                    "--fraction 1e-300": ["--fraction", "1e-300"], "--k-interp 10**9": ["--k-interp", str(10**9)]}.items():
    case(f"curvature:{label}", "curvature", "{mesh.inner}", "-o", "{out}/c.parquet", *opts, outputs=CURV_OUT)
case("curvature:out under a file", "curvature", "{mesh.inner}", "-o", "{block}/c.parquet", expect="error")


# ---------------------------------------------------------------------------- thickness
def _thickness_not_unit_mixed(corpus, out, case_id):
    """A thickness between a nm and a µm mesh is either refused or converted: most rays hit."""
    from nemo.tables import read_table

    got = read_table(out / "t.parquet")["thickness"].to_numpy()
    ref = read_table(corpus["tab.thickness"])["thickness"].to_numpy()
    assert np.isfinite(got).mean() >= 0.5 * np.isfinite(ref).mean(), \
        f"[{case_id}] thickness between meshes in nm and µm: {np.isfinite(got).mean():.0%} hits (mixed units?)"


THICK_OUT = [_out("{out}/t.parquet", "table:thickness")]
for name, expect in MESHES.items():
    chk = _thickness_not_unit_mixed if name == "nm" else None
    exp = "ok" if name in ("inner", "whole") else ("any" if expect == "ok" else expect)
    case(f"thickness:mesh.{name}->mesh.outer", "thickness", f"{{mesh.{name}}}", "{mesh.outer}", "-o",
         "{out}/t.parquet", expect=exp, outputs=THICK_OUT, check=chk)
    if name not in ("inner", "outer"):
        case(f"thickness:mesh.inner->mesh.{name}", "thickness", "{mesh.inner}", f"{{mesh.{name}}}", "-o",
             "{out}/t.parquet", expect=exp, outputs=THICK_OUT, check=chk)
case("thickness:mesh.inner->itself inward", "thickness", "{mesh.inner}", "{mesh.inner}", "--direction", "inward",
     "-o", "{out}/t.parquet", expect="ok", outputs=THICK_OUT)
for label, opts in {"--max-distance 0": ["--max-distance", "0"], "--max-distance nan": ["--max-distance", "nan"]}.items():
    case(f"thickness:{label}", "thickness", "{mesh.inner}", "{mesh.outer}", "-o", "{out}/t.parquet", *opts,
         expect="error")
case("thickness:--max-distance 1e-308", "thickness", "{mesh.inner}", "{mesh.outer}", "-o", "{out}/t.parquet",
     "--max-distance", "1e-308", outputs=THICK_OUT)
case("thickness:out = input table name", "thickness", "{mesh.inner}", "{mesh.outer}", "-o", "{mesh.inner}",
     expect="error")

# ---------------------------------------------------------------------------- measure
NOT_MANIFOLD = ("bowtie", "dupface")  # nemo measure is a diagnostic: it reports them (notes)
for name, expect in MESHES.items():
    case(f"measure:mesh.{name}", "measure", f"{{mesh.{name}}}", "--json",
         expect="ok" if name in NOT_MANIFOLD else expect, outputs=[_out("", "stdout-json")])
case("measure:--curvature tab.curvature", "measure", "{mesh.inner}", "--curvature", "{tab.curvature}", expect="ok")
for name in ("curvature_outer", "wrongcols", "csv", "empty", "missing", "layer"):
    case(f"measure:--curvature tab.{name}", "measure", "{mesh.inner}", "--curvature", f"{{tab.{name}}}",
         expect="error")
case("measure:mesh.outer --curvature tab.curvature", "measure", "{mesh.outer}", "--curvature", "{tab.curvature}",
     expect="error")


# ---------------------------------------------------------------------------- peel
def _peel_same_as_um(corpus, out, case_id):
    """A mesh in nm peeled from a µm image is either refused or converted: same intensities."""
    from nemo.tables import read_table

    got = read_table(out / "l.parquet")["intensity"].to_numpy()
    ref = read_table(corpus["tab.layer"])["intensity"].to_numpy()
    assert got.shape == ref.shape and np.allclose(got, ref, rtol=1e-3, equal_nan=True), \
        f"[{case_id}] the nm mesh peeled other intensities than the same surface in µm (units not converted)"


LAYER_OUT = [_out("{out}/l.parquet", "table:layer")]
for name, expect in MESHES.items():
    exp = {"half": "any", "nm": "any"}.get(name, expect)
    case(f"peel:img.valid+mesh.{name}", "peel", "{img.valid}", f"{{mesh.{name}}}", "-o", "{out}/l.parquet",
         expect=exp, outputs=LAYER_OUT, check=_peel_same_as_um if name == "nm" else None)
for name, expect in PIXELS.items():
    if name != "valid":
        case(f"peel:img.{name}+mesh.inner", "peel", f"{{img.{name}}}", "{mesh.inner}", "-o", "{out}/l.parquet",
             expect="any" if expect == "ok" or name == "zero" else expect, outputs=LAYER_OUT)
case("peel:--shift tab.curvature:H --profile", "peel", "{img.valid}", "{mesh.inner}", "-o", "{out}/l.parquet",
     "--shift", "{tab.curvature}:H", "--profile", expect="ok",
     outputs=[*LAYER_OUT, _out("{out}/l.profile.parquet", "table")])
for label, shift in {"tab.curvature:nope": "{tab.curvature}:nope", "tab.curvature_outer:H": "{tab.curvature_outer}:H",
                     "tab.wrongcols:a": "{tab.wrongcols}:a", "tab.csv:vertex": "{tab.csv}:vertex",
                     "tab.missing:H": "{tab.missing}:H", "no column": "{tab.curvature}",
                     "tab.empty:H": "{tab.empty}:H"}.items():
    case(f"peel:--shift {label}", "peel", "{img.valid}", "{mesh.inner}", "-o", "{out}/l.parquet", "--shift", shift,
         expect="error")
for label, opts in {"--range 5 0": ["--range", "5", "0"], "--range nan 5": ["--range", "nan", "5"],
                    "--range 0 inf": ["--range", "0", "inf"], "--samples 0": ["--samples", "0"],
                    "--spacing 0 1 1": ["--spacing", "0", "1", "1"], "--spacing 2 2 2": ["--spacing", "2", "2", "2"],
                    "--t 3": ["--t", "3"], "--shift-fraction nan": ["--shift", "{tab.curvature}:H", "--shift-fraction", "nan"]
                    }.items():
    case(f"peel:{label}", "peel", "{img.valid}", "{mesh.inner}", "-o", "{out}/l.parquet", *opts, expect="error")
for label, opts in {"--range 0 1e308": ["--range", "0", "1e308"], "--range -1e308 1e308": ["--range", "-1e308", "1e308"],
                    "--range 0 1e-12": ["--range", "0", "1e-12"], "--samples 1e9": ["--samples", "1000000000"],
                    "--range 1000 2000 (outside)": ["--range", "1000", "2000"],
                    "--shift-fraction 1e308": ["--shift", "{tab.curvature}:H", "--shift-fraction", "1e308"]}.items():
    case(f"peel:{label}", "peel", "{img.valid}", "{mesh.inner}", "-o", "{out}/l.parquet", *opts, outputs=LAYER_OUT)
case("peel:out = the --shift table", "peel", "{img.valid}", "{mesh.inner}", "--shift", "{tab.curvature}:H",
     "-o", "{tab.curvature}", expect="error")

# ---------------------------------------------------------------------------- directors
DIRS_OUT = [_out("{out}/d.parquet", "table:directors")]
for name, expect in MESHES.items():
    exp = {"half": "any", "nm": "any", "outer": "error", "whole": "error"}.get(name, expect)
    case(f"directors:mesh.{name}+tab.layer", "directors", f"{{mesh.{name}}}", "{tab.layer}", "-o", "{out}/d.parquet",
         expect=exp, outputs=DIRS_OUT)
for name in ("layer_outer", "wrongcols", "csv", "empty", "missing", "curvature"):
    case(f"directors:mesh.inner+tab.{name}", "directors", "{mesh.inner}", f"{{tab.{name}}}", "-o", "{out}/d.parquet",
         expect="error")
case("directors:mesh.inner+img.folder", "directors", "{mesh.inner}", "{img.folder}", "-o", "{out}/d.parquet",
     expect="error")
for label, opts in {"--seed -1": ["--seed", "-1"], "--pixel 1e-9": ["--pixel", "1e-9"], "--n-patches 0": ["--n-patches", "0"],
                    "--sigma nan": ["--sigma", "nan"], "--patch-k 1": ["--patch-k", "1"],
                    "--patch-radius 0": ["--patch-radius", "0"]}.items():
    case(f"directors:{label}", "directors", "{mesh.inner}", "{tab.layer}", "-o", "{out}/d.parquet", *opts,
         expect="error")
for label, opts in {"--patch-radius 1e308": ["--patch-radius", "1e308"], "--patch-radius 1e-9": ["--patch-radius", "1e-9"],
                    "--patch-radius 1e-308": ["--patch-radius", "1e-308"],
                    "--sigma inf": ["--sigma", "inf"], "--sigma 1e-300": ["--sigma", "1e-300"],
                    "--pixel 1e308": ["--pixel", "1e308"], "--n-patches 10**12": ["--n-patches", str(10**12)],
                    "--patch-k 10**9": ["--patch-k", str(10**9)], "--frames smooth": ["--frames", "smooth"]}.items():
    case(f"directors:{label}", "directors", "{mesh.inner}", "{tab.layer}", "-o", "{out}/d.parquet", *opts,
         outputs=DIRS_OUT)
case("directors:out = input layer", "directors", "{mesh.inner}", "{tab.layer}", "-o", "{tab.layer}", expect="error")

# ---------------------------------------------------------------------------- order
ORDER_OUT = [_out("{out}/o.parquet", "table:order")]
for name, expect in MESHES.items():
    exp = {"half": "any", "nm": "any", "outer": "error", "whole": "error"}.get(name, expect)
    case(f"order:mesh.{name}+tab.directors", "order", f"{{mesh.{name}}}", "{tab.directors}", "-o", "{out}/o.parquet",
         expect=exp, outputs=ORDER_OUT)
for name in ("directors_outer", "layer", "wrongcols", "csv", "empty", "missing"):
    case(f"order:mesh.inner+tab.{name}", "order", "{mesh.inner}", f"{{tab.{name}}}", "-o", "{out}/o.parquet",
         expect="error")
case("order:mesh.inner+tab.directors_half", "order", "{mesh.inner}", "{tab.directors_half}", "-o", "{out}/o.parquet",
     outputs=ORDER_OUT)
for label, opts in {"--radius 0": ["--radius", "0"], "--radius nan": ["--radius", "nan"],
                    "--radius -1": ["--radius", "-1"]}.items():
    case(f"order:{label}", "order", "{mesh.inner}", "{tab.directors}", "-o", "{out}/o.parquet", *opts, expect="error")
for label, opts in {"--radius inf": ["--radius", "inf"], "--radius 1e308": ["--radius", "1e308"],
                    "--radius 1e-308": ["--radius", "1e-308"], "--targets directors": ["--targets", "directors"]}.items():
    case(f"order:{label}", "order", "{mesh.inner}", "{tab.directors}", "-o", "{out}/o.parquet", *opts,
         outputs=ORDER_OUT)
case("order:out = input directors", "order", "{mesh.inner}", "{tab.directors}", "-o", "{tab.directors}",
     expect="error")
case("order:out = input directors (./ path)", "order", "{mesh.inner}", "{tab.directors}", "-o",
     "{dot:tab.directors}", expect="error")

# ---------------------------------------------------------------------------- align
ALIGN_OUT = [_out("{out}/a.parquet", "table:align")]
case("align:tab.directors+tab.directors", "align", "{tab.directors}", "{tab.directors}", "-o", "{out}/a.parquet",
     expect="ok", outputs=ALIGN_OUT)
case("align:tab.directors_outer+tab.directors --mesh outer", "align", "{tab.directors_outer}", "{tab.directors}",
     "--mesh", "{mesh.outer}", "-o", "{out}/a.parquet", expect="ok", outputs=ALIGN_OUT)
for name in ("wrongcols", "csv", "empty", "missing", "layer"):
    case(f"align:tab.directors+tab.{name}", "align", "{tab.directors}", f"{{tab.{name}}}", "-o", "{out}/a.parquet",
         expect="error")
    case(f"align:tab.{name}+tab.directors", "align", f"{{tab.{name}}}", "{tab.directors}", "-o", "{out}/a.parquet",
         expect="error")
for name, expect in MESHES.items():
    exp = {"half": "any", "nm": "any", "outer": "error", "whole": "error"}.get(name, expect)
    case(f"align:--mesh mesh.{name}", "align", "{tab.directors}", "{tab.directors_outer}", "--mesh",
         f"{{mesh.{name}}}", "-o", "{out}/a.parquet", expect=exp, outputs=ALIGN_OUT)
for label, opts in {"--bins 0": ["--bins", "0"], "--max-distance 0": ["--max-distance", "0"],
                    "--max-distance nan": ["--max-distance", "nan"]}.items():
    case(f"align:{label}", "align", "{tab.directors}", "{tab.directors}", "-o", "{out}/a.parquet", *opts,
         expect="error")
for label, opts in {"--bins 10**5": ["--bins", str(10**5)], "--max-distance 1e-308": ["--max-distance", "1e-308"]}.items():
    case(f"align:{label}", "align", "{tab.directors}", "{tab.directors}", "-o", "{out}/a.parquet", *opts,
         outputs=ALIGN_OUT)
case("align:out = input A", "align", "{tab.directors}", "{tab.directors_outer}", "-o", "{tab.directors}",
     expect="error")

# ---------------------------------------------------------------------------- defects
DEF_OUT = [_out("{out}/x.parquet", "table:defects")]
DEF = ("defects", "{mesh.inner}", "{tab.order}", "{tab.directors}")
case("defects:valid", *DEF, "-o", "{out}/x.parquet", expect="ok", outputs=DEF_OUT)
for source in ("contour", "angle-defects"):
    case(f"defects:--curvature-source {source}", *DEF, "--curvature-source", source, "-o", "{out}/x.parquet",
         expect="ok", outputs=DEF_OUT)
case("defects:--curvature-source table without --curvature", *DEF, "--curvature-source", "table", "-o",
     "{out}/x.parquet", expect="error")
case("defects:--curvature with --curvature-source contour", *DEF, "--curvature", "{tab.curvature}",
     "--curvature-source", "contour", "-o", "{out}/x.parquet", expect="warn", outputs=DEF_OUT,
     warns=("is not used",))
case("defects:valid --layer --refined --curvature", *DEF, "--layer", "{tab.layer}", "--refined", "{out}/r.parquet",
     "--curvature", "{tab.curvature}", "--curvature-source", "table", "-o", "{out}/x.parquet", expect="ok",
     outputs=[*DEF_OUT, _out("{out}/r.parquet", "table:directors")])
for name, expect in MESHES.items():
    exp = {"half": "any", "nm": "any", "outer": "error", "whole": "error"}.get(name, expect)
    case(f"defects:mesh.{name}", "defects", f"{{mesh.{name}}}", "{tab.order}", "{tab.directors}", "-o",
         "{out}/x.parquet", expect=exp, outputs=DEF_OUT)
for name in ("wrongcols", "csv", "empty", "missing", "directors", "layer"):
    case(f"defects:order=tab.{name}", "defects", "{mesh.inner}", f"{{tab.{name}}}", "{tab.directors}", "-o",
         "{out}/x.parquet", expect="error")
for name in ("wrongcols", "csv", "empty", "missing", "directors_outer", "order"):
    case(f"defects:directors=tab.{name}", "defects", "{mesh.inner}", "{tab.order}", f"{{tab.{name}}}", "-o",
         "{out}/x.parquet", expect="error")
for name in ("curvature_outer", "wrongcols", "csv"):
    case(f"defects:--curvature tab.{name}", *DEF, "--curvature", f"{{tab.{name}}}", "--curvature-source", "table",
         "-o", "{out}/x.parquet", expect="error")
for name in ("layer_outer", "csv", "wrongcols"):
    case(f"defects:--layer tab.{name}", *DEF, "--layer", f"{{tab.{name}}}", "-o", "{out}/x.parquet", expect="error")
for label, opts in {"--max-defects 0": ["--max-defects", "0"], "--s-threshold nan": ["--s-threshold", "nan"],
                    "--refine-directors 2": ["--layer", "{tab.layer}", "--refine-directors", "2"],
                    "--refine-directors nan": ["--layer", "{tab.layer}", "--refine-directors", "nan"],
                    "--refine-directors -1": ["--layer", "{tab.layer}", "--refine-directors", "-1"],
                    "--contour-radius -1": ["--contour-radius", "-1"]}.items():
    case(f"defects:{label}", *DEF, "-o", "{out}/x.parquet", *opts, expect="error")
for label, opts in {"--contour-radius 1e308": ["--contour-radius", "1e308"],
                    "--contour-radius 1e-308": ["--contour-radius", "1e-308"],
                    "--min-distance 1e308": ["--min-distance", "1e308"], "--avg-radius inf": ["--avg-radius", "inf"],
                    "--s-threshold 1e308": ["--s-threshold", "1e308"], "--max-defects 10**12": ["--max-defects", str(10**12)],
                    "--winding-field directors --refine q": ["--winding-field", "directors", "--refine", "q"]}.items():
    case(f"defects:{label}", *DEF, "-o", "{out}/x.parquet", *opts, outputs=DEF_OUT)
case("defects:out = input order", *DEF, "-o", "{tab.order}", expect="error")
case("defects:--refined = input layer", *DEF, "--layer", "{tab.layer}", "--refined", "{tab.layer}", "-o",
     "{out}/x.parquet", expect="error")
case("defects:out = --curvature input", *DEF, "--curvature", "{tab.curvature}", "-o", "{tab.curvature}",
     expect="error")

# ---------------------------------------------------------------------------- run
RUN_OUT = [_out("{out}/r", "run")]
for name, expect in PIXELS.items():
    if name == "valid":
        continue  # the valid image runs with the valid config below (the same steps, shorter)
    case(f"run:img.{name}", "run", f"{{img.{name}}}", "--config", "{cfg.valid}", "-o", "{out}/r", expect=expect,
         outputs=RUN_OUT)
case("run:img.valid --config cfg.valid", "run", "{img.valid}", "--config", "{cfg.valid}", "-o", "{out}/r",
     expect="ok", outputs=RUN_OUT)
case("run:img.valid --print-config", "run", "{img.valid}", "--print-config", expect="ok",
     outputs=[_out("", "stdout-yaml")])
for name in ("neg_seed", "radius0", "unknown", "types", "strnum", "nan", "notyaml", "list", "missing"):
    case(f"run:--config cfg.{name}", "run", "{img.valid}", "--config", f"{{cfg.{name}}}", "-o", "{out}/r",
         expect="error")
case("run:--config cfg.huge", "run", "{img.valid}", "--config", "{cfg.huge}", "-o", "{out}/r", outputs=RUN_OUT)
case("run:--config img.valid (not YAML)", "run", "{img.valid}", "--config", "{img.valid}", "-o", "{out}/r",
     expect="error")
case("run:out under a file", "run", "{img.valid}", "-o", "{block}/r", expect="error")
case("run:out = the input image", "run", "{img.valid}", "-o", "{img.valid}", expect="error")
case("run:--dataset nope", "run", "{img.valid}", "--dataset", "nope", "-o", "{out}/r", expect="error")
case("run:no image", "run", "-o", "{out}/r", expect="error")
case("run:--t 5", "run", "{img.valid}", "--t", "5", "-o", "{out}/r", expect="error")
case("run:--spacing 0 1 1", "run", "{img.valid}", "--spacing", "0", "1", "1", "-o", "{out}/r", expect="error")

# ---------------------------------------------------------------------------- track
TRACK_OUT = [_out("{out}/tracks.parquet", "table"), _out("{out}/linked.parquet", "table")]
case("track:tab.defects_t", "track", "{tab.defects_t}", "-o", "{out}/tracks.parquet", "--linked",
     "{out}/linked.parquet", expect="ok", outputs=TRACK_OUT)
for name in ("defects", "wrongcols", "csv", "empty", "missing", "layer"):
    case(f"track:tab.{name}", "track", f"{{tab.{name}}}", "-o", "{out}/tracks.parquet", expect="error")
case("track:img.folder", "track", "{img.folder}", "-o", "{out}/tracks.parquet", expect="error")
for label, opts in {"--max-distance 0": ["--max-distance", "0"], "--gap-frames -1": ["--gap-frames", "-1"],
                    "--max-distance nan": ["--max-distance", "nan"]}.items():
    case(f"track:{label}", "track", "{tab.defects_t}", "-o", "{out}/tracks.parquet", *opts, expect="error")
case("track:--frames 0 -2.5e-311 (a negative value argparse takes for an option)", "track", "{tab.defects_t}", "-o",
     "{out}/tracks.parquet", "--frames", "0", "-2.5e-311", expect="error")
for label, opts in {"--max-distance 1e308": ["--max-distance", "1e308"], "--gap-frames 10**9": ["--gap-frames", str(10**9)],
                    "--frames -1 0 1": ["--frames", "-1", "0", "1"], "--frames 0": ["--frames", "0"],
                    "--gap-max-distance 1e-308": ["--gap-max-distance", "1e-308"]}.items():
    case(f"track:{label}", "track", "{tab.defects_t}", "-o", "{out}/tracks.parquet", *opts,
         outputs=TRACK_OUT[:1])
case("track:out = input", "track", "{tab.defects_t}", "-o", "{tab.defects_t}", expect="error")
case("track:--linked = input", "track", "{tab.defects_t}", "-o", "{out}/tracks.parquet", "--linked",
     "{tab.defects_t}", expect="error")

# ---------------------------------------------------------------------------- render
FIGS = [_out("{out}/f", "figs")]
case("render:frame", "render", "{frame}", "-o", "{out}/f", expect="ok", outputs=FIGS)
case("render:frame --no-surfaces --layer fibres", "render", "{frame}", "--no-surfaces", "--layer", "fibres", "-o",
     "{out}/f", expect="ok", outputs=FIGS)
case("render:frame --list", "render", "{frame}", "--list", expect="ok")
case("render:files", "render", "{mesh.inner}", "{tab.layer}", "{tab.order}", "{tab.defects}", "--no-surfaces", "-o",
     "{out}/f", expect="ok", outputs=FIGS)
case("render:frame_bad", "render", "{frame_bad}", "--no-surfaces", "-o", "{out}/f", expect="warn", outputs=FIGS,
     warns=("mesh.inner.ply", "order_fibres.parquet"))
case("render:mesh.cut + tab.order", "render", "{mesh.cut}", "{tab.order}", "--no-surfaces", "-o", "{out}/f",
     expect="error")
case("render:mesh.outer + tab.order (other mesh)", "render", "{mesh.outer}", "{tab.order}", "-o", "{out}/f",
     expect="warn", outputs=FIGS, warns=("order.parquet",))
case("render:mesh.bowtie + tab.layer", "render", "{mesh.bowtie}", "{tab.layer}", "--no-surfaces", "-o", "{out}/f",
     expect="any")  # renders show what is there; the table of another mesh is left out with a warning
case("render:--summary summary", "render", "--summary", "{summary}", "-o", "{out}/f", expect="ok", outputs=FIGS)
case("render:--summary frame", "render", "--summary", "{frame}", "-o", "{out}/f", expect="error")
case("render:--summary tab.wrongcols", "render", "--summary", "{tab.wrongcols}", "-o", "{out}/f", expect="error")
case("render:missing", "render", "{tab.missing}", "-o", "{out}/f", expect="error")
case("render:img.folder (empty folder)", "render", "{img.folder}", "-o", "{out}/f", expect="error")
case("render:out under a file", "render", "{frame}", "--no-surfaces", "-o", "{block}/f", expect="error")

# ---------------------------------------------------------------------------- validate
_ELL = '{"kind": "ellipsoid", "axes": [6, 5, 4], "spacing": [1, 1, 1]}'
case("validate:shape", "validate", "shape", _ELL, "-o", "{out}/e.tif", "--truth", "{out}/e.json", expect="ok",
     outputs=[_out("{out}/e.tif", "tif"), _out("{out}/e.json", "json")])
case("validate:shape not JSON", "validate", "shape", "{kind: torus", "-o", "{out}/e.tif", "--truth", "{out}/e.json",
     expect="error")
case("validate:shape torus without minor", "validate", "shape", '{"kind": "torus", "major": 5}', "-o", "{out}/e.tif",
     "--truth", "{out}/e.json", expect="error")
case("validate:shape out under a file", "validate", "shape", _ELL, "-o", "{block}/e.tif", "--truth", "{out}/e.json",
     expect="error")
case("validate:score-shape truth = a table", "validate", "score-shape", "{mesh.inner}", "{tab.defects}", "-o",
     "{out}/s.json", expect="error")
case("validate:score tab.defects without truth", "validate", "score", "--truth", "{tab.missing}", "--defects",
     "{tab.defects}", "-o", "{out}/s.json", expect="error")
case("validate:aggregate --scores a table", "validate", "aggregate", "--scores", "{tab.defects}", "-o",
     "{out}/summary", expect="error")

assert len({c.id for c in CASES}) == len(CASES), "duplicate case ids"
COMMANDS_COVERED = {c.argv[0] for c in CASES}


def test_every_command_is_covered():
    from nemo.cli import COMMANDS

    assert set(COMMANDS) - {"view"} <= COMMANDS_COVERED


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_command_on_hostile_input(case, corpus, tmp_path, capsys, monkeypatch):
    run_case(case, corpus, tmp_path, capsys, monkeypatch)


# ============================================================================ outputs never replace inputs

@pytest.mark.parametrize("argv, victim", [
    (["order", "{mesh.inner}", "{tab.directors}", "-o", "{tab.directors}"], "tab.directors"),
    (["directors", "{mesh.inner}", "{tab.layer}", "-o", "{tab.layer}"], "tab.layer"),
], ids=["order -o directors", "directors -o layer"])
def test_output_equal_to_input_is_refused_and_the_input_kept(argv, victim, corpus, tmp_path, capsys, monkeypatch):
    before = corpus.baseline[str(corpus[victim].relative_to(corpus.root))]
    code, _, err = run_case(Case(f"{argv[0]} -o {victim}", tuple(argv), "error"), corpus, tmp_path, capsys, monkeypatch)
    assert code == 2 and "input" in error_paragraph(argv[0], err)
    assert corpus.snapshot()[str(corpus[victim].relative_to(corpus.root))] == before


def test_a_wall_is_never_written_over_the_input_surface(corpus, tmp_path, capsys):
    """``nemo mesh --from-mesh W.inner.ply -o W.ply`` would write its inner wall over the input."""
    import hashlib

    surface = tmp_path / "w.inner.ply"
    shutil.copy(corpus["mesh.whole"], surface)
    before = hashlib.md5(surface.read_bytes()).hexdigest()
    code, _, err = invoke(["mesh", str(corpus["img.valid"]), "--from-mesh", str(surface), "-o",
                           str(tmp_path / "w.ply")], capsys, "mesh over its input's name")
    assert code == 2 and "is the input" in err
    assert hashlib.md5(surface.read_bytes()).hexdigest() == before


def test_peel_warns_when_its_mesh_was_made_with_another_psf(corpus, tmp_path, capsys):
    """A mesh made from the deconvolved image, peeled from the raw one, is named with the fix."""
    from nemo.tables import read_provenance

    mesh = tmp_path / "m.ply"
    assert invoke(["mesh", str(corpus["img.valid"]), "-o", str(mesh), "--psf", "2", "1", "1"], capsys, "mesh")[0] == 0
    inner = tmp_path / "m.inner.ply"
    code, _, err = invoke(["peel", str(corpus["img.valid"]), str(inner), "-o", str(tmp_path / "a.parquet")],
                          capsys, "peel without")
    assert code == 0 and "was made with --psf 2.0 1.0 1.0" in err and "give nemo peel the same --psf" in err
    code, _, err = invoke(["peel", str(corpus["img.valid"]), str(inner), "-o", str(tmp_path / "b.parquet"), "--psf",
                           "2", "1", "1"], capsys, "peel with")
    assert code == 0 and "--psf" not in err
    record = read_provenance(tmp_path / "b.parquet")["parameters"]["deconvolution"]
    assert record["psf"] == [2.0, 1.0, 1.0] and record["iterations"] > 0


def test_the_step_commands_go_through_an_all_zero_channel(corpus, tmp_path, capsys):
    """An all-zero channel peeled on a good mesh: the workflow's step commands each write their table
    (no directors, NaN order, no defect search, no alignment) and say why, so one bad channel or
    frame does not stop the dataset (`nemo peel` refused it; `nemo defects` then crashed on its print)."""
    from nemo.tables import read_provenance, read_table

    mesh, f = str(corpus["mesh.inner"]), {k: str(tmp_path / f"{k}.parquet") for k in ("l", "d", "o", "x", "a")}
    steps = {"peel": ["peel", str(corpus["img.zero"]), mesh, "-o", f["l"], "--range", "0", "2"],
             "directors": ["directors", mesh, f["l"], "-o", f["d"]], "order": ["order", mesh, f["d"], "-o", f["o"]],
             "defects": ["defects", mesh, f["o"], f["d"], "-o", f["x"], "--candidates", str(tmp_path / "c.parquet")],
             "align": ["align", f["d"], f["d"], "-o", f["a"]]}
    said = {}
    for name, argv in steps.items():
        code, out, err = invoke(argv, capsys, name)
        assert code == 0, (name, err)
        said[name] = out + err
    assert "intensity is 0 at every vertex" in said["peel"] and "no directors" in said["directors"]
    assert "no order value: no director" in said["order"] and "Mean of empty slice" not in said["order"]
    assert "no defect search" in said["defects"] and "no alignment" in said["align"]
    assert len(read_table(f["d"], "directors")) == 0 and read_table(f["o"], "order")["S"].isna().all()
    assert len(read_table(f["x"], "defects")) == 0 and read_provenance(f["x"])["euler_check"]["skipped"]
    assert len(read_table(tmp_path / "c.parquet")) == 0  # no candidate examined


def test_psf_auto_is_read_wherever_it_stands():
    """--psf auto (or --psf=auto) before or after the image: the image stays the image, and --psf
    with three numbers still stops after them (the first --psf auto swallowed what followed it)."""
    from nemo.cli import build_parser
    from nemo.cli.common import psf_auto_option

    for argv in (["run", "--psf", "auto", "v.tif", "-o", "out"], ["run", "v.tif", "--psf=auto", "-o", "out"]):
        args = build_parser("run").parse_args(psf_auto_option(argv))
        assert args.psf == "auto" and args.image == "v.tif", args
    args = build_parser("run").parse_args(psf_auto_option(["run", "--psf", "2", "1", "1", "v.tif", "-o", "out"]))
    assert args.psf == [2.0, 1.0, 1.0] and args.image == "v.tif"
    assert psf_auto_option(["peel", "auto.tif", "--psf", "1", "1", "1"]) == ["peel", "auto.tif", "--psf", "1", "1", "1"]


def test_psf_none_and_the_default_auto_on_the_step_commands():
    """nemo mesh / peel / deconvolve take the config's default, auto, when --psf is not given; --psf none
    (or --psf=none, before or after the image) deconvolves nothing; nemo run leaves it to the dataset."""
    from nemo.cli import build_parser
    from nemo.cli.common import psf_auto_option, step_psf

    for argv, psf in ((["mesh", "v.tif", "-o", "m.ply"], "auto"), (["mesh", "--psf", "none", "v.tif", "-o", "m.ply"], None),
                      (["mesh", "v.tif", "--psf=none", "-o", "m.ply"], None),
                      (["mesh", "v.tif", "--psf", "2", "1", "1", "-o", "m.ply"], (2.0, 1.0, 1.0))):
        args = build_parser("mesh").parse_args(psf_auto_option(argv))
        step_psf(args)
        assert args.psf == psf and args.image == "v.tif", (argv, args)
    assert build_parser("run").parse_args(["run", "v.tif", "-o", "out"]).psf is None  # the dataset's (auto)


def test_peel_compares_the_psf_only_with_a_mesh_of_its_own_channel():
    """A mesh of channel 0 deconvolved by channel 0's PSF, peeled on channel 1 with channel 1's
    PSF (datasets.NAME.psf per channel): no warning; on channel 0 with another PSF: the warning."""
    import trimesh

    from nemo.cli.peel import _check_same_psf

    mesh = trimesh.creation.icosphere(subdivisions=1)
    mesh.metadata["nemo_params"] = {"deconvolution": {"psf": [2.0, 1.0, 1.0]}, "t": 0, "c": 0}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _check_same_psf(mesh, [3.0, 1.5, 1.5], "m.ply", 1)
        _check_same_psf(mesh, [2.0, 1.0, 1.0], "m.ply", 0)
    with pytest.warns(NemoWarning, match="was made with --psf 2.0 1.0 1.0"):
        _check_same_psf(mesh, [3.0, 1.5, 1.5], "m.ply", 0)
    with pytest.warns(NemoWarning, match=r"was made with --psf 2.0 1.0 1.0, this peel has auto \(the default\)"):
        _check_same_psf(mesh, "auto", "m.ply", 0)
    mesh.metadata["nemo_params"]["deconvolution"] = {"psf": [1.7, 0.0, 0.0], "estimated": True}  # psf: auto
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _check_same_psf(mesh, "auto", "m.ply", 0)
    with pytest.warns(NemoWarning, match="was made with --psf auto, this peel has another"):
        _check_same_psf(mesh, [1.7, 0.0, 0.0], "m.ply", 0)
    # made with --psf none, peeled at the default (auto): the slip the default makes likely is named
    mesh.metadata["nemo_params"]["deconvolution"] = {"psf": None, "estimated": False, "iterations": 0}
    with pytest.warns(NemoWarning, match=r"was made with --psf none, this peel has auto \(the default\)"):
        _check_same_psf(mesh, "auto", "m.ply", 0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _check_same_psf(mesh, None, "m.ply", 0)
        mesh.metadata["nemo_params"] = {"t": 0, "c": 0}  # no record (another tool's mesh): nothing to compare
        _check_same_psf(mesh, "auto", "m.ply", 0)


def test_deconvolved_once_meshes_and_peels_as_deconvolving_again(corpus, tmp_path, capsys):
    """nemo deconvolve, then nemo mesh / peel --deconvolved: the same mesh and layer as with --psf
    alone (the workflow's path and nemo run's), and a file made for another PSF is refused."""
    from nemo.mesh import load_mesh
    from nemo.tables import read_table

    img, psf = str(corpus["img.valid"]), ["--psf", "2", "1", "1"]
    dec = str(tmp_path / "d.tif")
    assert invoke(["deconvolve", img, *psf, "-o", dec], capsys, "deconvolve")[0] == 0
    for tag, extra in (("a", []), ("b", ["--deconvolved", dec])):
        assert invoke(["mesh", img, *psf, *extra, "-o", str(tmp_path / f"{tag}.ply")], capsys, "mesh")[0] == 0
        assert invoke(["peel", img, str(tmp_path / f"{tag}.inner.ply"), *psf, *extra, "-o",
                       str(tmp_path / f"{tag}.parquet")], capsys, "peel")[0] == 0
    a, b = (load_mesh(tmp_path / f"{tag}.inner.ply") for tag in "ab")
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.faces, b.faces)
    a, b = (read_table(tmp_path / f"{tag}.parquet") for tag in "ab")
    np.testing.assert_array_equal(a["intensity"], b["intensity"])
    import tifffile

    from nemo.tables import read_provenance

    made = json.loads(tifffile.TiffFile(dec).pages[0].description)["record"]
    used = read_provenance(tmp_path / "b.parquet")["parameters"]["deconvolution"]
    assert used == made  # the file's deconvolution (its record, seconds included), not one made again
    code, _, err = invoke(["peel", img, str(tmp_path / "a.inner.ply"), "--psf", "2.5", "1", "1", "--deconvolved",
                           dec, "-o", str(tmp_path / "c.parquet")], capsys, "other psf")
    assert code == 2 and "made for the PSF [2.0, 1.0, 1.0]" in err and "nemo deconvolve again" in err


def test_walls_of_an_earlier_run_are_named_when_not_replaced(corpus, tmp_path, capsys):
    out = tmp_path / "m.ply"
    assert invoke(["mesh", str(corpus["img.valid"]), "-o", str(out)], capsys, "split")[0] == 0
    code, _, err = invoke(["mesh", str(corpus["img.valid"]), "-o", str(out), "--split", "none"], capsys, "none")
    assert code == 0 and "m.inner.ply and" in err and "left from an earlier run" in err


# ============================================================================ real processes

@pytest.mark.parametrize("argv, expect", [
    (["info", "{img.text}"], 2),
    (["mesh", "{img.trunc_mid}", "-o", "{out}/m.ply"], 2),
    (["order", "{mesh.inner}", "{tab.directors}", "-o", "{tab.directors}"], 2),
    (["curvature", "{mesh.inner}", "--seed", "-1", "-o", "{out}/c.parquet"], 2),
    (["info", "{odd.subst}"], 0),
], ids=["info text", "mesh truncated", "order -o input", "curvature --seed -1", "info $(touch pwned).tif"])
def test_exit_status_of_the_real_command(argv, expect, corpus, tmp_path):
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    args = [fill(a, corpus, out_dir) for a in argv]
    proc = subprocess.run([str(NEMO), *args], capture_output=True, text=True, cwd=tmp_path, timeout=120, check=False,
                          env={**os.environ, "NEMO_WORKER": "off"})
    case_id = " ".join(argv)
    try:
        assert proc.returncode == expect, f"[{case_id}] exit {proc.returncode}, expected {expect}\n{proc.stderr[-2000:]}"
        assert "Traceback" not in proc.stderr, f"[{case_id}] traceback:\n{proc.stderr[-2000:]}"
        if expect == 2:
            error_paragraph(argv[0], proc.stderr)
    finally:
        corpus_intact(corpus, case_id, tmp_path)


# ============================================================================ option values (Hypothesis)

#: Hostile option values: numbers of every sign and size, non-numbers, odd spellings.
NUMBERS = ["-1", "0", "-0", "nan", "NaN", "inf", "-inf", "1e308", "-1e308", "1e-308", "1e400", "0.5", "3", "1000",
           "4294967296", "-4294967297", "1e-9", "2.5", "10", "1e6"]
STRINGS = ["", " ", "abc", "1,5", "0x10", "1_000", "٣", "½", "1e", "--", "-", "None", "$(touch pwned)", "; touch pwned"]
VALUE = st.one_of(
    st.sampled_from(NUMBERS),
    st.integers(-3, 300).map(str),
    st.integers(-(2**66), 2**66).map(str),
    st.floats(min_value=1e-3, max_value=1e3).map(repr),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.sampled_from(STRINGS),
    st.text(max_size=4),
)

#: Step command -> (fixed arguments, {option: number of values}).
STEPS = {
    "mesh": (["{img.valid}", "-o", "{out}/m.ply"],
             {"--sigma": 1, "--threshold": 1, "--step": 1, "--t": 1, "--c": 1, "--spacing": 3, "--centre": 3}),
    "curvature": (["{mesh.inner}", "-o", "{out}/c.parquet"],
                  {"--radius": 1, "--samples": 1, "--k-interp": 1, "--seed": 1, "--fraction": 1}),
    "thickness": (["{mesh.inner}", "{mesh.outer}", "-o", "{out}/t.parquet"], {"--max-distance": 1}),
    "peel": (["{img.valid}", "{mesh.inner}", "-o", "{out}/l.parquet", "--shift", "{tab.curvature}:H"],
             {"--range": 2, "--samples": 1, "--shift-fraction": 1, "--spacing": 3, "--t": 1, "--c": 1}),
    "directors": (["{mesh.inner}", "{tab.layer}", "-o", "{out}/d.parquet"],
                  {"--patch-radius": 1, "--n-patches": 1, "--pixel": 1, "--sigma": 1, "--seed": 1}),
    "order": (["{mesh.inner}", "{tab.directors}", "-o", "{out}/o.parquet"], {"--radius": 1}),
    "align": (["{tab.directors}", "{tab.directors_outer}", "-o", "{out}/a.parquet"], {"--max-distance": 1, "--bins": 1}),
    "defects": (["{mesh.inner}", "{tab.order}", "{tab.directors}", "-o", "{out}/x.parquet", "--layer", "{tab.layer}"],
                {"--s-threshold": 1, "--min-distance": 1, "--max-defects": 1, "--contour-radius": 1,
                 "--avg-radius": 1, "--refine-directors": 1}),
    "track": (["{tab.defects_t}", "-o", "{out}/tracks.parquet"],
              {"--max-distance": 1, "--gap-frames": 1, "--gap-max-distance": 1, "--frames": 2}),
    "synth": (["{out}/s.tif", *hostile.SYNTH_ARGS],
              {"--radius": 1, "--size": 1, "--seed": 1, "--noise": 1, "--blur": 1, "--fibre-spacing": 1,
               "--layer-depth": 1, "--frames": 1}),
}
OUTPUT_KIND = {"mesh": "mesh", "curvature": "table:curvature", "thickness": "table:thickness", "peel": "table:layer",
               "directors": "table:directors", "order": "table:order", "align": "table:align",
               "defects": "table:defects", "track": "table", "synth": "tif"}

#: A forked child running longer than this (seconds) is reported as a hang. The slowest legitimate case,
#: `defects --avg-radius 2 --min-distance 2` on the corpus mesh (~1 500 low-S candidates, three searches),
#: takes 8-12 s alone and ran past 30 s with both cores busy (CI beside other jobs).
CHILD_TIMEOUT = 60
#: Address space granted to a child above what it starts with (bytes).
CHILD_EXTRA_MEMORY = 6 * 2**30


@pytest.fixture(scope="session")
def forker():
    """Runs ``nemo ARGV`` in a child forked from a clean server process that has imported the
    heavy modules once (multiprocessing's forkserver): fast, isolated from this process's
    threads, with a time and a memory limit."""
    import multiprocessing as mp

    from nemo.worker import PRELOAD

    ctx = mp.get_context("forkserver")
    ctx.set_forkserver_preload([*PRELOAD, "hostile"])
    return ctx


def run_forked(ctx, argv: list[str], result: Path, timeout: float = CHILD_TIMEOUT) -> dict:
    proc = ctx.Process(target=hostile.child_main, args=(argv, str(result), CHILD_EXTRA_MEMORY))
    proc.start()
    proc.join(timeout)
    if proc.is_alive():
        proc.kill()
        proc.join()
        return {"code": None, "hang": True, "out": "", "err": ""}
    if not result.exists():
        return {"code": None, "died": proc.exitcode, "out": "", "err": ""}
    return json.loads(result.read_text())


@pytest.mark.parametrize("command", sorted(STEPS))
def test_option_values_never_crash(command, corpus, forker, tmp_path_factory):
    fixed, options = STEPS[command]
    names = sorted(options)

    def check(data):
        chosen = data.draw(st.lists(st.sampled_from(names), min_size=1, max_size=2, unique=True), label="options")
        opts = []
        for name in chosen:
            opts += [name, *(data.draw(VALUE, label=name) for _ in range(options[name]))]
        tmp = tmp_path_factory.mktemp(command)
        out_dir = tmp / "out"
        out_dir.mkdir()
        # values are attached with '=' so that '-1' or '--' are taken as values, not options
        argv = [command] + [fill(a, corpus, out_dir) for a in fixed]
        i = 0
        while i < len(opts):
            n = options[opts[i]]
            if n == 1:
                argv.append(f"{opts[i]}={opts[i + 1]}")
            else:
                argv += [opts[i], *opts[i + 1:i + 1 + n]]
            i += 1 + n
        case_id = f"{command} {' '.join(opts)!r}"
        res = run_forked(forker, argv, tmp / "result.json")
        try:
            assert not res.get("hang"), f"[{case_id}] still running after {CHILD_TIMEOUT} s (hang?)"
            assert "died" not in res, f"[{case_id}] the process died (exit code {res.get('died')}: a crash/signal)"
            assert "exception" not in res, f"[{case_id}] uncaught {res['exception']}\n{res.get('traceback', '')}"
            code, out, err = res["code"], res["out"], res["err"]
            assert code in (0, 2), f"[{case_id}] exit {code}\n{err[-1500:]}"
            assert "Traceback" not in err, f"[{case_id}] traceback:\n{err[-1500:]}"
            if code == 2:
                try:
                    error_paragraph(command, err)
                except AssertionError as exc:
                    raise AssertionError(f"[{case_id}] {exc}") from None
            else:
                path = Path(argv[1] if command == "synth" else argv[argv.index("-o") + 1])
                try:
                    check_output(OUTPUT_KIND[command], path, out)
                except Exception as exc:  # noqa: BLE001
                    raise AssertionError(f"[{case_id}] exit 0 but {path.name} does not read back: "
                                         f"{type(exc).__name__}: {exc}") from None
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
            corpus_intact(corpus, case_id, tmp)

    check._hypothesis_internal_add_digest = command.encode()  # derandomized, but other draws per command
    settings(max_examples=20, deadline=None, derandomize=True, database=None,
             phases=(Phase.explicit, Phase.generate), suppress_health_check=list(HealthCheck))(
        given(data=st.data())(check))()



def test_the_defect_step_takes_each_objects_averaging_radius_as_nemo_run_does(tmp_path):
    """An order table of three objects, one without a radius (a cap too small for directors): the
    others keep theirs, as nemo.pipeline passes them per object (the step command had estimated
    every object's radius from S, so the workflow's defects differed from nemo run's)."""
    from nemo.cli.defects import _averaging_radius
    from nemo.order import no_order
    from nemo.tables import write_table

    path = tmp_path / "order.parquet"
    table = no_order(np.zeros((3, 3)))
    write_table(table, path, command="order",
                parameters={"objects": [{"radius": 23.5}, {"radius": None}, {"radius": 18.0}]})
    assert _averaging_radius(str(path)) == [23.5, None, 18.0]
    write_table(table, path, command="order", parameters={"radius": 12.0})
    assert _averaging_radius(str(path)) == 12.0
    write_table(table, path, command="order", parameters={"radius": None})
    assert _averaging_radius(str(path)) is None
