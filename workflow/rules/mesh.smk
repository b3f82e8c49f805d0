# Surface reconstruction (method note §2): one mesh per time point from the segmented channel,
# split into inner/outer walls when the dataset's mesh.split is not none. Outputs live in
# t{t}/c{segment_channel}/ (names: nemo.layout; datasets SPLIT_MESH / SINGLE_MESH: common.smk).
# With a PSF (datasets.NAME.psf; auto by default: its z blur estimated per frame) each frame is
# deconvolved once (rule deconvolve) for the mesh and every peel of that channel, as nemo run
# deconvolves it once in memory. The file is kept (not
# temp): a temporary one would be made again for any peel rerun and would rerun the mesh with it.


rule deconvolve:
    input:
        image=image,
    output:
        frame_path(layout.DECONVOLVED),
    log:
        log_path("deconvolve/t{t}_c{c}.log"),
    benchmark:
        bench_path("deconvolve/t{t}_c{c}.tsv")
    group:
        "frame"
    conda:
        "../envs/nemo.yaml"
    threads: res("deconvolve", "threads")
    resources:
        mem_mb=mem_image("deconvolve"),
        runtime=res("deconvolve", "runtime"),
    params:
        calibration=calibration_opts,
    shell:
        nemo_shell(
            "deconvolve {input.image:q} -o {output:q} --t {wildcards.t} --c {wildcards.c}"
            " {params.calibration} > {log:q} 2>&1"
        )


if SPLIT_MESH:

    rule mesh:
        input:
            image=image,
            mask=mask_file,
            surface=surface_file,
            deconvolved=mesh_deconvolved,
        output:
            whole=frame_path(layout.MESH["whole"]),
            inner=frame_path(layout.MESH["inner"]),
            outer=frame_path(layout.MESH["outer"]),
        log:
            log_path("mesh/t{t}_c{c}.log"),
        benchmark:
            bench_path("mesh/t{t}_c{c}.tsv")
        wildcard_constraints:
            dataset=dataset_regex(SPLIT_MESH),
        group:
            "frame"
        conda:
            "../envs/nemo.yaml"
        threads: res("mesh", "threads")
        resources:
            mem_mb=mem_image("mesh"),
            runtime=res("mesh", "runtime"),
        params:
            opts=opts("mesh"),
            calibration=calibration_opts,
            deconvolved=deconvolved_opts,
            source=mesh_source_opts,
        shell:
            MESH_SHELL


if SINGLE_MESH:

    rule mesh_single:
        input:
            image=image,
            mask=mask_file,
            surface=surface_file,
            deconvolved=mesh_deconvolved,
        output:
            whole=frame_path(layout.MESH["whole"]),
        log:
            log_path("mesh/t{t}_c{c}.log"),
        benchmark:
            bench_path("mesh/t{t}_c{c}.tsv")
        wildcard_constraints:
            dataset=dataset_regex(SINGLE_MESH),
        group:
            "frame"
        conda:
            "../envs/nemo.yaml"
        threads: res("mesh", "threads")
        resources:
            mem_mb=mem_image("mesh"),
            runtime=res("mesh", "runtime"),
        params:
            opts=opts("mesh"),
            calibration=calibration_opts,
            deconvolved=deconvolved_opts,
            source=mesh_source_opts,
        shell:
            MESH_SHELL
