# Surface reconstruction (method note §2): one mesh per time point from the segmented channel,
# split into inner/outer walls when the dataset's mesh.split is not none. Outputs live in
# t{t}/c{segment_channel}/ (names: nemo.layout; datasets SPLIT_MESH / SINGLE_MESH: common.smk).


if SPLIT_MESH:

    rule mesh:
        input:
            image=image,
            mask=mask_file,
            surface=surface_file,
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
            source=mesh_source_opts,
        shell:
            MESH_SHELL


if SINGLE_MESH:

    rule mesh_single:
        input:
            image=image,
            mask=mask_file,
            surface=surface_file,
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
            source=mesh_source_opts,
        shell:
            MESH_SHELL
