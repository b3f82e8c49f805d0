# Tracking (method note §9): link defects frame to frame (laptrack, same charge only).


rule track:
    input:
        SUMMARY + "/defects_untracked.parquet",
    output:
        tracks=report(SUMMARY + "/tracks.parquet", caption="../report/tracks.rst", category="Summary"),
        defects=report(SUMMARY + "/defects.parquet", caption="../report/defects.rst", category="Summary"),
    params:
        opts=opts("tracking"),
        frames=lambda wc: " ".join(str(t) for t in DATA[wc.dataset]["t"]),
    log:
        LOGS + "/track.log",
    benchmark:
        BENCH + "/track.tsv"
    threads: res("track", "threads")
    resources:
        mem_mb=res("track", "mem_mb"),
        runtime=res("track", "runtime"),
    conda:
        "../envs/nemo.yaml"
    shell:
        NEMO + " track {input:q} -o {output.tracks:q} --linked {output.defects:q}"
        " --frames {params.frames} {params.opts} > {log:q} 2>&1"
