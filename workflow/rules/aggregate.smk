# Aggregation (method note §9): per-frame tables -> results/{dataset}/summary/*.parquet.


def _frame_records(name):
    """One record per (t, c, layer); a dataset without layers: one per (t, surface)."""
    d = DATA[name]
    s = SECTIONS[name]
    records = []

    def morphology(t, surface):
        seg = layout.frame_dir(RESULTS, name, t, d["seg"])
        return {
            "measure": f"{seg}/{layout.measure_file(surface)}",
            "curvature": f"{seg}/{layout.curvature_file(surface)}" if s["curvature"] is not None else None,
            "thickness": f"{seg}/{layout.THICKNESS}" if s["thickness"] is not None
            and s["thickness"]["from"] == surface else None,
        }

    for t, c, layer in layer_frames(name):
        frame = layout.frame_dir(RESULTS, name, t, c)
        surface = s["layers"][layer]["surface"]
        records.append({"t": t, "c": c, "layer": layer, "surface": surface, **morphology(t, surface),
                        **{k if k != "layer" else "layer_table": f"{frame}/{layout.layer_file(k, layer)}"
                           for k in layout.LAYER_KINDS if k != "layer" or not imported(name, layer)}})
    if not s["layers"]:
        records = [{"t": t, "c": d["seg"], "layer": "", "surface": surface, **morphology(t, surface)}
                   for t in d["t"] for surface in s["surfaces"]]
    return records


def _record_files(records, keys):
    return sorted({r[k] for r in records for k in keys if r.get(k)})


rule aggregate_frames:
    input:
        lambda wc: _record_files(
            _frame_records(wc.dataset),
            ("measure", "curvature", "thickness", "layer_table", "directors", "order", "defects"),
        ),
        lambda wc: [f for t in DATA[wc.dataset]["t"] for f in morphology_files(wc.dataset, t)],
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
                            for r in _frame_records(wc.dataset) if r.get("defects")],
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
         "align": f"{layout.frame_dir(RESULTS, name, t, c)}/{layout.align_file(a, b)}"}
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
