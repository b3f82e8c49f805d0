# Tangential nematic average (method note §6): Q-tensor average within a radius -> S, n.


rule order:
    input:
        mesh=layer_mesh,
        directors=frame_path("directors_{layer}.parquet"),
    output:
        frame_path("order_{layer}.parquet"),
    log:
        log_path("order/t{t}_c{c}_{layer}.log"),
    benchmark:
        bench_path("order/t{t}_c{c}_{layer}.tsv")
    group:
        "frame"
    conda:
        "../envs/nemo.yaml"
    threads: res("order", "threads")
    resources:
        mem_mb=res("order", "mem_mb"),
        runtime=res("order", "runtime"),
    params:
        opts=opts("order"),
    shell:
        nemo_shell(
            "order {input.mesh:q} {input.directors:q} -o {output:q} {params.opts} > {log:q} 2>&1"
        )
