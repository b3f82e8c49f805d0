# Report: the summary tables are report items (captions in workflow/report/); with
# report.render: true every frame and layer is also rendered by `nemo render` (pyvista,
# off-screen) into results/{dataset}/t{t}/c{c}/figures/{layer}/, shown by
# `snakemake --report report.html`.

RENDER = config["report"]["render"]


rule render:
    input:
        mesh=layer_mesh,
        layer=FRAME + "/layer_{layer}.parquet",
        directors=FRAME + "/directors_{layer}.parquet",
        order=FRAME + "/order_{layer}.parquet",
        defects=FRAME + "/defects_{layer}.parquet",
    output:
        report(
            directory(FRAME + "/figures/{layer}"),
            patterns=["{name}.png"],
            caption="../report/render.rst",
            category="Frames",
            subcategory="t{t} c{c} {layer}",
        ),
    log:
        LOGS + "/render/t{t}_c{c}_{layer}.log",
    benchmark:
        BENCH + "/render/t{t}_c{c}_{layer}.tsv"
    threads: res("render", "threads")
    resources:
        mem_mb=res("render", "mem_mb"),
        runtime=res("render", "runtime"),
    conda:
        "../envs/nemo.yaml"
    shell:
        NEMO + " render {input.mesh} --layer {input.layer} --directors {input.directors}"
        " --order {input.order} --defects {input.defects} -o {output} > {log} 2>&1"


def render_targets(name):
    if not RENDER:
        return []
    return [FRAME.format(dataset=name, t=t, c=c) + f"/figures/{layer}" for t, c, layer in layer_frames(name)]
