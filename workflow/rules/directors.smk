# Directors (method note §5): tangential orientation of the layer's intensity in patches; or,
# for a layer with `directors_from`, another tool's director field mapped onto the mesh.


rule directors:
    input:
        mesh=layer_mesh,
        layer=FRAME + "/layer_{layer}.parquet",
    output:
        FRAME + "/directors_{layer}.parquet",
    wildcard_constraints:
        layer=_layer_regex(MEASURED_LAYERS),
    params:
        opts=opts("directors"),
    log:
        LOGS + "/directors/t{t}_c{c}_{layer}.log",
    benchmark:
        BENCH + "/directors/t{t}_c{c}_{layer}.tsv"
    group:
        "frame"
    threads: res("directors", "threads")
    resources:
        mem_mb=res("directors", "mem_mb"),
        runtime=res("directors", "runtime"),
    conda:
        "../envs/nemo.yaml"
    shell:
        NEMO + " directors {input.mesh:q} {input.layer:q} -o {output:q} {params.opts} > {log:q} 2>&1"


if IMPORTED_LAYERS:

    rule directors_import:
        input:
            mesh=layer_mesh,
            points=directors_source,
        output:
            FRAME + "/directors_{layer}.parquet",
        wildcard_constraints:
            layer=_layer_regex(IMPORTED_LAYERS),
        params:
            opts=lambda wc: cli_opts(nconfig.section("directors_import", layer_cfg(wc).get("import"))),
        log:
            LOGS + "/directors_import/t{t}_c{c}_{layer}.log",
        benchmark:
            BENCH + "/directors_import/t{t}_c{c}_{layer}.tsv"
        group:
            "frame"
        threads: res("directors", "threads")
        resources:
            mem_mb=res("directors", "mem_mb"),
            runtime=res("directors", "runtime"),
        conda:
            "../envs/nemo.yaml"
        shell:
            NEMO + " directors import {input.mesh:q} {input.points:q} -o {output:q} {params.opts} > {log:q} 2>&1"
