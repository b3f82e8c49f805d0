# Morphology (method note §3): global measures, curvature (H, K) and the thickness between two
# surfaces. Computed once per time point on the meshes of the segmented channel.


rule measure:
    input:
        mesh=lambda wc: frame_file(wc, layout.MESH[wc.surface]),
    output:
        FRAME + "/measure_{surface}.json",
    log:
        LOGS + "/measure/t{t}_c{c}_{surface}.log",
    benchmark:
        BENCH + "/measure/t{t}_c{c}_{surface}.tsv"
    group:
        "frame"
    threads: res("measure", "threads")
    resources:
        mem_mb=res("measure", "mem_mb"),
        runtime=res("measure", "runtime"),
    conda:
        "../envs/nemo.yaml"
    shell:
        # stdout is the JSON: write it to a temporary file and rename (atomic)
        NEMO + " measure {input.mesh:q} --json > {output:q}.tmp 2> {log:q} && mv {output:q}.tmp {output:q}"


rule curvature:
    input:
        mesh=lambda wc: frame_file(wc, layout.MESH[wc.surface]),
    output:
        FRAME + "/curvature_{surface}.parquet",
    params:
        opts=opts("curvature"),
    log:
        LOGS + "/curvature/t{t}_c{c}_{surface}.log",
    benchmark:
        BENCH + "/curvature/t{t}_c{c}_{surface}.tsv"
    group:
        "frame"
    threads: res("curvature", "threads")
    resources:
        mem_mb=res("curvature", "mem_mb"),
        runtime=res("curvature", "runtime"),
    conda:
        "../envs/nemo.yaml"
    shell:
        NEMO + " curvature {input.mesh:q} -o {output:q} {params.opts} > {log:q} 2>&1"


rule thickness:
    input:
        mesh_from=lambda wc: frame_file(wc, layout.MESH[sec(wc.dataset, "thickness")["from"]]),
        mesh_to=lambda wc: frame_file(wc, layout.MESH[sec(wc.dataset, "thickness")["to"]]),
    output:
        FRAME + "/" + layout.THICKNESS,
    params:
        opts=opts("thickness", skip=("from", "to")),
    log:
        LOGS + "/thickness/t{t}_c{c}.log",
    benchmark:
        BENCH + "/thickness/t{t}_c{c}.tsv"
    group:
        "frame"
    threads: res("thickness", "threads")
    resources:
        mem_mb=res("thickness", "mem_mb"),
        runtime=res("thickness", "runtime"),
    conda:
        "../envs/nemo.yaml"
    shell:
        NEMO + " thickness {input.mesh_from:q} {input.mesh_to:q} -o {output:q} {params.opts} > {log:q} 2>&1"
