# Topological defects (method note §7): localisation from low S, curvature-corrected charge,
# refinement pass with extra directors near each first-pass defect.


def _defects_inputs(wc):
    inputs = {
        "mesh": layer_mesh(wc),
        "order": frame_file(wc, layout.layer_file("order", wc.layer)),
        "directors": frame_file(wc, layout.layer_file("directors", wc.layer)),
    }
    if not imported(wc.dataset, wc.layer):  # imported directors: no layer, no refinement pass
        inputs["layer"] = frame_file(wc, layout.layer_file("layer", wc.layer))
    d = sec(wc.dataset, "defects")
    if d["curvature_source"] == "table" and d["curvature_correction"]:
        inputs["curvature"] = f"{seg_dir(wc)}/{layout.curvature_file(layer_cfg(wc)['surface'])}"
    return inputs


rule defects:
    input:
        unpack(_defects_inputs),
    output:
        defects=FRAME + "/defects_{layer}.parquet",
        refined=FRAME + "/refined_{layer}.parquet",
    params:
        opts=lambda wc: cli_opts(sec(wc.dataset, "defects"), skip=("curvature_correction",))
        + ("" if sec(wc.dataset, "defects")["curvature_correction"] else " --no-curvature-correction"),
        curvature=lambda wc, input: f"--curvature {shlex.quote(input.curvature)}" if "curvature" in input.keys() else "",
        layer=lambda wc, input: f"--layer {shlex.quote(input.layer)}" if "layer" in input.keys() else "",
    log:
        LOGS + "/defects/t{t}_c{c}_{layer}.log",
    benchmark:
        BENCH + "/defects/t{t}_c{c}_{layer}.tsv"
    group:
        "frame"
    threads: res("defects", "threads")
    resources:
        mem_mb=res("defects", "mem_mb"),
        runtime=res("defects", "runtime"),
    conda:
        "../envs/nemo.yaml"
    shell:
        NEMO + " defects {input.mesh:q} {input.order:q} {input.directors:q} {params.curvature}"
        " {params.layer} --refined {output.refined:q} -o {output.defects:q} {params.opts}"
        " > {log:q} 2>&1"
