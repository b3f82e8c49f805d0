# Inter-layer alignment (method note §6): c = cos 2(θ_B − θ_A) for each director of layer A.


rule align:
    input:
        a=FRAME + "/directors_{a}.parquet",
        b=FRAME + "/directors_{b}.parquet",
        mesh=lambda wc: layer_mesh(wc, wc.a),
    output:
        FRAME + "/align_{a}_{b}.parquet",
    log:
        LOGS + "/align/t{t}_c{c}_{a}_{b}.log",
    benchmark:
        BENCH + "/align/t{t}_c{c}_{a}_{b}.tsv"
    group:
        "frame"
    threads: res("align", "threads")
    resources:
        mem_mb=res("align", "mem_mb"),
        runtime=res("align", "runtime"),
    conda:
        "../envs/nemo.yaml"
    shell:
        NEMO + " align {input.a:q} {input.b:q} --mesh {input.mesh:q} -o {output:q} > {log:q} 2>&1"
