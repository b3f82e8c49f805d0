# Figures and report (`nemo render`, pyvista off-screen + matplotlib): per frame and layer for
# the time points chosen by report.frames (default: the first and the last), per dataset
# (tracks, per-frame summaries) with report.summary: true. The summary tables are previewed as
# HTML and the dataset's configuration is written beside them. All are report items, so
# `snakemake --report report.html` shows them with captions. Helpers: common.smk.

# two small Python jobs: on a cluster they run beside Snakemake instead of being submitted


localrules:
    report_config,
    report_tables,


rule render:
    input:
        render_inputs,
    output:
        report(
            directory(frame_path("figures/{layer}")),
            patterns=["{name}.png"],
            caption="../report/render.rst",
            category="Frames",
            subcategory="layer {layer}",
            labels={"t": "{t}", "c": "{c}", "layer": "{layer}", "figure": "{name}"},
        ),
    log:
        log_path("render/t{t}_c{c}_{layer}.log"),
    benchmark:
        bench_path("render/t{t}_c{c}_{layer}.tsv")
    conda:
        "../envs/nemo.yaml"
    threads: res("render", "threads")
    resources:
        mem_mb=res("render", "mem_mb"),
        runtime=res("render", "runtime"),
    shell:
        nemo_shell(
            "render {input:q} --layer {wildcards.layer} -o {output:q} > {log:q} 2>&1"
        )


rule render_summary:
    input:
        summary_path("frames.parquet"),
        summary_path("defects.parquet"),
    output:
        report(
            directory(summary_path("figures")),
            patterns=["{name}.png"],
            caption="../report/render_summary.rst",
            category="Summary",
            subcategory="Figures",
            labels={"dataset": "{dataset}", "figure": "{name}"},
        ),
    log:
        log_path("render/summary.log"),
    benchmark:
        bench_path("render/summary.tsv")
    conda:
        "../envs/nemo.yaml"
    threads: res("render", "threads")
    resources:
        mem_mb=res("render", "mem_mb"),
        runtime=res("render", "runtime"),
    shell:
        nemo_shell("render --summary {input:q} -o {output:q} > {log:q} 2>&1")


rule report_tables:
    input:
        frames=summary_path("frames.parquet"),
        defects=summary_path("defects.parquet"),
        tracks=summary_path("tracks.parquet"),
        alignment=summary_path("alignment.parquet"),
    output:
        frames=report(
            summary_path("frames.html"),
            caption="../report/frames.rst",
            category="Summary",
            subcategory="Tables",
            labels={"dataset": "{dataset}", "table": "frames"},
        ),
        defects=report(
            summary_path("defects.html"),
            caption="../report/defects.rst",
            category="Summary",
            subcategory="Tables",
            labels={"dataset": "{dataset}", "table": "defects"},
        ),
        tracks=report(
            summary_path("tracks.html"),
            caption="../report/tracks.rst",
            category="Summary",
            subcategory="Tables",
            labels={"dataset": "{dataset}", "table": "tracks"},
        ),
        alignment=report(
            summary_path("alignment.html"),
            caption="../report/alignment.rst",
            category="Summary",
            subcategory="Tables",
            labels={"dataset": "{dataset}", "table": "alignment"},
        ),
    log:
        log_path("report/tables.log"),
    conda:
        "../envs/nemo.yaml"
    threads: 1
    resources:
        mem_mb=res("aggregate", "mem_mb"),
        runtime=res("aggregate", "runtime"),
    params:
        max_rows=1000,
    script:
        "../scripts/report_tables.py"


rule report_config:
    output:
        yaml=summary_path("config.yaml"),
        html=report(
            summary_path("config.html"),
            caption="../report/config.rst",
            category="Configuration",
            labels={"dataset": "{dataset}"},
        ),
    log:
        log_path("report/config.log"),
    conda:
        "../envs/nemo.yaml"
    threads: 1
    resources:
        mem_mb=res("aggregate", "mem_mb"),
        runtime=res("aggregate", "runtime"),
    params:
        config=lambda wc: report_config(wc.dataset),
    script:
        "../scripts/report_config.py"
