# Surface reconstruction (method note §2): one mesh per time point from the segmented channel,
# split into inner/outer walls when the dataset's mesh.split is not none. Outputs live in
# t{t}/c{segment_channel}/ (names: nemo.layout).

_SPLIT = [name for name in DATA if sec(name, "mesh")["split"] != "none"]
_SINGLE = [name for name in DATA if name not in _SPLIT]


def _mesh_params():
    return dict(
        opts=opts("mesh"),
        spacing=spacing_opt,
        mask=lambda wc, input: f"--mask {shlex.quote(input.mask)}" if input.mask else "",
    )


_MESH_SHELL = (
    NEMO + " mesh {input.image:q} -o {output.whole:q} --t {wildcards.t} --c {wildcards.c}"
    " {params.spacing} {params.mask} {params.opts} > {log:q} 2>&1"
)

if _SPLIT:

    rule mesh:
        input:
            image=image,
            mask=lambda wc: DATA[wc.dataset]["mask"] or [],
        output:
            whole=FRAME + "/" + layout.MESH["whole"],
            inner=FRAME + "/" + layout.MESH["inner"],
            outer=FRAME + "/" + layout.MESH["outer"],
        wildcard_constraints:
            dataset="|".join(map(re.escape, _SPLIT)),
        params:
            **_mesh_params(),
        log:
            LOGS + "/mesh/t{t}_c{c}.log",
        benchmark:
            BENCH + "/mesh/t{t}_c{c}.tsv"
        group:
            "frame"
        threads: res("mesh", "threads")
        resources:
            mem_mb=mem_image("mesh"),
            runtime=res("mesh", "runtime"),
        conda:
            "../envs/nemo.yaml"
        shell:
            _MESH_SHELL


if _SINGLE:

    rule mesh_single:
        input:
            image=image,
            mask=lambda wc: DATA[wc.dataset]["mask"] or [],
        output:
            whole=FRAME + "/" + layout.MESH["whole"],
        wildcard_constraints:
            dataset="|".join(map(re.escape, _SINGLE)),
        params:
            **_mesh_params(),
        log:
            LOGS + "/mesh/t{t}_c{c}.log",
        benchmark:
            BENCH + "/mesh/t{t}_c{c}.tsv"
        group:
            "frame"
        threads: res("mesh", "threads")
        resources:
            mem_mb=mem_image("mesh"),
            runtime=res("mesh", "runtime"),
        conda:
            "../envs/nemo.yaml"
        shell:
            _MESH_SHELL
