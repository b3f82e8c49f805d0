# Tangential nematic average (method note §6): Q-tensor average within a radius -> S, n.


rule order:
    input:
        mesh=layer_mesh,
        directors=FRAME + "/directors_{layer}.parquet",
    output:
        FRAME + "/order_{layer}.parquet",
    params:
        opts=opts("order"),
    log:
        LOGS + "/order/t{t}_c{c}_{layer}.log",
    benchmark:
        BENCH + "/order/t{t}_c{c}_{layer}.tsv"
    group:
        "frame"
    threads: res("order", "threads")
    resources:
        mem_mb=res("order", "mem_mb"),
        runtime=res("order", "runtime"),
    conda:
        "../envs/nemo.yaml"
    shell:
        NEMO + " order {input.mesh:q} {input.directors:q} -o {output:q} {params.opts} > {log:q} 2>&1"
