# Tracking (method note §9): link defects frame to frame (laptrack, same charge only).


rule track:
    input:
        summary_path("defects_untracked.parquet"),
    output:
        tracks=summary_path("tracks.parquet"),
        defects=summary_path("defects.parquet"),
    log:
        log_path("track.log"),
    benchmark:
        bench_path("track.tsv")
    conda:
        "../envs/nemo.yaml"
    threads: res("track", "threads")
    resources:
        mem_mb=res("track", "mem_mb"),
        runtime=res("track", "runtime"),
    params:
        opts=opts("tracking"),
        frames=lambda wc: " ".join(str(t) for t in DATA[wc.dataset]["t"]),
    shell:
        nemo_shell(
            "track {input:q} -o {output.tracks:q} --linked {output.defects:q}"
            " --frames {params.frames} {params.opts} > {log:q} 2>&1"
        )
