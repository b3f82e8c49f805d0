# Morphology (method note §3): global measures, curvature (H, K) and the thickness between two
# surfaces. Computed once per time point on the meshes of the segmented channel.


rule measure:
    input:
        mesh=lambda wc: f"{FRAME}/{SURFACE_FILE[wc.surface]}".format(**wc),
    output:
        FRAME + "/measure_{surface}.json",
    log:
        LOGS + "/measure/t{t}_c{c}_{surface}.log",
    benchmark:
        BENCH + "/measure/t{t}_c{c}_{surface}.tsv"
    threads: res("measure", "threads")
    resources:
        mem_mb=res("measure", "mem_mb"),
        runtime=res("measure", "runtime"),
    conda:
        "../envs/nemo.yaml"
    shell:
        # stdout is the JSON: write it to a temporary file and rename (atomic)
        NEMO + " measure {input.mesh} --json > {output}.tmp 2> {log} && mv {output}.tmp {output}"


rule curvature:
    input:
        mesh=lambda wc: f"{FRAME}/{SURFACE_FILE[wc.surface]}".format(**wc),
    output:
        FRAME + "/curvature_{surface}.parquet",
    params:
        opts=cli_opts(CURVATURE or {}),
    log:
        LOGS + "/curvature/t{t}_c{c}_{surface}.log",
    benchmark:
        BENCH + "/curvature/t{t}_c{c}_{surface}.tsv"
    threads: res("curvature", "threads")
    resources:
        mem_mb=res("curvature", "mem_mb"),
        runtime=res("curvature", "runtime"),
    conda:
        "../envs/nemo.yaml"
    shell:
        NEMO + " curvature {input.mesh} -o {output} {params.opts} > {log} 2>&1"


rule thickness:
    input:
        mesh_from=lambda wc: f"{FRAME}/{SURFACE_FILE[THICKNESS['from']]}".format(**wc),
        mesh_to=lambda wc: f"{FRAME}/{SURFACE_FILE[THICKNESS['to']]}".format(**wc),
    output:
        FRAME + "/thickness.parquet",
    params:
        opts=cli_opts({k: v for k, v in (THICKNESS or {}).items() if k not in ("from", "to")}),
    log:
        LOGS + "/thickness/t{t}_c{c}.log",
    benchmark:
        BENCH + "/thickness/t{t}_c{c}.tsv"
    threads: res("thickness", "threads")
    resources:
        mem_mb=res("thickness", "mem_mb"),
        runtime=res("thickness", "runtime"),
    conda:
        "../envs/nemo.yaml"
    shell:
        NEMO + " thickness {input.mesh_from} {input.mesh_to} -o {output} {params.opts} > {log} 2>&1"
