# Inter-layer alignment (method note §6): c = cos 2(θ_B − θ_A) for each director of layer A, and
# c_avg between the two layers' averaged directors (their order tables).


rule align:
    input:
        a=frame_path("directors_{a}.parquet"),
        b=frame_path("directors_{b}.parquet"),
        order_a=frame_path("order_{a}.parquet"),
        order_b=frame_path("order_{b}.parquet"),
        mesh=lambda wc: layer_mesh(wc, wc.a),
    output:
        frame_path("align_{a}_{b}.parquet"),
    log:
        log_path("align/t{t}_c{c}_{a}_{b}.log"),
    benchmark:
        bench_path("align/t{t}_c{c}_{a}_{b}.tsv")
    group:
        "frame"
    conda:
        "../envs/nemo.yaml"
    threads: res("align", "threads")
    resources:
        mem_mb=res("align", "mem_mb"),
        runtime=res("align", "runtime"),
    shell:
        nemo_shell(
            "align {input.a:q} {input.b:q} --order-a {input.order_a:q} --order-b {input.order_b:q} "
            "--mesh {input.mesh:q} -o {output:q} > {log:q} 2>&1"
        )
