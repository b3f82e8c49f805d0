"""Bad input on the command line: exit status 2, one clear line, no traceback."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import tifffile

from nemo.errors import NemoWarning
from nemo.io import write_hyperstack
from nemo.mesh import make_mesh, save_mesh


def _ball(shape=(20, 24, 24), radius=6.0, amp=200):
    z, y, x = np.ogrid[: shape[0], : shape[1], : shape[2]]
    r = np.sqrt((z - shape[0] / 2) ** 2 + (y - shape[1] / 2) ** 2 + (x - shape[2] / 2) ** 2)
    return (amp * (r < radius)).astype(np.uint8)


@pytest.fixture
def hyperstack(tmp_path):
    """2 time points x 2 channels; channel 1 of t = 1 is all dark."""
    data = np.zeros((2, 20, 2, 24, 24), np.uint8)
    data[0, :, 0] = data[0, :, 1] = data[1, :, 0] = _ball()
    path = tmp_path / "stack.tif"
    write_hyperstack(path, data, (1.0, 0.5, 0.5))
    return path


def _one_clear_line(code, out, err, *words):
    assert code == 2, (code, out, err)
    lines = [line for line in err.splitlines() if line.strip() and not line.startswith("nemo: ")]
    assert len(lines) == 1, err  # progress lines "nemo: ..." aside, exactly one error line
    assert lines[0].startswith("nemo ") and "error:" in lines[0]
    assert "Traceback" not in err and "Traceback" not in out
    for word in words:
        assert word.lower() in lines[0].lower(), (word, lines[0])
    return lines[0]


@pytest.mark.parametrize("command", ["info", "mesh"])
def test_missing_file(tmp_path, run_cli, command):
    args = [command, tmp_path / "nope.tif"] + (["-o", tmp_path / "m.ply"] if command == "mesh" else [])
    _one_clear_line(*run_cli(*args), "not found", "nope.tif")


@pytest.mark.parametrize("command", ["info", "mesh"])
def test_non_tiff_file(tmp_path, run_cli, command):
    (tmp_path / "table.csv").write_text("a,b\n1,2\n")
    args = [command, tmp_path / "table.csv"] + (["-o", tmp_path / "m.ply"] if command == "mesh" else [])
    _one_clear_line(*run_cli(*args), "not a readable TIFF")


@pytest.mark.parametrize("command", ["info", "mesh"])
def test_two_dimensional_image(tmp_path, run_cli, command):
    tifffile.imwrite(tmp_path / "flat.tif", np.zeros((30, 40), np.uint8))
    args = [command, tmp_path / "flat.tif"] + (["-o", tmp_path / "m.ply"] if command == "mesh" else [])
    _one_clear_line(*run_cli(*args), "2-D", "Z axis")


@pytest.mark.parametrize("option,value,words", [("--t", "2", ("t = 2", "2 time points")),
                                                ("--c", "5", ("c = 5", "2 channels")),
                                                ("--t", "-1", ("out of range",))])
def test_frame_out_of_range(hyperstack, tmp_path, run_cli, option, value, words):
    _one_clear_line(*run_cli("mesh", hyperstack, "-o", tmp_path / "m.ply", option, value), *words)


def test_all_dark_stack(hyperstack, tmp_path, run_cli):
    line = _one_clear_line(*run_cli("mesh", hyperstack, "-o", tmp_path / "m.ply", "--t", "1", "--c", "1"),
                           "constant")
    assert "time point/channel" in line and "--mask" in line  # suggests the fix (flags on the CLI)
    assert not (tmp_path / "m.ply").exists()


def test_threshold_selecting_nothing_or_everything(hyperstack, tmp_path, run_cli):
    _one_clear_line(*run_cli("mesh", hyperstack, "-o", tmp_path / "m.ply", "--threshold", "250"),
                    "selects no voxel", "lower --threshold")
    _one_clear_line(*run_cli("mesh", hyperstack, "-o", tmp_path / "m.ply", "--threshold", "-5"),
                    "selects every voxel")


def test_mask_of_wrong_shape(hyperstack, tmp_path, run_cli):
    write_hyperstack(tmp_path / "mask.tif", np.ones((20, 24, 23), np.uint8), (1, 1, 1), axes="ZYX")
    _one_clear_line(*run_cli("mesh", hyperstack, "-o", tmp_path / "m.ply", "--mask", tmp_path / "mask.tif"),
                    "mask", "shape", "(20, 24, 23)", "(20, 24, 24)")


def test_empty_mask(hyperstack, tmp_path, run_cli):
    write_hyperstack(tmp_path / "mask.tif", np.zeros((20, 24, 24), np.uint8), (1, 1, 1), axes="ZYX")
    _one_clear_line(*run_cli("mesh", hyperstack, "-o", tmp_path / "m.ply", "--mask", tmp_path / "mask.tif"),
                    "is empty: no voxel is nonzero")


def test_good_mask_is_used(hyperstack, tmp_path, run_cli):
    """The mask's object is meshed, not the image's: the mask's ball (radius 8 voxels) is the
    image's ball (radius 6 voxels) scaled by 4/3 about the same centre, so the fitted sphere's
    radius must scale by 4/3 (measured: 5.619 µm with the mask / 4.225 µm without = 1.330)."""
    import json

    mask = _ball(radius=8.0) > 0
    write_hyperstack(tmp_path / "mask.tif", mask.astype(np.uint8), (1, 1, 1), axes="ZYX")
    radii = {}
    for name, extra in (("image", []), ("mask", ["--mask", tmp_path / "mask.tif"])):
        code, _, err = run_cli("mesh", hyperstack, "-o", tmp_path / f"{name}.ply", *extra,
                                 "--fit-sphere", "--step", "1", "--split", "none")
        assert code == 0, err
        sphere = json.loads((tmp_path / f"{name}.sphere.json").read_text())["whole"]
        np.testing.assert_allclose(sphere["centre"], (6.0, 6.0, 10.0), atol=0.01)  # both balls' centre
        radii[name] = sphere["radius"]
    # the ratio (1.330 measured) within 0.02 of 4/3: the same mesh twice (ratio 1) fails
    assert radii["mask"] / radii["image"] == pytest.approx(4 / 3, abs=0.02), radii
    # and the values themselves, ±0.1 µm (5.62 and 4.22 measured: 1.4 µm apart)
    assert radii["mask"] == pytest.approx(5.62, abs=0.1) and radii["image"] == pytest.approx(4.22, abs=0.1)


def test_bad_output_suffix_and_options(hyperstack, tmp_path, run_cli):
    _one_clear_line(*run_cli("mesh", hyperstack, "-o", tmp_path / "m.vtk"), ".ply or .obj")
    _one_clear_line(*run_cli("mesh", hyperstack, "-o", tmp_path / "m.ply", "--split", "axis"), "--axis")
    _one_clear_line(*run_cli("mesh", hyperstack, "-o", tmp_path / "m.ply", "--spacing", "1", "0", "1"), "spacing")
    # the ball is a single wall: nothing to split off
    _one_clear_line(*run_cli("mesh", hyperstack, "-o", tmp_path / "m.ply", "--split", "centre"), "single wall")


def test_mesh_of_a_single_wall_at_the_default_split(hyperstack, tmp_path, run_cli):
    """split auto (the default): the ball is one wall, its inner and outer files are the whole."""
    from nemo.mesh import load_mesh

    code, out, err = run_cli("mesh", hyperstack, "-o", tmp_path / "m.ply")
    assert code == 0 and "one wall" in err, err
    whole = load_mesh(tmp_path / "m.ply")
    for name in ("inner", "outer"):
        np.testing.assert_array_equal(load_mesh(tmp_path / f"m.{name}.ply").vertices, whole.vertices)
    assert whole.metadata["nemo_params"]["walls"] == 1


@pytest.mark.parametrize("bad_value", [["--threshold", "triangle"], ["--step", "0"], ["--smooth", "-1"],
                                       ["--keep", "biggest"]])
def test_argparse_rejects_bad_values(hyperstack, tmp_path, run_cli, bad_value):
    with pytest.raises(SystemExit) as exc:
        run_cli("mesh", hyperstack, "-o", tmp_path / "m.ply", *bad_value)
    assert exc.value.code == 2


def test_corrupt_ply_given_to_a_command(hyperstack, tmp_path, run_cli):
    ico = __import__("trimesh").creation.icosphere(subdivisions=2, radius=5.0)
    save_mesh(make_mesh(ico.vertices + 6.0, ico.faces), tmp_path / "good.ply")
    raw = (tmp_path / "good.ply").read_bytes()
    (tmp_path / "bad.ply").write_bytes(raw[: len(raw) * 2 // 3])
    line = _one_clear_line(*run_cli("peel", hyperstack, tmp_path / "bad.ply", "-o", tmp_path / "l.parquet",
                                    "--range", "0", "2"), "bad.ply")
    assert "corrupt" in line or "truncated" in line
    (tmp_path / "text.ply").write_text("solid nothing\n")
    _one_clear_line(*run_cli("peel", hyperstack, tmp_path / "text.ply", "-o", tmp_path / "l.parquet",
                             "--range", "0", "2"), "not a PLY")


def test_info_on_a_good_file_still_works(hyperstack, run_cli):
    code, out, err = run_cli("info", hyperstack, "--json")
    assert code == 0, err
    import json

    d = json.loads(out)
    assert d["shape"] == {"T": 2, "C": 2, "Z": 20, "Y": 24, "X": 24}
    assert d["spacing"] == [1.0, 0.5, 0.5] and d["unit"] == "um"


def _warn_from(module: str, message: str, category: type[Warning]) -> None:
    """Raise a warning as if from code in ``module`` (the filters match the caller's ``__name__``)."""
    warnings.warn_explicit(message, category, module.replace(".", "/") + ".py", 1, module=module)


def _warning_command(monkeypatch):
    """``nemo info`` replaced by a command that warns from a dependency, from NEMO and as a NemoWarning."""
    import nemo.cli.info

    def run(args):
        _warn_from("pydantic.fields", "dependency deprecation", DeprecationWarning)
        _warn_from("nemo.fake", "numbers from nemo code", RuntimeWarning)
        _warn_from("somewhere", "a nemo warning", NemoWarning)
        return 0

    monkeypatch.setattr(nemo.cli.info, "run", run)


def test_only_nemo_warnings_are_printed(monkeypatch, tmp_path, run_cli):
    _warning_command(monkeypatch)
    monkeypatch.delenv("NEMO_DEBUG", raising=False)
    monkeypatch.setattr("sys.warnoptions", [])
    code, _, err = run_cli("info", tmp_path)
    assert code == 0, err
    assert "nemo: warning: a nemo warning" in err
    assert "nemo: warning: numbers from nemo code" in err
    assert "dependency deprecation" not in err
    # asked for: NEMO_DEBUG or python -W / PYTHONWARNINGS (sys.warnoptions) show them
    monkeypatch.setenv("NEMO_DEBUG", "1")
    assert "nemo: warning: dependency deprecation" in run_cli("info", tmp_path)[2]
    monkeypatch.delenv("NEMO_DEBUG")
    monkeypatch.setattr("sys.warnoptions", ["default"])
    with warnings.catch_warnings():
        warnings.simplefilter("default")  # what python -W default installed at start-up
        err = run_cli("info", tmp_path)[2]
    assert "nemo: warning: dependency deprecation" in err and "nemo: warning: a nemo warning" in err
