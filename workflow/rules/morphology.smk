# Morphology (method note §3): global measures, curvature (H, K) and the thickness between two
# surfaces. Computed once per time point on the meshes of the segmented channel.


rule measure:
    input:
        mesh=lambda wc: frame_file(wc, layout.MESH[wc.surface]),
    output:
        frame_path("measure_{surface}.json"),
    log:
        log_path("measure/t{t}_c{c}_{surface}.log"),
    benchmark:
        bench_path("measure/t{t}_c{c}_{surface}.tsv")
    group:
        "frame"
    conda:
        "../envs/nemo.yaml"
    threads: res("measure", "threads")
    resources:
        mem_mb=res("measure", "mem_mb"),
        runtime=res("measure", "runtime"),
    shell:
        # stdout is the JSON: write it to a temporary file and rename (atomic)
        nemo_shell(
            "measure {input.mesh:q} --json > {output:q}.tmp 2> {log:q} && mv {output:q}.tmp {output:q}"
        )


rule curvature:
    input:
        mesh=lambda wc: frame_file(wc, layout.MESH[wc.surface]),
    output:
        frame_path("curvature_{surface}.parquet"),
    log:
        log_path("curvature/t{t}_c{c}_{surface}.log"),
    benchmark:
        bench_path("curvature/t{t}_c{c}_{surface}.tsv")
    group:
        "frame"
    conda:
        "../envs/nemo.yaml"
    threads: res("curvature", "threads")
    resources:
        mem_mb=res("curvature", "mem_mb"),
        runtime=res("curvature", "runtime"),
    params:
        opts=opts("curvature"),
    shell:
        nemo_shell(
            "curvature {input.mesh:q} -o {output:q} {params.opts} > {log:q} 2>&1"
        )


rule thickness:
    input:
        mesh_from=lambda wc: thickness_mesh(wc, "from"),
        mesh_to=lambda wc: thickness_mesh(wc, "to"),
    output:
        frame_path(layout.THICKNESS),
    log:
        log_path("thickness/t{t}_c{c}.log"),
    benchmark:
        bench_path("thickness/t{t}_c{c}.tsv")
    group:
        "frame"
    conda:
        "../envs/nemo.yaml"
    threads: res("thickness", "threads")
    resources:
        mem_mb=res("thickness", "mem_mb"),
        runtime=res("thickness", "runtime"),
    params:
        opts=opts("thickness", skip=("from", "to")),
    shell:
        nemo_shell(
            "thickness {input.mesh_from:q} {input.mesh_to:q} -o {output:q} {params.opts}"
            " > {log:q} 2>&1"
        )
