# Benchmark and validation protocol (issue 8; docs/benchmarks.md). Included by the Snakefile
# when the config has a `benchmark:` section (config/benchmark.yaml, config/benchmark-ci.yaml).
#
# Vesicle cases (nemo.benchmark.expand_cases): volume (nemo synth) -> nemo run (mesh, peel,
# directors, order, curvature, defects with the case's parameters) -> score against the truth.
# Analytic shapes: volume (python -m nemo.benchmark shape) -> nemo mesh -> score curvature and
# thickness. The datasets of the same config run through the ordinary per-stage rules, and
# their defects are scored too (sweep "workflow"). Everything is collected by bench_aggregate
# into results/benchmark/summary/. No science here: nemo.benchmark and the nemo CLI compute.

import json

from nemo.benchmark import expand_cases, expand_shapes

BENCHMARK = config["benchmark"]
BRES = RESULTS + "/benchmark"
BCASES = expand_cases(BENCHMARK)
BSHAPES = expand_shapes(BENCHMARK)
BVOLUMES = {c["volume"]: c["synth"] for c in BCASES.values() if c["volume"]}
for _cid, _c in BCASES.items():
    if _c["dataset"] is not None and _c["dataset"] not in DATA:
        config_error(f"benchmark.cases.{_cid}.dataset",
                     f"'{_c['dataset']}' is not under datasets (defined: {', '.join(DATA)})")
    if _c["dataset"] is not None and not DATA[_c["dataset"]]["synthetic"]:
        config_error(f"benchmark.cases.{_cid}.dataset", "needs a synthetic dataset (its truth.json)")
_BMATCH = BENCHMARK.get("match_radius")
_BORDERED = BENCHMARK.get("ordered_distance")
_BSCORE_OPTS = ((f" --match-radius {_BMATCH}" if _BMATCH else "")
                + (f" --ordered-distance {_BORDERED}" if _BORDERED else ""))

wildcard_constraints:
    case="|".join(sorted(BCASES)),
    vid=r"v[0-9a-f]{10}",
    shape="|".join(sorted(BSHAPES)) or "NONE",


def _truth_of(path):
    return os.path.splitext(path)[0] + ".truth.json"


def _case_image(wc):
    c = BCASES[wc.case]
    if c["dataset"] is not None:
        return DATA[c["dataset"]]["path"]
    return f"{BRES}/volumes/{c['volume']}.tif"


def _workflow_frames():
    """(dataset, t, c, layer) of each synthetic dataset's first frame and layer: scored too."""
    out = []
    for name, d in DATA.items():
        if d["synthetic"] and layer_frames(name):
            t, c, layer = layer_frames(name)[0]
            out.append((name, t, c, layer))
    return out


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


rule bench_run:
    input:
        image=_case_image,
    output:
        config=BRES + "/cases/{case}/config.yaml",
        summary=BRES + "/cases/{case}/summary.json",
        defects=BRES + "/cases/{case}/defects.parquet",
        directors=BRES + "/cases/{case}/directors.parquet",
        order=BRES + "/cases/{case}/order.parquet",
        curvature=BRES + "/cases/{case}/curvature.parquet",
    params:
        cfg=lambda wc: json.dumps(BCASES[wc.case]["run"], sort_keys=True),
        outdir=lambda wc: f"{BRES}/cases/{wc.case}",
    log:
        BRES + "/logs/run/{case}.log",
    benchmark:
        BRES + "/benchmarks/cases/run/{case}.tsv"
    threads: res("benchmark", "threads")
    resources:
        mem_mb=res("benchmark", "mem_mb"),
        runtime=res("benchmark", "runtime"),
    conda:
        "../envs/nemo.yaml"
    shell:
        "printf '%s\\n' '{params.cfg}' > {output.config} && "
        + NEMO + " run {input.image} -o {params.outdir} --config {output.config} > {log} 2>&1"


rule bench_score:
    input:
        image=_case_image,
        truth=lambda wc: _truth_of(_case_image(wc)),
        summary=BRES + "/cases/{case}/summary.json",
        defects=BRES + "/cases/{case}/defects.parquet",
        directors=BRES + "/cases/{case}/directors.parquet",
        order=BRES + "/cases/{case}/order.parquet",
        curvature=BRES + "/cases/{case}/curvature.parquet",
    output:
        BRES + "/cases/{case}/score.json",
    params:
        case=lambda wc: json.dumps({k: BCASES[wc.case][k] for k in
                                    ("case", "sweep", "parameter", "value", "value_label", "rotation",
                                     "synth", "run", "dataset")}).replace("'", ""),
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
        "python -m nemo.benchmark score --truth {input.truth} --defects {input.defects}"
        " --directors {input.directors} --order {input.order} --curvature {input.curvature}"
        " --summary {input.summary} --case '{params.case}' {params.opts} -o {output} > {log} 2>&1"


def _workflow_score_inputs(wc):
    t, c, layer = (int(wc.t), int(wc.c), wc.layer)
    frame = f"{RESULTS}/{wc.dataset}/t{t}/c{c}"
    seg = f"{RESULTS}/{wc.dataset}/t{t}/c{DATA[wc.dataset]['seg']}"
    inputs = {"truth": _truth_of(DATA[wc.dataset]["path"]), "defects": f"{frame}/defects_{layer}.parquet",
              "directors": f"{frame}/directors_{layer}.parquet", "order": f"{frame}/order_{layer}.parquet"}
    if CURVATURE is not None:
        inputs["curvature"] = f"{seg}/curvature_{LAYERS[layer]['surface']}.parquet"
    return inputs


rule bench_score_workflow:
    input:
        unpack(_workflow_score_inputs),
    output:
        BRES + "/workflow/{dataset}/t{t}_c{c}_{layer}.score.json",
    params:
        case=lambda wc: json.dumps({"case": f"workflow-{wc.dataset}", "sweep": "workflow",
                                    "parameter": None, "value": None, "value_label": wc.dataset,
                                    "rotation": None, "synth": DATA[wc.dataset]["synthetic"],
                                    "run": {}, "dataset": wc.dataset}).replace("'", ""),
        curvature=lambda wc, input: f"--curvature {input.curvature}" if "curvature" in input.keys() else "",
        opts=_BSCORE_OPTS,
    log:
        BRES + "/logs/score/workflow_{dataset}_t{t}_c{c}_{layer}.log",
    threads: 1
    resources:
        mem_mb=res("benchmark", "mem_mb"),
        runtime=res("benchmark", "runtime"),
    conda:
        "../envs/nemo.yaml"
    shell:
        "python -m nemo.benchmark score --truth {input.truth} --defects {input.defects}"
        " --directors {input.directors} --order {input.order} {params.curvature}"
        " --case '{params.case}' {params.opts} -o {output} > {log} 2>&1"


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
    files = [f"{BRES}/benchmarks/cases/run/{c}.tsv" for c in BCASES]
    files += [f"{BRES}/benchmarks/cases/synth/{v}.tsv" for v in BVOLUMES]
    files += [f"{BRES}/benchmarks/shapes/{k}/{s}.tsv" for s in BSHAPES for k in ("mesh", "score")]
    return files


def _workflow_stage_files():
    """Snakemake benchmark files of the ordinary per-stage rules for the configured datasets."""
    out = []
    for name in DATA:
        b = BENCH.format(dataset=name)
        for t, c, layer in layer_frames(name):
            seg = DATA[name]["seg"]
            out += [f"{b}/mesh/t{t}_c{seg}.tsv", f"{b}/peel/t{t}_c{c}_{layer}.tsv",
                    f"{b}/directors/t{t}_c{c}_{layer}.tsv", f"{b}/order/t{t}_c{c}_{layer}.tsv",
                    f"{b}/defects/t{t}_c{c}_{layer}.tsv"]
            if CURVATURE is not None:
                out.append(f"{b}/curvature/t{t}_c{seg}_{LAYERS[layer]['surface']}.tsv")
            if THICKNESS is not None:
                out.append(f"{b}/thickness/t{t}_c{seg}.tsv")
    return sorted(set(out))


BENCHMARK_TARGETS = [BRES + "/summary/cases.parquet"]


rule bench_aggregate:
    input:
        scores=[f"{BRES}/cases/{c}/score.json" for c in BCASES],
        workflow=[f"{BRES}/workflow/{n}/t{t}_c{c}_{l}.score.json" for n, t, c, l in _workflow_frames()],
        shapes=[f"{BRES}/shapes/{s}/score.json" for s in BSHAPES],
        stages=_bench_stage_files(),
        workflow_stages=_workflow_stage_files(),
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
        "python -m nemo.benchmark aggregate --scores {input.scores} {input.workflow}"
        " --shapes {input.shapes} --stages {input.stages} {input.workflow_stages}"
        " -o {BRES}/summary > {log} 2>&1"
