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


include: "benchmark_common.smk"


wildcard_constraints:
    case="|".join(sorted(BCASES)),
    vid=r"v[0-9a-f]{10}",
    shape="|".join(sorted(BSHAPES)) or "NONE",


rule bench_synth:
    output:
        image=bench_file("volumes/{vid}.tif"),
        truth=bench_file("volumes/{vid}.truth.json"),
    log:
        bench_file("logs/synth/{vid}.log"),
    benchmark:
        bench_file("benchmarks/cases/synth/{vid}.tsv")
    conda:
        "../envs/nemo.yaml"
    threads: res("benchmark", "threads")
    resources:
        mem_mb=res("benchmark", "mem_mb"),
        runtime=res("benchmark", "runtime"),
    params:
        opts=lambda wc: cli_opts(BVOLUMES[wc.vid]),
    shell:
        nemo_shell("synth {output.image} {params.opts} > {log} 2>&1")


rule bench_score:
    input:
        unpack(bench_score_inputs),
    output:
        bench_file("cases/{case}/score.json"),
    log:
        bench_file("logs/score/{case}.log"),
    conda:
        "../envs/nemo.yaml"
    threads: 1
    resources:
        mem_mb=res("benchmark", "mem_mb"),
        runtime=res("benchmark", "runtime"),
    params:
        case=bench_case_json,
        curvature=lambda wc, input: optional_file("--curvature", input, "curvature"),
        opts=BSCORE_OPTS,
    shell:
        "python -m nemo.benchmark score --truth {input.truth:q} --defects {input.defects:q}"
        " --directors {input.directors:q} --order {input.order:q} {params.curvature}"
        " --stage-files {input.stages:q} --case '{params.case}' {params.opts} -o {output:q} > {log:q} 2>&1"


rule bench_shape:
    output:
        image=bench_file("shapes/{shape}/volume.tif"),
        truth=bench_file("shapes/{shape}/truth.json"),
    log:
        bench_file("logs/shape/{shape}.log"),
    benchmark:
        bench_file("benchmarks/shapes/shape/{shape}.tsv")
    conda:
        "../envs/nemo.yaml"
    threads: 1
    resources:
        mem_mb=res("benchmark", "mem_mb"),
        runtime=res("benchmark", "runtime"),
    params:
        spec=bench_shape_spec,
    shell:
        "python -m nemo.benchmark shape '{params.spec}' -o {output.image} --truth {output.truth} > {log} 2>&1"


rule bench_shape_mesh:
    input:
        image=bench_file("shapes/{shape}/volume.tif"),
        truth=bench_file("shapes/{shape}/truth.json"),
    output:
        bench_file("shapes/{shape}/mesh.ply"),
    log:
        bench_file("logs/shape_mesh/{shape}.log"),
    benchmark:
        bench_file("benchmarks/shapes/mesh/{shape}.tsv")
    conda:
        "../envs/nemo.yaml"
    threads: res("mesh", "threads")
    resources:
        mem_mb=res("mesh", "mem_mb"),
        runtime=res("mesh", "runtime"),
    params:
        opts=bench_shape_mesh_opts,
    shell:
        nemo_shell("mesh {input.image} -o {output} {params.opts} > {log} 2>&1")


rule bench_shape_score:
    input:
        mesh=bench_file("shapes/{shape}/mesh.ply"),
        truth=bench_file("shapes/{shape}/truth.json"),
    output:
        bench_file("shapes/{shape}/score.json"),
    log:
        bench_file("logs/shape_score/{shape}.log"),
    benchmark:
        bench_file("benchmarks/shapes/score/{shape}.tsv")
    conda:
        "../envs/nemo.yaml"
    threads: 1
    resources:
        mem_mb=res("benchmark", "mem_mb"),
        runtime=res("benchmark", "runtime"),
    shell:
        "python -m nemo.benchmark score-shape {input.mesh} {input.truth} -o {output} > {log} 2>&1"


BENCHMARK_TARGETS = [bench_file("summary/cases.parquet")]


rule bench_aggregate:
    input:
        scores=[bench_file(f"cases/{c}/score.json") for c in BCASES],
        shapes=[bench_file(f"shapes/{s}/score.json") for s in BSHAPES],
        stages=bench_stage_files(),
    output:
        cases=bench_file("summary/cases.parquet"),
        sweeps=bench_file("summary/sweeps.parquet"),
        shapes=bench_file("summary/shapes.parquet"),
        stages=bench_file("summary/stages.parquet"),
        table=bench_file("summary/benchmark.md"),
    log:
        bench_file("logs/aggregate.log"),
    conda:
        "../envs/nemo.yaml"
    threads: 1
    resources:
        mem_mb=res("benchmark", "mem_mb"),
        runtime=res("benchmark", "runtime"),
    params:
        summary=lambda wc, output: os.path.dirname(output.cases),
    shell:
        "python -m nemo.benchmark aggregate --scores {input.scores:q}"
        " --shapes {input.shapes:q} --stages {input.stages:q} -o {params.summary:q} > {log:q} 2>&1"
