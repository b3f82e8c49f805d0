# Figures and report (`nemo render`, pyvista off-screen + matplotlib): per frame and layer with
# report.frames: true, per dataset (tracks, per-frame summaries) with report.summary: true.
# Both are report items, so `snakemake --report report.html` shows them with captions.

REPORT = config["report"]


def _render_inputs(wc):
    seg = seg_dir(wc)
    s = SECTIONS[wc.dataset]
    surface = layer_cfg(wc)["surface"]
    kinds = [k for k in layout.LAYER_KINDS if k != "layer" or not imported(wc.dataset, wc.layer)]
    inputs = [layer_mesh(wc)] + [frame_file(wc, layout.layer_file(kind, wc.layer)) for kind in kinds]
    if s["curvature"] is not None:
        inputs.append(f"{seg}/{layout.curvature_file(surface)}")
    if s["thickness"] is not None and s["thickness"]["from"] == surface:
        inputs.append(f"{seg}/{layout.THICKNESS}")
    return inputs


rule render:
    input:
        _render_inputs,
    output:
        report(
            directory(FRAME + "/figures/{layer}"),
            patterns=["{name}.png"],
            caption="../report/render.rst",
            category="Frames",
            subcategory="layer {layer}",
            labels={"t": "{t}", "c": "{c}", "layer": "{layer}", "figure": "{name}"},
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
        NEMO + " render {input:q} --layer {wildcards.layer} -o {output:q} > {log:q} 2>&1"


rule render_summary:
    input:
        SUMMARY + "/frames.parquet",
        SUMMARY + "/defects.parquet",
    output:
        report(
            directory(SUMMARY + "/figures"),
            patterns=["{name}.png"],
            caption="../report/render_summary.rst",
            category="Summary",
            labels={"figure": "{name}"},
        ),
    log:
        LOGS + "/render/summary.log",
    benchmark:
        BENCH + "/render/summary.tsv"
    threads: res("render", "threads")
    resources:
        mem_mb=res("render", "mem_mb"),
        runtime=res("render", "runtime"),
    conda:
        "../envs/nemo.yaml"
    shell:
        NEMO + " render --summary {input:q} -o {output:q} > {log:q} 2>&1"


def render_targets(name):
    targets = []
    if REPORT["summary"] and layer_frames(name):
        targets.append(SUMMARY.format(dataset=name) + "/figures")
    if REPORT["frames"]:
        targets += [FRAME.format(dataset=name, t=t, c=c) + f"/figures/{layer}"
                    for t, c, layer in layer_frames(name)]
    return targets
