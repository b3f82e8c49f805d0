"""The one parameter schema (nemo.config): validation, defaults, per-dataset sections, surfaces."""

from __future__ import annotations

import pytest
import yaml

from nemo import config
from nemo.errors import NemoError

ROOT = config.SCHEMA_PATH.parents[2]


def test_workflow_schema_is_the_package_schema():
    linked = ROOT / "workflow" / "schemas" / "config.schema.yaml"
    assert linked.resolve() == config.SCHEMA_PATH.resolve()


def test_defaults_fill_every_analysis_section():
    cfg = config.validate(None)
    assert cfg["layers"] == {"fibres": {"range": [0, 5], "surface": None, "channels": "all", "reduce": "mean",
                                        "samples": 11, "interp": "linear", "inward": False, "shift": 0}}
    assert cfg["mesh"]["split"] == "centre" and cfg["mesh"]["step"] is None  # step: from the stack size
    for key in ("patch_radius", "pixel", "n_patches"):
        assert cfg["directors"][key] is None  # derived from the mesh
    assert cfg["order"]["radius"] is None and cfg["curvature"]["radius"] is None
    assert cfg["defects"]["refine_directors"] == 0.5 and cfg["tracking"]["max_distance"] is None


def test_every_problem_is_listed_with_its_dotted_key():
    with pytest.raises(NemoError) as exc:
        config.validate({"mesh": {"stp": 1}, "order": {"radius": -1}, "directors": {"seed": -1},
                         "layers": {"a": {"range": [0]}}})
    text = str(exc.value)
    for key in ("'mesh'", "'order.radius'", "'directors.seed'", "'layers.a.range'"):
        assert key in text, text
    assert "stp" in text


def test_section_merges_over_defaults_and_names_unknown_keys():
    assert config.section("order", {"radius": 30}) == {"radius": 30, "targets": "all"}
    assert config.section("order", {"radius": None})["radius"] is None  # None = the default
    with pytest.raises(NemoError, match="'order.radus'"):
        config.section("order", {"radus": 3})
    with pytest.raises(NemoError, match="'defects.refine_directors'"):
        config.section("defects", {"refine_directors": 1.5})


def test_null_sections_switch_steps_off_and_single_walls_need_no_thickness():
    cfg = config.validate({"mesh": {"split": "none"}, "layers": {}, "curvature": None})
    a = config.analysis(cfg)
    assert a["thickness"] is None and a["curvature"] is None and a["surfaces"] == ["whole"]
    cfg = config.validate({"mesh": {"split": "none"}})  # the default layer then lies on the whole mesh
    assert config.analysis(cfg)["layers"]["fibres"]["surface"] == "whole"
    cfg = config.validate({"thickness": None})
    assert config.analysis(cfg)["thickness"] is None


@pytest.mark.parametrize("bad, key", [
    ({"mesh": {"split": "none"}, "layers": {"a": {"range": [0, 1], "surface": "inner"}}}, "mesh.split"),
    ({"mesh": {"split": "none"}, "thickness": {"from": "inner"}}, "mesh.split"),
    ({"layers": {"a": {"range": [2, 1]}}}, "layers.a.range"),
    ({"layers": {"a": {"range": [0, 1], "shift": 0.2}}, "thickness": None}, "layers.a.shift"),
    ({"alignment": [["fibres", "other"]]}, "alignment.0"),
    ({"mesh": {"split": "axis"}}, "mesh.axis"),
])
def test_inconsistent_sections_are_refused(bad, key):
    with pytest.raises(NemoError, match=key.replace(".", r"\.")):
        config.analysis(config.validate(bad))


def test_per_dataset_overrides_merge_key_by_key():
    cfg = config.validate({
        "order": {"radius": 25}, "directors": {"patch_radius": 10, "seed": 3},
        "datasets": {"vesicle": {"path": "v.tif"},
                     "drop": {"path": "d.tif", "mesh": {"split": "none"}, "layers": {}, "curvature": None,
                              "directors": {"patch_radius": 4}}}})
    assert "mesh" not in cfg["datasets"]["drop"] or cfg["datasets"]["drop"]["mesh"] == {"split": "none"}
    v, d = config.analysis(cfg, "vesicle"), config.analysis(cfg, "drop")
    assert v["mesh"]["split"] == "centre" and v["curvature"] is not None and v["layers"]
    assert d["mesh"]["split"] == "none" and d["mesh"]["threshold"] == "yen"  # merged, not replaced
    assert d["curvature"] is None and d["layers"] == {} and d["thickness"] is None
    assert d["directors"]["patch_radius"] == 4 and d["directors"]["seed"] == 3
    with pytest.raises(NemoError, match="nope"):
        config.analysis(cfg, "nope")


def test_bundled_configs_validate(tmp_path):
    for path in sorted((ROOT / "config").glob("*.yaml")):
        cfg = config.load(path)
        for name in cfg["datasets"]:
            config.analysis(cfg, name)
    bad = tmp_path / "bad.yaml"
    bad.write_text("order: [unclosed\n")
    with pytest.raises(NemoError, match="not valid YAML"):
        config.load(bad)
    bad.write_text("- a list\n")
    with pytest.raises(NemoError, match="mapping"):
        config.load(bad)
    with pytest.raises(NemoError, match="not found"):
        config.load(tmp_path / "missing.yaml")


def test_every_section_key_is_an_option_of_its_command():
    """The workflow passes each section as --key value: every key must be a flag of its command."""
    from nemo.cli import build_parser

    commands = {"mesh": "mesh", "curvature": "curvature", "directors": "directors", "order": "order",
                "defects": "defects", "tracking": "track"}
    for section, command in commands.items():
        sub = build_parser(command)._subparsers._group_actions[0].choices[command]
        flags = {opt for action in sub._actions for opt in action.option_strings}
        for key in config.section_defaults(section):
            flag = "--" + key.replace("_", "-")
            if section == "defects" and key == "curvature_correction":
                flag = "--no-curvature-correction"
            assert flag in flags, (section, key)
    peel = build_parser("peel")._subparsers._group_actions[0].choices["peel"]
    flags = {opt for action in peel._actions for opt in action.option_strings}
    assert {"--range", "--samples", "--reduce", "--interp", "--inward", "--shift-fraction"} <= flags
    assert yaml.safe_load(config.SCHEMA_PATH.read_text())["$defs"]["thickness"]["properties"].keys() >= {
        "direction", "max_distance"}


def test_keys_of_the_former_run_config_say_what_replaced_them():
    with pytest.raises(NemoError) as exc:
        config.validate({"peel": {"range": [0, 5]}, "mesh": {"step_um": 2.0}})
    assert "'peel' is now layers.NAME" in str(exc.value) and "'mesh.step_um' is now mesh.step" in str(exc.value)
