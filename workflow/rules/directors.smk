# Directors (method note §5): tangential orientation of the layer's intensity in patches; or,
# for a layer with `directors_from`, another tool's director field mapped onto the mesh.


rule directors:
    input:
        mesh=layer_mesh,
        layer=frame_path("layer_{layer}.parquet"),
    output:
        frame_path("directors_{layer}.parquet"),
    log:
        log_path("directors/t{t}_c{c}_{layer}.log"),
    benchmark:
        bench_path("directors/t{t}_c{c}_{layer}.tsv")
    wildcard_constraints:
        layer=layer_regex(MEASURED_LAYERS),
    group:
        "frame"
    conda:
        "../envs/nemo.yaml"
    threads: res("directors", "threads")
    resources:
        mem_mb=res("directors", "mem_mb"),
        runtime=res("directors", "runtime"),
    params:
        opts=opts("directors"),
    shell:
        nemo_shell(
            "directors {input.mesh:q} {input.layer:q} -o {output:q} {params.opts} > {log:q} 2>&1"
        )


if IMPORTED_LAYERS:

    rule directors_import:
        input:
            mesh=layer_mesh,
            points=directors_source,
        output:
            frame_path("directors_{layer}.parquet"),
        log:
            log_path("directors_import/t{t}_c{c}_{layer}.log"),
        benchmark:
            bench_path("directors_import/t{t}_c{c}_{layer}.tsv")
        wildcard_constraints:
            layer=layer_regex(IMPORTED_LAYERS),
        group:
            "frame"
        conda:
            "../envs/nemo.yaml"
        threads: res("directors", "threads")
        resources:
            mem_mb=res("directors", "mem_mb"),
            runtime=res("directors", "runtime"),
        params:
            opts=import_opts,
        shell:
            nemo_shell(
                "directors import {input.mesh:q} {input.points:q} -o {output:q} {params.opts}"
                " > {log:q} 2>&1"
            )
