# Parse-time part of the benchmark protocol (workflow/rules/benchmark.smk, which includes this
# file): the cases and shapes of the config's `benchmark:` section, the datasets they are
# analysed as, and the helpers of the benchmark rules.

import json

from nemo.benchmark import expand_cases, expand_shapes

BENCHMARK = config["benchmark"]
BRES = f"{RESULTS}/benchmark"
BCASES = expand_cases(BENCHMARK)
BSHAPES = expand_shapes(BENCHMARK)
BVOLUMES = {c["volume"]: c["synth"] for c in BCASES.values() if c["volume"]}
_BMATCH = BENCHMARK.get("match_radius")
_BORDERED = BENCHMARK.get("ordered_distance")
BSCORE_OPTS = (f" --match-radius {_BMATCH}" if _BMATCH else "") + (
    f" --ordered-distance {_BORDERED}" if _BORDERED else ""
)


def _case_dataset(cid, case):
    """The dataset a case is analysed as: a configured one, or `bench.CASE` on its volume."""
    if case["dataset"] is not None:
        if case["dataset"] not in DATA:
            config_error(
                f"benchmark.cases.{cid}.dataset",
                f"'{case['dataset']}' is not under datasets (defined: {', '.join(DATA)})",
            )
        if not DATA[case["dataset"]]["synthetic"]:
            config_error(
                f"benchmark.cases.{cid}.dataset",
                "needs a synthetic dataset (its truth.json)",
            )
        return case["dataset"]
    name = f"bench.{cid}"
    path = f"{BRES}/volumes/{case['volume']}.tif"
    try:
        overrides = nconfig.validate(
            {"datasets": {name: {"path": path, **case["run"]}}}
        )["datasets"][name]
        SECTIONS[name] = nconfig.analysis(
            {**config, "datasets": {name: overrides}}, name
        )
    except NemoError as exc:
        _fail(f"benchmark case '{cid}' (run: {case['run']}): {exc}")
    DATA[name] = {
        "path": path,
        "spacing": None,
        "mask": None,
        "synthetic": None,
        "seg": 0,
        "t": [0],
        "c": [0],
        "stack_mb": None,
    }
    return name


BCASE_DATA = {cid: _case_dataset(cid, case) for cid, case in BCASES.items()}


def _scored_frame(name):
    """(t, c, layer) scored for a dataset: its first frame and layer."""
    frames = layer_frames(name)
    if not frames:
        _fail(f"benchmark: dataset '{name}' has no layer to score")
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


def bench_score_inputs(wc):
    name = BCASE_DATA[wc.case]
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


def bench_stage_files():
    files = [f"{BRES}/benchmarks/cases/synth/{v}.tsv" for v in BVOLUMES]
    files += [
        f"{BRES}/benchmarks/shapes/{k}/{s}.tsv"
        for s in BSHAPES
        for k in ("mesh", "score")
    ]
    return files


def bench_file(name):
    """A file of the benchmark protocol: ``results/benchmark/NAME``."""
    return f"{BRES}/{name}"


def bench_case_json(wc):
    """The case's description for `nemo.benchmark score --case` (JSON without single quotes)."""
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
    case = {**{k: BCASES[wc.case][k] for k in keys}, "dataset": BCASE_DATA[wc.case]}
    return json.dumps(case).replace("'", "")


def bench_shape_spec(wc):
    return json.dumps(
        {
            **{k: v for k, v in BSHAPES[wc.shape].items() if k != "mesh"},
            "name": wc.shape,
        }
    )


def bench_shape_mesh_opts(wc, input):
    with open(input.truth) as f:
        threshold = json.load(f)["threshold"]
    keep = "all" if BSHAPES[wc.shape]["kind"] == "shells" else "largest"
    return cli_opts(
        {
            "threshold": threshold,
            "keep": keep,
            "split": "none",
            **BSHAPES[wc.shape]["mesh"],
        }
    )
