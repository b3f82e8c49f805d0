# Surface reconstruction (method note §2): one mesh per time point from the segmented channel,
# split into inner/outer walls when configured. Outputs live in t{t}/c{segment_channel}/.

_split = config["mesh"]["split"] != "none"


rule mesh:
    input:
        image=image,
        mask=lambda wc: DATA[wc.dataset]["mask"] or [],
    output:
        whole=FRAME + "/mesh.ply",
        **({"inner": FRAME + "/mesh.inner.ply", "outer": FRAME + "/mesh.outer.ply"} if _split else {}),
    params:
        opts=cli_opts({k: v for k, v in config["mesh"].items() if k != "split"})
        + (f" --split {config['mesh']['split']}" if _split else ""),
        spacing=spacing_opt,
        mask=lambda wc, input: f"--mask {input.mask}" if input.mask else "",
    log:
        LOGS + "/mesh/t{t}_c{c}.log",
    benchmark:
        BENCH + "/mesh/t{t}_c{c}.tsv"
    threads: res("mesh", "threads")
    resources:
        mem_mb=mem_image("mesh"),
        runtime=res("mesh", "runtime"),
    conda:
        "../envs/nemo.yaml"
    shell:
        NEMO + " mesh {input.image} -o {output.whole} --t {wildcards.t} --c {wildcards.c}"
        " {params.spacing} {params.mask} {params.opts} > {log} 2>&1"
