# Peeling (method note §4): one intensity value per vertex of the layer's surface, sampled along
# the normals over the layer's depth range, optionally shifted by a fraction of the thickness.
# Inputs and options: peel_inputs, peel_opts (common.smk).


rule peel:
    input:
        unpack(peel_inputs),
    output:
        frame_path("layer_{layer}.parquet"),
    log:
        log_path("peel/t{t}_c{c}_{layer}.log"),
    benchmark:
        bench_path("peel/t{t}_c{c}_{layer}.tsv")
    group:
        "frame"
    conda:
        "../envs/nemo.yaml"
    threads: res("peel", "threads")
    resources:
        mem_mb=mem_image("peel"),
        runtime=res("peel", "runtime"),
    params:
        opts=peel_opts,
        calibration=calibration_opts,
        shift=lambda wc, input: optional_file("--shift", input, "shift", ":thickness"),
        deconvolved=deconvolved_opts,
    shell:
        nemo_shell(
            "peel {input.image:q} {input.mesh:q} -o {output:q} --t {wildcards.t} --c {wildcards.c}"
            " {params.calibration} {params.deconvolved} {params.opts} {params.shift}"
            " > {log:q} 2>&1"
        )
