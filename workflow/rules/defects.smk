# Topological defects (method note §7): localisation from low S, curvature-corrected charge,
# refinement pass with extra directors near each first-pass defect. Inputs: defects_inputs
# (common.smk).


rule defects:
    input:
        unpack(defects_inputs),
    output:
        defects=frame_path("defects_{layer}.parquet"),
        refined=frame_path("refined_{layer}.parquet"),
    log:
        log_path("defects/t{t}_c{c}_{layer}.log"),
    benchmark:
        bench_path("defects/t{t}_c{c}_{layer}.tsv")
    group:
        "frame"
    conda:
        "../envs/nemo.yaml"
    threads: res("defects", "threads")
    resources:
        mem_mb=res("defects", "mem_mb"),
        runtime=res("defects", "runtime"),
    params:
        opts=defects_opts,
        curvature=lambda wc, input: optional_file("--curvature", input, "curvature"),
        layer=lambda wc, input: optional_file("--layer", input, "layer"),
    shell:
        nemo_shell(
            "defects {input.mesh:q} {input.order:q} {input.directors:q} {params.curvature}"
            " {params.layer} --refined {output.refined:q} -o {output.defects:q} {params.opts}"
            " > {log:q} 2>&1"
        )
