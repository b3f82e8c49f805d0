# Topological defects (method note §7): localisation from low S, curvature-corrected charge.


def _defects_inputs(wc):
    inputs = {
        "mesh": layer_mesh(wc),
        "order": FRAME.format(**wc) + f"/order_{wc.layer}.parquet",
        "directors": FRAME.format(**wc) + f"/directors_{wc.layer}.parquet",
    }
    if config["defects"]["refine_directors"] > 0:  # refinement pass: extra directors on the layer
        inputs["layer"] = FRAME.format(**wc) + f"/layer_{wc.layer}.parquet"
    if CURVATURE is not None and config["defects"]["curvature_correction"]:
        inputs["curvature"] = f"{seg_dir(wc)}/curvature_{LAYERS[wc.layer]['surface']}.parquet"
    return inputs


rule defects:
    input:
        unpack(_defects_inputs),
    output:
        FRAME + "/defects_{layer}.parquet",
    params:
        opts=cli_opts(config["defects"], skip=("curvature_correction",))
        + ("" if config["defects"]["curvature_correction"] else " --no-curvature-correction"),
        curvature=lambda wc, input: f"--curvature {input.curvature}" if "curvature" in input.keys() else "",
        layer=lambda wc, input: f"--layer {input.layer}" if "layer" in input.keys() else "",
    log:
        LOGS + "/defects/t{t}_c{c}_{layer}.log",
    benchmark:
        BENCH + "/defects/t{t}_c{c}_{layer}.tsv"
    threads: res("defects", "threads")
    resources:
        mem_mb=res("defects", "mem_mb"),
        runtime=res("defects", "runtime"),
    conda:
        "../envs/nemo.yaml"
    shell:
        NEMO + " defects {input.mesh} {input.order} {input.directors} {params.curvature} {params.layer}"
        " -o {output} {params.opts} > {log} 2>&1"
