# Directors (method note §5): tangential orientation of the layer's intensity in patches.


rule directors:
    input:
        mesh=layer_mesh,
        layer=FRAME + "/layer_{layer}.parquet",
    output:
        FRAME + "/directors_{layer}.parquet",
    params:
        opts=cli_opts(config["directors"]),
    log:
        LOGS + "/directors/t{t}_c{c}_{layer}.log",
    benchmark:
        BENCH + "/directors/t{t}_c{c}_{layer}.tsv"
    threads: res("directors", "threads")
    resources:
        mem_mb=res("directors", "mem_mb"),
        runtime=res("directors", "runtime"),
    conda:
        "../envs/nemo.yaml"
    shell:
        NEMO + " directors {input.mesh} {input.layer} -o {output} {params.opts} > {log} 2>&1"
