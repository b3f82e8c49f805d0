# Parse-time part of the validation protocol (workflow/rules/validation.smk, which includes this
# file): the cases and shapes of the config's `validation:` section, the datasets they are
# analysed as, and the helpers of the validation rules.

import json

from nemo.validation import expand_cases, expand_shapes

VALIDATION = config["validation"]
VRES = f"{RESULTS}/validation"
VCASES = expand_cases(VALIDATION)
VSHAPES = expand_shapes(VALIDATION)
VVOLUMES = {c["volume"]: c["synth"] for c in VCASES.values() if c["volume"]}
_VMATCH = VALIDATION.get("match_radius")
_VORDERED = VALIDATION.get("ordered_distance")
VSCORE_OPTS = (f" --match-radius {_VMATCH}" if _VMATCH else "") + (
    f" --ordered-distance {_VORDERED}" if _VORDERED else ""
)


def _case_dataset(cid, case):
    """The dataset a case is analysed as: a configured one, or `validation.CASE` on its volume."""
    if case["dataset"] is not None:
        if case["dataset"] not in DATA:
            config_error(
                f"validation.cases.{cid}.dataset",
                f"'{case['dataset']}' is not under datasets (defined: {', '.join(DATA)})",
            )
        if not DATA[case["dataset"]]["synthetic"]:
            config_error(
                f"validation.cases.{cid}.dataset",
                "needs a synthetic dataset (its truth.json)",
            )
        return case["dataset"]
    name = f"validation.{cid}"
    path = f"{VRES}/volumes/{case['volume']}.tif"
    try:
        overrides = nconfig.validate(
            {"datasets": {name: {"path": path, **case["run"]}}}
        )["datasets"][name]
        SECTIONS[name] = nconfig.analysis(
            {**config, "datasets": {name: overrides}}, name
        )
    except NemoError as exc:
        _fail(f"validation case '{cid}' (run: {case['run']}): {exc}")
    # every dataset key with its default (whatever common.smk reads); one frame, one channel
    DATA[name] = {**overrides, "seg": 0, "t": [0], "c": [0], "stack_mb": None}
    return name


VCASE_DATA = {cid: _case_dataset(cid, case) for cid, case in VCASES.items()}

# common.smk sorted the configured datasets into the mesh rules (and layer kinds) before the
# cases were added: sort the cases' datasets too (in place: the rules below read these)
SPLIT_MESH[:] = [name for name in DATA if sec(name, "mesh")["split"] != "none"]
SINGLE_MESH[:] = [name for name in DATA if name not in SPLIT_MESH]
for _names_now, _names_all in zip(
    (IMPORTED_LAYERS, MEASURED_LAYERS), _split_layer_names()
):
    _names_now |= _names_all


def _scored_frame(name):
    """(t, c, layer) scored for a dataset: its first frame and layer."""
    frames = layer_frames(name)
    if not frames:
        _fail(f"validation: dataset '{name}' has no layer to score")
    return frames[0]


def _stage_files(name):
    """Snakemake benchmark files of the per-frame rules of the scored frame of a dataset."""
    t, c, layer = _scored_frame(name)
    b = BENCH.format(dataset=name)
    s, seg = SECTIONS[name], DATA[name]["seg"]
    out = [f"{b}/mesh/t{t}_c{seg}.tsv"] + [
        f"{b}/{rule}/t{t}_c{c}_{layer}.tsv"
        for rule in ("peel", "directors", "order", "defects")
    ]
    out += [
        f"{b}/measure/t{t}_c{seg}_{x}.tsv"
        for x in (s["measure"]["surfaces"] or s["surfaces"])
    ]
    if s["curvature"] is not None:
        out += [f"{b}/curvature/t{t}_c{seg}_{x}.tsv" for x in s["surfaces"]]
    if s["thickness"] is not None:
        out.append(f"{b}/thickness/t{t}_c{seg}.tsv")
    return out


def validation_score_inputs(wc):
    name = VCASE_DATA[wc.case]
    t, c, layer = _scored_frame(name)
    frame = layout.frame_dir(RESULTS, name, t, c)
    seg = layout.frame_dir(RESULTS, name, t, DATA[name]["seg"])
    inputs = {"truth": truth_path(DATA[name]["path"]), "stages": _stage_files(name)}
    for kind in ("defects", "directors", "order"):
        inputs[kind] = f"{frame}/{layout.layer_file(kind, layer)}"
    if SECTIONS[name]["curvature"] is not None:
        inputs["curvature"] = (
            f"{seg}/{layout.curvature_file(SECTIONS[name]['layers'][layer]['surface'])}"
        )
    return inputs


def validation_stage_files():
    """Snakemake benchmark files of the protocol's own jobs (volumes, shapes)."""
    files = [f"{VRES}/benchmarks/cases/synth/{v}.tsv" for v in VVOLUMES]
    files += [
        f"{VRES}/benchmarks/shapes/{k}/{s}.tsv"
        for s in VSHAPES
        for k in ("mesh", "score")
    ]
    return files


def validation_file(name):
    """A file of the validation protocol: ``results/validation/NAME``."""
    return f"{VRES}/{name}"


def validation_case_json(wc):
    """The case's description for `nemo validate score --case` (JSON without single quotes)."""
    keys = (
        "case",
        "sweep",
        "parameter",
        "value",
        "value_label",
        "rotation",
        "synth",
        "run",
    )
    case = {**{k: VCASES[wc.case][k] for k in keys}, "dataset": VCASE_DATA[wc.case]}
    return json.dumps(case).replace("'", "")


def validation_shape_spec(wc):
    return json.dumps(
        {
            **{k: v for k, v in VSHAPES[wc.shape].items() if k != "mesh"},
            "name": wc.shape,
        }
    )


def validation_shape_mesh_opts(wc, input):
    with open(input.truth) as f:
        threshold = json.load(f)["threshold"]
    keep = "all" if VSHAPES[wc.shape]["kind"] == "shells" else "largest"
    return cli_opts(
        {
            "threshold": threshold,
            "keep": keep,
            "split": "none",
            **VSHAPES[wc.shape]["mesh"],
        }
    )
