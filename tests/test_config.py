"""The one parameter schema (nemo.config): validation, defaults, per-dataset sections, surfaces."""

from __future__ import annotations

import copy
import math

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

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
    assert cfg["mesh"]["split"] == "auto" and cfg["mesh"]["step"] is None  # step: from the stack size
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
    assert config.section("order", {"radius": 30}) == {"radius": 30, "targets": "all", "weights": "none"}
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
    assert v["mesh"]["split"] == "auto" and v["curvature"] is not None and v["layers"]
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


# ============================================================================ property-based (Hypothesis)
#
# Random mappings and values for every section: nemo.config.validate either accepts them or
# raises NemoError (never another exception), and whatever it accepts has the documented types:
# it passes the schema with strict JSON types (an integer is an int, not 1.0 or True; a number
# is finite -- JSON has no NaN or infinity). nemo.config.analysis and nemo.config.section on
# accepted values likewise return (strictly typed) or raise NemoError.

SCHEMA = config.schema()
#: Hypothesis warns when it prints the (large) repr of the schema strategies in a failure report.
quiet = pytest.mark.filterwarnings("ignore::hypothesis.errors.HypothesisWarning")
PROPERTY_SETTINGS = settings(max_examples=200, deadline=None, derandomize=True, database=None,
                             suppress_health_check=list(HealthCheck))


def _strict_validator(ref: str | None = None):
    import jsonschema
    from jsonschema import validators

    def is_integer(_, x):
        return isinstance(x, int) and not isinstance(x, bool)

    def is_number(_, x):
        return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)

    checker = jsonschema.Draft202012Validator.TYPE_CHECKER.redefine_many({"integer": is_integer,
                                                                          "number": is_number})
    strict = validators.extend(jsonschema.Draft202012Validator, type_checker=checker)
    node = SCHEMA if ref is None else {"$ref": f"#/$defs/{ref}", "$defs": SCHEMA["$defs"]}
    return strict(node)


STRICT = _strict_validator()


def assert_documented_types(instance, ref: str | None = None, what: str = "config") -> None:
    validator = STRICT if ref is None else _strict_validator(ref)
    problems = [f"{'.'.join(map(str, e.absolute_path)) or '(top)'}: {e.message}"
                for e in validator.iter_errors(instance)]
    assert not problems, f"{what} was accepted but does not have the documented types:\n  " + "\n  ".join(problems)


def _deref(node):
    while isinstance(node, dict) and "$ref" in node:
        node = {**SCHEMA["$defs"][node["$ref"].rsplit("/", 1)[-1]], **{k: v for k, v in node.items() if k != "$ref"}}
    return node


#: Values that are wrong almost everywhere, and the YAML spellings of odd numbers.
HOSTILE = st.one_of(
    st.none(), st.booleans(), st.integers(-(2**70), 2**70), st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0, -1, -0.0, 1e308, -1e308, 1e-308, 4294967296, 1.0, 2.0, True, "", "15", "1e3", "nan",
                     "yen", "all", "inner", "none", "centre", [], {}, [0, 5], [1, 2, 3], {"range": [0, 5]}]),
    st.text(max_size=6),
)
KEYS = st.one_of(st.text(max_size=8), st.integers(-3, 3), st.none(), st.booleans(), st.floats(allow_nan=False))


def from_schema(node, depth: int = 0):
    """Values of a schema node: mostly of the right shape, often of the wrong type or out of
    range (1.0 for an integer, NaN or 1e308 for a length, an unknown key), sometimes hostile."""
    node = _deref(node)
    options = [HOSTILE]
    if "enum" in node:
        options.append(st.sampled_from(node["enum"]))
    if "const" in node:
        options.append(st.just(node["const"]))
    for branch in node.get("oneOf", []) + node.get("anyOf", []):
        options.append(from_schema(branch, depth + 1))
    types = node.get("type", [])
    types = [types] if isinstance(types, str) else types
    for t in types:
        if t == "number":
            options += [st.floats(allow_nan=True, allow_infinity=True), st.integers(-5, 10**6),
                        st.sampled_from([0, 0.5, 3, 1e308, float("nan"), float("inf"), -float("inf")])]
        elif t == "integer":
            options += [st.integers(-5, 2**33), st.sampled_from([1.0, 2.0, 0.0, True, 10**30])]
        elif t == "string":
            options.append(st.text(max_size=8))
        elif t == "boolean":
            options.append(st.booleans())
        elif t == "null":
            options.append(st.none())
        elif t == "array" and depth < 4:
            items = node.get("items")
            options.append(st.lists(from_schema(items, depth + 1) if items else HOSTILE, max_size=4))
        elif t == "object" and depth < 4:
            options.append(objects(node, depth))
    if not types and "properties" in node and depth < 4:
        options.append(objects(node, depth))
    typed = options[1:]
    return st.one_of(*typed, *typed, HOSTILE) if typed else HOSTILE  # mostly well-shaped: deeper checks


def objects(node, depth: int = 0):
    node = _deref(node)
    props = node.get("properties", {})
    known = st.fixed_dictionaries({}, optional={k: from_schema(v, depth + 1) for k, v in props.items()})
    extra = node.get("additionalProperties")
    if isinstance(extra, dict):
        pattern = _deref(node.get("propertyNames", {})).get("pattern")
        names = st.from_regex(pattern, fullmatch=True).filter(lambda s: len(s) < 12) if pattern else st.text(max_size=8)
        enum = _deref(node.get("propertyNames", {})).get("enum")
        if enum:
            names = st.sampled_from(enum)
        more = st.dictionaries(st.one_of(names, KEYS), from_schema(extra, depth + 1), max_size=2)
    else:
        more = st.dictionaries(KEYS, HOSTILE, max_size=1)  # unknown keys
    return st.builds(lambda a, b: {**b, **a}, known, st.one_of(st.just({}), more))


TOP_LEVEL = sorted(SCHEMA["properties"])


def _validate_or_refuse(cfg):
    """validate(cfg): the checked config, or None when refused with NemoError."""
    before = repr(cfg)
    try:
        out = config.validate(cfg)
    except NemoError:
        return None
    finally:
        assert repr(cfg) == before, "validate changed its input"
    return out


def _analysis_or_refuse(cfg, dataset=None):
    try:
        return config.analysis(cfg, dataset)
    except NemoError:
        return None


def _check_analysis(a: dict, where: str) -> None:
    for name in config.ANALYSIS_SECTIONS:
        if a.get(name) is not None:
            assert_documented_types(a[name], name, f"analysis({where})['{name}']")


@quiet
@pytest.mark.parametrize("key", TOP_LEVEL)
def test_random_values_of_a_section_validate_or_raise_nemo_error(key):
    def check(value):
        cfg = _validate_or_refuse({key: value})
        if cfg is None:
            return
        assert_documented_types(cfg, what=f"{{{key!r}: {value!r}}}")
        a = _analysis_or_refuse(cfg)
        if a is not None:
            _check_analysis(a, "top level")
        for name in cfg.get("datasets") or {}:
            a = _analysis_or_refuse(cfg, name)
            if a is not None:
                _check_analysis(a, name)

    check._hypothesis_internal_add_digest = key.encode()  # derandomized, but other draws per key
    PROPERTY_SETTINGS(given(value=from_schema(SCHEMA["properties"][key]))(check))()


@quiet
@PROPERTY_SETTINGS
@given(cfg=st.one_of(objects(SCHEMA), st.dictionaries(KEYS, HOSTILE, max_size=3)))
def test_random_whole_configs_validate_or_raise_nemo_error(cfg):
    out = _validate_or_refuse(cfg)
    if out is not None:
        assert_documented_types(out, what=repr(cfg)[:300])
        a = _analysis_or_refuse(out)
        if a is not None:
            _check_analysis(a, "top level")


@quiet
@pytest.mark.parametrize("name", ["mesh", "measure", "curvature", "thickness", "directors", "order", "defects",
                                  "tracking", "layer"])
def test_section_merges_random_params_or_raises_nemo_error(name):
    node = _deref({"$ref": f"#/$defs/{name}"})
    keys = st.one_of(st.sampled_from(sorted(node.get("properties", {"x": None}))), st.text(max_size=5))

    def check(params):
        try:
            merged = config.section(name, copy.deepcopy(params))
        except NemoError:
            return
        assert_documented_types(merged, name, f"section({name!r}, {params!r})")

    check._hypothesis_internal_add_digest = name.encode()
    PROPERTY_SETTINGS(given(params=st.one_of(objects(node), st.dictionaries(keys, HOSTILE, max_size=3)))(check))()


@quiet
@PROPERTY_SETTINGS
@given(data=st.one_of(
    st.text(alphabet=st.sampled_from(list("abcmeshorderadius:[]{}-,.#!&*|>'\"0123456789 \n\t\\%@`")),
            max_size=60).map(str.encode),
    st.builds(lambda d: yaml.safe_dump(d).encode(), objects(SCHEMA)),
    st.binary(max_size=40),
))
def test_random_config_files_load_or_raise_nemo_error(tmp_path_factory, data):
    path = tmp_path_factory.mktemp("cfg") / "config.yaml"
    path.write_bytes(data)
    try:
        cfg = config.load(path)
    except NemoError:
        return
    assert_documented_types(cfg, what=f"the file {data!r}")


@pytest.mark.parametrize("layer, out", [
    ({"surface": "inner", "range": [0, 5]}, True),         # the default layer on a droplet: the background
    ({"surface": "outer", "range": [2, 4]}, True),
    ({"surface": "inner", "range": [-1, 1]}, False),       # a membrane layer straddling the outline
    ({"surface": "inner", "range": [0, 5], "inward": True}, False),
    ({"surface": "whole", "range": [0, 5]}, False),        # the outline by choice (split: none)
])
def test_a_layer_reaches_out_of_an_object_of_one_wall_when_its_range_lies_mostly_outward(layer, out):
    assert config.reaches_out_of_one_wall(layer) is out


def test_psf_auto_is_a_psf_and_other_words_are_named():
    """datasets.NAME.psf: auto (alone or for one channel) and none are valid, auto the default (a frame
    without a dataset takes it too) and null kept as given (none); another word is refused naming the
    key and the forms a PSF takes."""
    from nemo import config
    from nemo.pipeline import frame_setup
    from nemo.psf import channel_psf

    for psf in ("auto", [None, "auto"], "none", ["none", [2, 1, 1]], None):
        assert config.validate({"datasets": {"a": {"path": "a.tif", "psf": psf}}})["datasets"]["a"]["psf"] == psf
    cfg = config.validate({"datasets": {"a": {"path": "a.tif"}, "b": {"path": "b.tif", "psf": None}}})
    assert cfg["datasets"]["a"]["psf"] == "auto" == config.dataset_default("psf")
    assert frame_setup(cfg, None, "x.tif", None)["psf"] == "auto"  # an image given without a dataset
    assert frame_setup(cfg, "b", None, None)["psf"] is None and frame_setup(cfg, "b", None, None, psf="none")["psf"] is None
    assert channel_psf(["none", "auto"], 0) is None and channel_psf(["none", "auto"], 1) == "auto"
    with pytest.raises(NemoError, match=r"'datasets.a.psf': \"automatic\" is not a PSF.*auto \(its z blur estimated"):
        config.validate({"datasets": {"a": {"path": "a.tif", "psf": "automatic"}}})


def test_edge_profile_with_a_psf_is_refused_naming_the_dataset():
    """``mesh.edge: profile`` (global or the dataset's own) and a dataset's ``psf``: one error naming
    the key; either alone, or the psf on another dataset, is fine."""
    from nemo import config

    for cfg in ({"mesh": {"edge": "profile"}, "datasets": {"a": {"path": "a.tif", "psf": [2, 1, 1]}}},
                {"datasets": {"a": {"path": "a.tif", "psf": [2, 1, 1], "mesh": {"edge": "profile"}}}}):
        with pytest.raises(NemoError, match=r"config key 'datasets.a.psf': mesh.edge: profile and a psf"):
            config.validate(cfg)
    ok = config.validate({"mesh": {"edge": "profile"},
                          "datasets": {"a": {"path": "a.tif"}, "b": {"path": "b.tif", "psf": [2, 1, 1],
                                                                     "mesh": {"edge": "half"}},
                                       "c": {"path": "c.tif", "psf": ["none", "auto"]}}})
    assert ok["mesh"]["edge"] == "profile" and ok["datasets"]["a"]["psf"] == "auto"  # auto: meshed undeconvolved
