# Benchmark and validation protocol (docs/benchmarks.md). Included by the Snakefile, right after
# common.smk, when the config has a `benchmark:` section (config/benchmark.yaml,
# config/benchmark-ci.yaml).
#
# Every vesicle case (nemo.benchmark.expand_cases) becomes a dataset `bench.CASE` of one frame,
# analysed by the workflow's own per-frame rules (mesh, morphology, peel, directors, order,
# defects) with the case's `run` overrides as per-dataset sections: the protocol measures what
# `snakemake` users get. Each case's defects are scored against the synthetic truth; the stage
# times are Snakemake's benchmark files of those rules. Analytic shapes (python -m
# nemo.benchmark shape) are meshed by nemo mesh and scored for curvature and thickness.
# Everything is collected by bench_aggregate into results/benchmark/summary/.

import json

from nemo.benchmark import expand_cases, expand_shapes

BENCHMARK = config["benchmark"]
BRES = RESULTS + "/benchmark"
BCASES = expand_cases(BENCHMARK)
BSHAPES = expand_shapes(BENCHMARK)
BVOLUMES = {c["volume"]: c["synth"] for c in BCASES.values() if c["volume"]}
_BMATCH = BENCHMARK.get("match_radius")
_BORDERED = BENCHMARK.get("ordered_distance")
_BSCORE_OPTS = ((f" --match-radius {_BMATCH}" if _BMATCH else "")
                + (f" --ordered-distance {_BORDERED}" if _BORDERED else ""))


def _case_dataset(cid, case):
    """The dataset a case is analysed as: a configured one, or `bench.CASE` on its volume."""
    if case["dataset"] is not None:
        if case["dataset"] not in DATA:
            config_error(f"benchmark.cases.{cid}.dataset",
                         f"'{case['dataset']}' is not under datasets (defined: {', '.join(DATA)})")
        if not DATA[case["dataset"]]["synthetic"]:
            config_error(f"benchmark.cases.{cid}.dataset", "needs a synthetic dataset (its truth.json)")
        return case["dataset"]
    name = f"bench.{cid}"
    path = f"{BRES}/volumes/{case['volume']}.tif"
    try:
        overrides = nconfig.validate({"datasets": {name: {"path": path, **case["run"]}}})["datasets"][name]
        SECTIONS[name] = nconfig.analysis({**config, "datasets": {name: overrides}}, name)
    except NemoError as exc:
        _fail(f"benchmark case '{cid}' (run: {case['run']}): {exc}")
    DATA[name] = {"path": path, "spacing": None, "mask": None, "synthetic": None, "seg": 0, "t": [0], "c": [0],
                  "stack_mb": None}
    return name


BCASE_DATA = {cid: _case_dataset(cid, case) for cid, case in BCASES.items()}


wildcard_constraints:
    case="|".join(sorted(BCASES)),
    vid=r"v[0-9a-f]{10}",
    shape="|".join(sorted(BSHAPES)) or "NONE",


def _truth_of(path):
    return os.path.splitext(path)[0] + ".truth.json"


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
    out = [f"{b}/mesh/t{t}_c{seg}.tsv"] + [f"{b}/{rule}/t{t}_c{c}_{layer}.tsv"
                                          for rule in ("peel", "directors", "order", "defects")]
    out += [f"{b}/measure/t{t}_c{seg}_{x}.tsv" for x in (s["measure"]["surfaces"] or s["surfaces"])]
    if s["curvature"] is not None:
        out += [f"{b}/curvature/t{t}_c{seg}_{x}.tsv" for x in s["surfaces"]]
    if s["thickness"] is not None:
        out.append(f"{b}/thickness/t{t}_c{seg}.tsv")
    return out


def _score_inputs(wc):
    name = BCASE_DATA[wc.case]
    t, c, layer = _scored_frame(name)
    frame = layout.frame_dir(RESULTS, name, t, c)
    seg = layout.frame_dir(RESULTS, name, t, DATA[name]["seg"])
    inputs = {"truth": _truth_of(DATA[name]["path"]), "stages": _stage_files(name)}
    for kind in ("defects", "directors", "order"):
        inputs[kind] = f"{frame}/{layout.layer_file(kind, layer)}"
    if SECTIONS[name]["curvature"] is not None:
        inputs["curvature"] = f"{seg}/{layout.curvature_file(SECTIONS[name]['layers'][layer]['surface'])}"
    return inputs


rule bench_synth:
    output:
        image=BRES + "/volumes/{vid}.tif",
        truth=BRES + "/volumes/{vid}.truth.json",
    params:
        opts=lambda wc: cli_opts(BVOLUMES[wc.vid]),
    log:
        BRES + "/logs/synth/{vid}.log",
    benchmark:
        BRES + "/benchmarks/cases/synth/{vid}.tsv"
    threads: res("benchmark", "threads")
    resources:
        mem_mb=res("benchmark", "mem_mb"),
        runtime=res("benchmark", "runtime"),
    conda:
        "../envs/nemo.yaml"
    shell:
        NEMO + " synth {output.image} {params.opts} > {log} 2>&1"


rule bench_score:
    input:
        unpack(_score_inputs),
    output:
        BRES + "/cases/{case}/score.json",
    params:
        case=lambda wc: json.dumps({**{k: BCASES[wc.case][k] for k in
                                       ("case", "sweep", "parameter", "value", "value_label", "rotation",
                                        "synth", "run")}, "dataset": BCASE_DATA[wc.case]}).replace("'", ""),
        curvature=lambda wc, input: f"--curvature {shlex.quote(input.curvature)}" if "curvature" in input.keys() else "",
        opts=_BSCORE_OPTS,
    log:
        BRES + "/logs/score/{case}.log",
    threads: 1
    resources:
        mem_mb=res("benchmark", "mem_mb"),
        runtime=res("benchmark", "runtime"),
    conda:
        "../envs/nemo.yaml"
    shell:
        "python -m nemo.benchmark score --truth {input.truth:q} --defects {input.defects:q}"
        " --directors {input.directors:q} --order {input.order:q} {params.curvature}"
        " --stage-files {input.stages:q} --case '{params.case}' {params.opts} -o {output:q} > {log:q} 2>&1"


rule bench_shape:
    output:
        image=BRES + "/shapes/{shape}/volume.tif",
        truth=BRES + "/shapes/{shape}/truth.json",
    params:
        spec=lambda wc: json.dumps({**{k: v for k, v in BSHAPES[wc.shape].items() if k != "mesh"},
                                    "name": wc.shape}),
    log:
        BRES + "/logs/shape/{shape}.log",
    benchmark:
        BRES + "/benchmarks/shapes/shape/{shape}.tsv"
    threads: 1
    resources:
        mem_mb=res("benchmark", "mem_mb"),
        runtime=res("benchmark", "runtime"),
    conda:
        "../envs/nemo.yaml"
    shell:
        "python -m nemo.benchmark shape '{params.spec}' -o {output.image} --truth {output.truth} > {log} 2>&1"


rule bench_shape_mesh:
    input:
        image=BRES + "/shapes/{shape}/volume.tif",
        truth=BRES + "/shapes/{shape}/truth.json",
    output:
        BRES + "/shapes/{shape}/mesh.ply",
    params:
        opts=lambda wc, input: cli_opts({"threshold": json.load(open(input.truth))["threshold"],
                                         "keep": "all" if BSHAPES[wc.shape]["kind"] == "shells" else "largest",
                                         "split": "none",
                                         **BSHAPES[wc.shape]["mesh"]}),
    log:
        BRES + "/logs/shape_mesh/{shape}.log",
    benchmark:
        BRES + "/benchmarks/shapes/mesh/{shape}.tsv"
    threads: res("mesh", "threads")
    resources:
        mem_mb=res("mesh", "mem_mb"),
        runtime=res("mesh", "runtime"),
    conda:
        "../envs/nemo.yaml"
    shell:
        NEMO + " mesh {input.image} -o {output} {params.opts} > {log} 2>&1"


rule bench_shape_score:
    input:
        mesh=BRES + "/shapes/{shape}/mesh.ply",
        truth=BRES + "/shapes/{shape}/truth.json",
    output:
        BRES + "/shapes/{shape}/score.json",
    log:
        BRES + "/logs/shape_score/{shape}.log",
    benchmark:
        BRES + "/benchmarks/shapes/score/{shape}.tsv"
    threads: 1
    resources:
        mem_mb=res("benchmark", "mem_mb"),
        runtime=res("benchmark", "runtime"),
    conda:
        "../envs/nemo.yaml"
    shell:
        "python -m nemo.benchmark score-shape {input.mesh} {input.truth} -o {output} > {log} 2>&1"


def _bench_stage_files():
    files = [f"{BRES}/benchmarks/cases/synth/{v}.tsv" for v in BVOLUMES]
    files += [f"{BRES}/benchmarks/shapes/{k}/{s}.tsv" for s in BSHAPES for k in ("mesh", "score")]
    return files


BENCHMARK_TARGETS = [BRES + "/summary/cases.parquet"]


rule bench_aggregate:
    input:
        scores=[f"{BRES}/cases/{c}/score.json" for c in BCASES],
        shapes=[f"{BRES}/shapes/{s}/score.json" for s in BSHAPES],
        stages=_bench_stage_files(),
    output:
        cases=BRES + "/summary/cases.parquet",
        sweeps=BRES + "/summary/sweeps.parquet",
        shapes=BRES + "/summary/shapes.parquet",
        stages=BRES + "/summary/stages.parquet",
        table=BRES + "/summary/benchmark.md",
    log:
        BRES + "/logs/aggregate.log",
    threads: 1
    resources:
        mem_mb=res("benchmark", "mem_mb"),
        runtime=res("benchmark", "runtime"),
    conda:
        "../envs/nemo.yaml"
    shell:
        "python -m nemo.benchmark aggregate --scores {input.scores:q}"
        " --shapes {input.shapes:q} --stages {input.stages:q} -o {BRES}/summary > {log:q} 2>&1"
