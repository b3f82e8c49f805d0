# Peeling (method note §4): one intensity value per vertex of the layer's surface, sampled along
# the normals over the layer's depth range, optionally shifted by a fraction of the thickness.


def _peel_inputs(wc):
    layer = LAYERS[wc.layer]
    inputs = {"image": image(wc), "mesh": layer_mesh(wc)}
    if layer["shift"]:
        inputs["shift"] = f"{seg_dir(wc)}/thickness.parquet"
    return inputs


def _peel_opts(wc):
    layer = LAYERS[wc.layer]
    dmin, dmax = layer["range"]
    opts = f"--range {dmin} {dmax} " + cli_opts(
        {k: layer[k] for k in ("reduce", "samples", "interp", "inward")}
    )
    if layer["shift"]:
        opts += f" --shift-fraction {layer['shift']}"
    return opts


rule peel:
    input:
        unpack(_peel_inputs),
    output:
        FRAME + "/layer_{layer}.parquet",
    params:
        opts=_peel_opts,
        spacing=spacing_opt,
        shift=lambda wc, input: f"--shift {input.shift}:thickness" if "shift" in input.keys() else "",
    log:
        LOGS + "/peel/t{t}_c{c}_{layer}.log",
    benchmark:
        BENCH + "/peel/t{t}_c{c}_{layer}.tsv"
    threads: res("peel", "threads")
    resources:
        mem_mb=mem_image("peel"),
        runtime=res("peel", "runtime"),
    conda:
        "../envs/nemo.yaml"
    shell:
        NEMO + " peel {input.image} {input.mesh} -o {output} --t {wildcards.t} --c {wildcards.c}"
        " {params.spacing} {params.opts} {params.shift} > {log} 2>&1"
