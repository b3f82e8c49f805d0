# Validation protocol (docs/validation.md). Included by the Snakefile, right after common.smk,
# when the config has a `validation:` section (config/validation.yaml,
# config/validation-ci.yaml).
#
# Every vesicle case (nemo.validation.expand_cases) becomes a dataset `validation.CASE` of one
# frame, analysed by the workflow's own per-frame rules (mesh, morphology, peel, directors,
# order, defects) with the case's `run` overrides as per-dataset sections: the protocol measures
# what `snakemake` users get. Each case's defects are scored against the synthetic truth
# (nemo validate score); the stage times are Snakemake's benchmark files of those rules.
# Analytic shapes (nemo validate shape) are meshed by nemo mesh and scored for curvature and
# thickness (nemo validate score-shape). Everything is collected by validation_aggregate into
# results/validation/summary/.


include: "validation_common.smk"


wildcard_constraints:
    case="|".join(sorted(VCASES)),
    vid=r"v[0-9a-f]{10}",
    shape="|".join(sorted(VSHAPES)) or "NONE",


rule validation_synth:
    output:
        image=validation_file("volumes/{vid}.tif"),
        truth=validation_file("volumes/{vid}.truth.json"),
    log:
        validation_file("logs/synth/{vid}.log"),
    benchmark:
        validation_file("benchmarks/cases/synth/{vid}.tsv")
    conda:
        "../envs/nemo.yaml"
    threads: res("validation", "threads")
    resources:
        mem_mb=res("validation", "mem_mb"),
        runtime=res("validation", "runtime"),
    params:
        opts=lambda wc: cli_opts(VVOLUMES[wc.vid]),
    shell:
        nemo_shell("synth {output.image} {params.opts} > {log} 2>&1")


rule validation_score:
    input:
        unpack(validation_score_inputs),
    output:
        validation_file("cases/{case}/score.json"),
    log:
        validation_file("logs/score/{case}.log"),
    conda:
        "../envs/nemo.yaml"
    threads: 1
    resources:
        mem_mb=res("validation", "mem_mb"),
        runtime=res("validation", "runtime"),
    params:
        case=validation_case_json,
        curvature=lambda wc, input: optional_file("--curvature", input, "curvature"),
        opts=VSCORE_OPTS,
    shell:
        nemo_shell(
            "validate score --truth {input.truth:q} --defects {input.defects:q}"
            " --directors {input.directors:q} --order {input.order:q} {params.curvature}"
            " --stage-files {input.stages:q} --case '{params.case}' {params.opts} -o {output:q} > {log:q} 2>&1"
        )


rule validation_shape:
    output:
        image=validation_file("shapes/{shape}/volume.tif"),
        truth=validation_file("shapes/{shape}/truth.json"),
    log:
        validation_file("logs/shape/{shape}.log"),
    benchmark:
        validation_file("benchmarks/shapes/shape/{shape}.tsv")
    conda:
        "../envs/nemo.yaml"
    threads: 1
    resources:
        mem_mb=res("validation", "mem_mb"),
        runtime=res("validation", "runtime"),
    params:
        spec=validation_shape_spec,
    shell:
        nemo_shell(
            "validate shape '{params.spec}' -o {output.image:q} --truth {output.truth:q} > {log:q} 2>&1"
        )


rule validation_shape_mesh:
    input:
        image=validation_file("shapes/{shape}/volume.tif"),
        truth=validation_file("shapes/{shape}/truth.json"),
    output:
        validation_file("shapes/{shape}/mesh.ply"),
    log:
        validation_file("logs/shape_mesh/{shape}.log"),
    benchmark:
        validation_file("benchmarks/shapes/mesh/{shape}.tsv")
    conda:
        "../envs/nemo.yaml"
    threads: res("mesh", "threads")
    resources:
        mem_mb=res("mesh", "mem_mb"),
        runtime=res("mesh", "runtime"),
    params:
        opts=validation_shape_mesh_opts,
    shell:
        nemo_shell("mesh {input.image} -o {output} {params.opts} > {log} 2>&1")


rule validation_shape_score:
    input:
        mesh=validation_file("shapes/{shape}/mesh.ply"),
        truth=validation_file("shapes/{shape}/truth.json"),
    output:
        validation_file("shapes/{shape}/score.json"),
    log:
        validation_file("logs/shape_score/{shape}.log"),
    benchmark:
        validation_file("benchmarks/shapes/score/{shape}.tsv")
    conda:
        "../envs/nemo.yaml"
    threads: 1
    resources:
        mem_mb=res("validation", "mem_mb"),
        runtime=res("validation", "runtime"),
    shell:
        nemo_shell(
            "validate score-shape {input.mesh:q} {input.truth:q} -o {output:q} > {log:q} 2>&1"
        )


VALIDATION_TARGETS = [validation_file("summary/cases.parquet")]


rule validation_aggregate:
    input:
        scores=[validation_file(f"cases/{c}/score.json") for c in VCASES],
        shapes=[validation_file(f"shapes/{s}/score.json") for s in VSHAPES],
        stages=validation_stage_files(),
    output:
        cases=validation_file("summary/cases.parquet"),
        sweeps=validation_file("summary/sweeps.parquet"),
        shapes=validation_file("summary/shapes.parquet"),
        stages=validation_file("summary/stages.parquet"),
        table=validation_file("summary/validation.md"),
    log:
        validation_file("logs/aggregate.log"),
    conda:
        "../envs/nemo.yaml"
    threads: 1
    resources:
        mem_mb=res("validation", "mem_mb"),
        runtime=res("validation", "runtime"),
    params:
        summary=lambda wc, output: os.path.dirname(output.cases),
    shell:
        nemo_shell(
            "validate aggregate --scores {input.scores:q}"
            " --shapes {input.shapes:q} --stages {input.stages:q} -o {params.summary:q} > {log:q} 2>&1"
        )
