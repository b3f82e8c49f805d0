# Aggregation (method note §9): per-frame tables -> results/{dataset}/summary/*.parquet.


def _frame_records(name):
    d = DATA[name]
    records = []
    for t, c, layer in layer_frames(name):
        seg = f"{RESULTS}/{name}/t{t}/c{d['seg']}"
        frame = f"{RESULTS}/{name}/t{t}/c{c}"
        surface = LAYERS[layer]["surface"]
        records.append({
            "t": t, "c": c, "layer": layer, "surface": surface,
            "measure": f"{seg}/measure_{surface}.json",
            "curvature": f"{seg}/curvature_{surface}.parquet" if CURVATURE is not None else None,
            "thickness": f"{seg}/thickness.parquet" if THICKNESS is not None else None,
            "layer_table": f"{frame}/layer_{layer}.parquet",
            "directors": f"{frame}/directors_{layer}.parquet",
            "order": f"{frame}/order_{layer}.parquet",
            "defects": f"{frame}/defects_{layer}.parquet",
        })
    return records


def _record_files(records, keys):
    return sorted({r[k] for r in records for k in keys if r.get(k)})


rule aggregate_frames:
    input:
        lambda wc: _record_files(
            _frame_records(wc.dataset),
            ("measure", "curvature", "thickness", "layer_table", "directors", "order", "defects"),
        ),
    output:
        report(SUMMARY + "/frames.parquet", caption="../report/frames.rst", category="Summary"),
    params:
        kind="frames",
        records=lambda wc: _frame_records(wc.dataset),
    log:
        LOGS + "/aggregate/frames.log",
    benchmark:
        BENCH + "/aggregate/frames.tsv"
    threads: res("aggregate", "threads")
    resources:
        mem_mb=res("aggregate", "mem_mb"),
        runtime=res("aggregate", "runtime"),
    conda:
        "../envs/nemo.yaml"
    script:
        "../scripts/aggregate.py"


rule aggregate_defects:
    input:
        lambda wc: _record_files(_frame_records(wc.dataset), ("defects",)),
    output:
        SUMMARY + "/defects_untracked.parquet",
    params:
        kind="defects",
        records=lambda wc: [{k: r[k] for k in ("t", "c", "layer", "defects")}
                            for r in _frame_records(wc.dataset)],
    log:
        LOGS + "/aggregate/defects.log",
    benchmark:
        BENCH + "/aggregate/defects.tsv"
    threads: res("aggregate", "threads")
    resources:
        mem_mb=res("aggregate", "mem_mb"),
        runtime=res("aggregate", "runtime"),
    conda:
        "../envs/nemo.yaml"
    script:
        "../scripts/aggregate.py"


def _align_records(name):
    return [
        {"t": t, "c": c, "layer_a": a, "layer_b": b,
         "align": f"{RESULTS}/{name}/t{t}/c{c}/align_{a}_{b}.parquet"}
        for t, c, a, b in align_frames(name)
    ]


rule aggregate_alignment:
    input:
        lambda wc: [r["align"] for r in _align_records(wc.dataset)],
    output:
        report(SUMMARY + "/alignment.parquet", caption="../report/alignment.rst", category="Summary"),
    params:
        kind="alignment",
        records=lambda wc: _align_records(wc.dataset),
    log:
        LOGS + "/aggregate/alignment.log",
    benchmark:
        BENCH + "/aggregate/alignment.tsv"
    threads: res("aggregate", "threads")
    resources:
        mem_mb=res("aggregate", "mem_mb"),
        runtime=res("aggregate", "runtime"),
    conda:
        "../envs/nemo.yaml"
    script:
        "../scripts/aggregate.py"
