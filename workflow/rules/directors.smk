# Directors (method note §5): tangential orientation of the layer's intensity in patches.


rule directors:
    input:
        mesh=layer_mesh,
        layer=FRAME + "/layer_{layer}.parquet",
    output:
        FRAME + "/directors_{layer}.parquet",
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
