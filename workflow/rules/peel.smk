# Peeling (method note §4): one intensity value per vertex of the layer's surface, sampled along
# the normals over the layer's depth range, optionally shifted by a fraction of the thickness.


def _peel_inputs(wc):
    inputs = {"image": image(wc), "mesh": layer_mesh(wc)}
    if layer_cfg(wc)["shift"]:
        inputs["shift"] = f"{seg_dir(wc)}/{layout.THICKNESS}"
    return inputs


def _peel_opts(wc):
    layer = layer_cfg(wc)
    opts = cli_opts({k: layer[k] for k in ("range", "reduce", "samples", "interp", "inward")})
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
        shift=lambda wc, input: f"--shift {shlex.quote(input.shift + ':thickness')}" if "shift" in input.keys() else "",
    log:
        LOGS + "/peel/t{t}_c{c}_{layer}.log",
    benchmark:
        BENCH + "/peel/t{t}_c{c}_{layer}.tsv"
    group:
        "frame"
    threads: res("peel", "threads")
    resources:
        mem_mb=mem_image("peel"),
        runtime=res("peel", "runtime"),
    conda:
        "../envs/nemo.yaml"
    shell:
        NEMO + " peel {input.image:q} {input.mesh:q} -o {output:q} --t {wildcards.t} --c {wildcards.c}"
        " {params.spacing} {params.opts} {params.shift} > {log:q} 2>&1"
