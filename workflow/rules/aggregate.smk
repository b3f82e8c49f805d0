# Aggregation (method note §9): per-frame tables -> results/{dataset}/summary/*.parquet.
# The records naming each frame's files: frame_records, align_records (common.smk).


rule aggregate_frames:
    input:
        lambda wc: record_files(
            frame_records(wc.dataset),
            (
                "measure",
                "curvature",
                "thickness",
                "layer_table",
                "directors",
                "order",
                "defects",
            ),
        ),
        lambda wc: [
            f for t in DATA[wc.dataset]["t"] for f in morphology_files(wc.dataset, t)
        ],
    output:
        summary_path("frames.parquet"),
    log:
        log_path("aggregate/frames.log"),
    benchmark:
        bench_path("aggregate/frames.tsv")
    conda:
        "../envs/nemo.yaml"
    threads: res("aggregate", "threads")
    resources:
        mem_mb=res("aggregate", "mem_mb"),
        runtime=res("aggregate", "runtime"),
    params:
        kind="frames",
        records=lambda wc: frame_records(wc.dataset),
    script:
        "../scripts/aggregate.py"


rule aggregate_defects:
    input:
        lambda wc: record_files(frame_records(wc.dataset), ("defects",)),
        frames=summary_path("frames.parquet"),
    output:
        summary_path("defects_untracked.parquet"),
    log:
        log_path("aggregate/defects.log"),
    benchmark:
        bench_path("aggregate/defects.tsv")
    conda:
        "../envs/nemo.yaml"
    threads: res("aggregate", "threads")
    resources:
        mem_mb=res("aggregate", "mem_mb"),
        runtime=res("aggregate", "runtime"),
    params:
        kind="defects",
        records=lambda wc: defect_records(wc.dataset),
    script:
        "../scripts/aggregate.py"


rule aggregate_alignment:
    input:
        lambda wc: [r["align"] for r in align_records(wc.dataset)],
        frames=summary_path("frames.parquet"),
    output:
        summary_path("alignment.parquet"),
    log:
        log_path("aggregate/alignment.log"),
    benchmark:
        bench_path("aggregate/alignment.tsv")
    conda:
        "../envs/nemo.yaml"
    threads: res("aggregate", "threads")
    resources:
        mem_mb=res("aggregate", "mem_mb"),
        runtime=res("aggregate", "runtime"),
    params:
        kind="alignment",
        records=lambda wc: align_records(wc.dataset),
    script:
        "../scripts/aggregate.py"
