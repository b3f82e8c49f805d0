"""One frame through the whole analysis: ``nemo run``.

:func:`run_frame` takes the workflow's own config (or None for the defaults), runs the steps of
:mod:`nemo.stages` in the order of the workflow's rules — mesh → measure, curvature,
thickness → per layer: peel → directors → order → defects (with refinement) → alignment — and
writes every file under the workflow's names (:mod:`nemo.layout`) into one folder. Every
intermediate passes through its file, as between the workflow's jobs, so the workflow and
``nemo run`` give the same numbers for the same config. ``summary.json`` records the resolved
parameters, timings, peak memory, counts, the Euler check of each layer and the quality control
of ``frames.parquet`` (``qc``: ``qc_pass`` and ``qc_flags`` per layer and object).
"""

from __future__ import annotations

import errno
import json
import os
import resource
import shutil
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from nemo import atomic, layout, objects, stages
from nemo import config as nconfig
from nemo._log import logger, step
from nemo.errors import NemoError
from nemo.psf import channel_psf, check_psf_spec, deconvolve, meshes_deconvolved


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def frame_setup(cfg: dict, dataset: str | None, image, spacing, psf=None, mask: dict | None = None) -> dict:
    """Image, spacing, PSF, mask and segmented channel of a frame: from the dataset, else given
    (``mask``: a dataset's ``mask``, ``mask_labels``, ``mask_threshold`` and ``mask_channel``, which
    replace the dataset's)."""
    if dataset is None and image is None and len(cfg["datasets"]) == 1:
        dataset = next(iter(cfg["datasets"]))
    d = cfg["datasets"].get(dataset, {}) if dataset is not None else {}
    if dataset is not None and dataset not in cfg["datasets"]:
        raise NemoError(f"dataset {dataset!r} is not in the config (datasets: "
                        f"{', '.join(cfg['datasets']) or 'none'})")
    image = image if image is not None else d.get("path")
    if image is None:
        raise NemoError("give an image (or a config with a dataset and --dataset NAME)")
    seg = d.get("segment_channel")
    m = mask if mask is not None else d
    return {"dataset": dataset, "image": str(image), "spacing": spacing or d.get("spacing"),
            "psf": check_psf_spec(psf if psf is not None else d.get("psf", nconfig.dataset_default("psf")), "psf"),
            "mask": m.get("mask"), "mask_labels": m.get("mask_labels"), "mask_threshold": m.get("mask_threshold"),
            "mask_channel": m.get("mask_channel"),
            "surface_mesh": d.get("surface_mesh"), "mesh_unit": d.get("mesh_unit"),
            "seg": cfg["segment_channel"] if seg is None else seg}


def check_selection(cfg: dict, frame: dict, t: int, c: int) -> None:
    """Refuse a dataset whose ``t``/``c`` selection the image does not have (as the workflow does);
    warn when the frame asked for is not in it (the workflow would not analyse it)."""
    if frame["dataset"] is None or not Path(frame["image"]).exists():
        return
    from nemo.io import read_info

    d, shape = cfg["datasets"][frame["dataset"]], read_info(frame["image"]).shape
    for axis, asked in (("T", t), ("C", c)):
        selected = nconfig.selected_indices(frame["dataset"], {**d, "path": frame["image"]}, axis, shape[axis])
        if asked not in selected:
            logger.warning("%s=%d is not in datasets.%s.%s %s: analysing it as asked (the workflow analyses those)",
                           axis.lower(), asked, frame["dataset"], axis.lower(), selected)


def run_frame(
    image: str | os.PathLike | None,
    outdir: str | os.PathLike,
    config: dict | str | os.PathLike | None = None,
    t: int = 0,
    c: int = 0,
    spacing: tuple[float, float, float] | None = None,
    dataset: str | None = None,
    psf: tuple[float, float, float] | str | None = None,
    mask: dict | None = None,
    layers: bool = True,
) -> dict:
    """Analyse one (t, c) frame into ``outdir``.

    Parameters
    ----------
    image : path-like or None
        Hyperstack (None: the path of ``dataset`` in the config).
    outdir : path-like
        Output folder (created); file names from :mod:`nemo.layout`.
    config : dict or path-like, optional
        The workflow's config (a dict or its YAML file); None = the schema's defaults.
    t, c : int
        Time point and analysed channel; the mesh comes from the segmented channel.
    spacing : (dz, dy, dx), optional
        Voxel size overriding the file's (and the dataset's) calibration.
    dataset : str, optional
        Take image, spacing, PSF, mask, segmented channel and section overrides from
        ``datasets.NAME``.
    psf : (σz, σy, σx), "auto" or "none", optional
        The PSF's standard deviations, overriding the dataset's (:mod:`nemo.psf`: the image is
        deconvolved by it before meshing and peeling; ``"auto"``, the default without a
        dataset, estimates its z blur from the image, :func:`nemo.psf.estimate_psf`;
        ``"none"`` deconvolves nothing), for every channel; a list of them per channel, in
        channel order, gives each channel its own, as ``datasets.NAME.psf`` does
        (:func:`nemo.psf.channel_psf`): the mesh takes the segmented channel's, the peels
        channel ``c``'s.
    mask : dict, optional
        ``mask`` (the segmentation's file), ``mask_labels``, ``mask_threshold``, ``mask_channel``
        as a dataset gives them, replacing the dataset's (``nemo run --mask``).
    layers : bool
        False: the morphology only, the config's (and the dataset's) layers and alignment
        dropped (``nemo run --no-layers``, as ``layers: {}``).

    Returns
    -------
    dict
        The run summary (also written to ``summary.json``).

    Notes
    -----
    The run writes into a hidden folder beside ``outdir`` and moves its files into ``outdir``
    only when every step succeeded: a failed or interrupted run leaves earlier results intact.
    """
    cfg = nconfig.load(config) if not isinstance(config, dict) else nconfig.validate(config)
    frame = frame_setup(cfg, dataset, image, spacing, psf, mask)
    check_selection(cfg, frame, t, c)
    sections = _analysis(cfg, frame["dataset"], layers)
    final = Path(outdir).resolve()  # `-o .`, `-o a/..` and symlinked folders: stage beside the real one
    _check_imports_outside(sections, final, frame["dataset"], t, c)
    out = _staging_folder(final)
    try:
        summary = _run_in(out, final, cfg, frame, sections, t, c)
        _publish(out, final, summary["files"])
    finally:
        shutil.rmtree(out, ignore_errors=True)  # on failure the previous results in `final` stay
    logger.info("nemo run: %d layer(s) in %.1f s, peak memory %.0f MB", len(summary["layers"]),
                summary["total_s"], summary["peak_rss_mb"])
    return summary


def _staging_folder(final: Path) -> Path:
    """A fresh, empty folder beside ``final`` where a run writes until it succeeds."""
    if final.exists() and not final.is_dir():
        raise NemoError(f"the output {final} is a file: give a folder (-o OUTDIR)")
    stage = atomic.make_folder(final.parent) / f".{final.name}.partial{os.getpid()}"
    for old in final.parent.glob(f".{final.name}.partial*"):  # left by a killed run (its process is gone)
        pid = old.name.rpartition(".partial")[2]
        if old != stage and pid.isdigit() and not _alive(int(pid)):
            shutil.rmtree(old, ignore_errors=True)
    shutil.rmtree(stage, ignore_errors=True)
    stage.mkdir()
    return stage


def _alive(pid: int) -> bool:
    """Whether a process with this id runs (on this machine)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def _publish(stage: Path, final: Path, written: list[str]) -> None:
    """Move a successful run's files from ``stage`` into ``final``; drop the stale ones there."""
    final.mkdir(parents=True, exist_ok=True)
    for name in [*written, layout.SUMMARY_JSON]:
        try:
            os.replace(stage / name, final / name)
        except OSError as exc:
            if exc.errno != errno.EXDEV:
                raise
            shutil.move(stage / name, final / name)  # another file system: copy, then remove
    _remove_stale(final, written)


def _check_imports_outside(sections: dict, final: Path, dataset: str | None, t: int, c: int) -> None:
    """Refuse a layer whose ``directors_from`` file lies in the output folder (it would be replaced)."""
    for name, layer in (sections["layers"] or {}).items():
        if layer.get("directors_from"):
            path = Path(nconfig.directors_from_path(layer["directors_from"], dataset=dataset or "", t=t, c=c,
                                                    layer=name)).resolve()
            if path.parent == final:
                raise NemoError(f"layers.{name}.directors_from {path} lies in the output folder {final}, where "
                                "nemo run writes its results: move it, or choose another output folder")


def _run_in(out: Path, final: Path, cfg: dict, frame: dict, sections: dict, t: int, c: int) -> dict:
    """The body of :func:`run_frame`: files written into ``out``, provenance naming ``final``."""
    from nemo.io import read_stack

    timings: dict[str, float] = {}
    start = time.perf_counter()

    @contextmanager
    def timed(name: str):
        t0 = time.perf_counter()
        with step(name):
            yield
        timings[name] = round(timings.get(name, 0.0) + time.perf_counter() - t0, 3)

    sp = tuple(frame["spacing"]) if frame["spacing"] else None
    with timed("read"):
        volume, info = read_stack(frame["image"], t, frame["seg"], spacing=sp)
    mask, mask_regions = _mesh_source(frame, t, volume.shape, sections, info.spacing)
    summary = {"image": frame["image"], "dataset": frame["dataset"], "t": t, "c": c,
               "segment_channel": frame["seg"], "spacing": list(info.spacing), "unit": info.unit,
               "outdir": str(final)}
    written: list[str] = []
    layers = {name: layer for name, layer in (sections["layers"] or {}).items()
              if layer["channels"] == "all" or c in layer["channels"]}
    peels = any(not layer.get("directors_from") for layer in layers.values())
    psf_seg, psf_c = channel_psf(frame["psf"], frame["seg"]), channel_psf(frame["psf"], c)
    meshed = mask is None and not frame["surface_mesh"] and meshes_deconvolved(psf_seg, sections["mesh"]["edge"])
    sharp = _deconvolved(volume, info, psf_seg, timed, meshed or (peels and c == frame["seg"]))
    meshes, mesh_params = morphology_frame(volume, info, mask, sections, out, written, timed, final=final,
                                           psf=psf_seg, deconvolved=sharp, frame={"t": t, "c": frame["seg"]},
                                           mask_regions=mask_regions)
    if c != frame["seg"]:
        with timed("read"):
            volume, info = read_stack(frame["image"], t, c, spacing=sp)
        sharp = _deconvolved(volume, info, psf_c, timed, peels)
    results = {name: layer_frame(name, layer, volume, info, meshes, sections, out, written, timed,
                                 prov={"image": frame["image"], "t": t, "c": c, "unit": info.unit},
                                 final=final, dataset=frame["dataset"], psf=psf_c, deconvolved=sharp)
               for name, layer in layers.items()}
    del volume, sharp
    pairs = [(a, b) for a, b in sections["alignment"] or [] if a in results and b in results]
    for a, b in pairs:
        align_frame(a, b, meshes[layers[a]["surface"]], out, written)
    frames = _frame_rows(out, sections, layers, t, c, frame["seg"])
    summary.update(config=sections, mesh=mesh_params, layers=results, files=sorted(written),
                   alignment=_alignment_rows(out, pairs, t, c, frames), qc=_quality(frames),
                   timings_s=timings, total_s=round(time.perf_counter() - start, 3),
                   peak_rss_mb=round(_peak_rss_mb(), 1))
    atomic.write_json(out / layout.SUMMARY_JSON, summary)
    return summary


def _frame_rows(out: Path, sections: dict, layers: dict, t: int, c: int, seg: int):
    """The frame's rows of the workflow's ``frames.parquet`` (:func:`nemo.summary.frame_summary` on the
    files just written): one per layer (per surface without layers) and object."""
    from nemo.summary import frame_summary

    records = [layout.frame_record(sections, t, c, name, str(out), str(out)) for name in layers]
    if not sections["layers"]:
        records = [layout.frame_record(sections, t, seg, "", str(out), surface=surface)
                   for surface in sections["surfaces"]]
    return frame_summary(records)


def _quality(frames) -> list[dict]:
    """The frame's quality control, as the workflow's ``frames.parquet`` has it: one record per
    layer (per surface without layers) and object, with ``qc_pass`` and ``qc_flags``."""
    return [{"layer": r.layer, "surface": r.surface, "object": int(r.object), "qc_pass": bool(r.qc_pass),
             "qc_flags": str(r.qc_flags)} for r in frames.itertuples()]


def _alignment_rows(out: Path, pairs: list, t: int, c: int, frames) -> list[dict]:
    """The frame's rows of the workflow's ``alignment.parquet`` (:func:`nemo.summary.alignment_summary`),
    NaN as None."""
    from nemo.summary import alignment_summary

    records = [{"t": t, "c": c, "layer_a": a, "layer_b": b, "align": out / layout.align_file(a, b)} for a, b in pairs]
    rows = alignment_summary(records, frames).to_dict("records")
    return [{k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in r.items()} for r in rows]


def _deconvolved(volume, info, psf, timed, needed: bool):
    """The channel deconvolved by ``psf`` and its record (:func:`nemo.psf.deconvolve`), made once for
    the mesh and every peel of it (as the workflow's deconvolve rule makes it once for its mesh and
    peel rules); None when no PSF is given or nothing needs it."""
    if psf is None or not needed:
        return None
    with timed("deconvolve"):
        return deconvolve(volume, info.spacing, psf)


def _analysis(cfg: dict, dataset: str | None, layers: bool) -> dict:
    """The analysis sections (:func:`nemo.config.analysis`), without layers and alignment when not ``layers``."""
    if not layers:
        cfg = {**cfg, "layers": {}, "alignment": []}
        if dataset is not None and dataset in (cfg.get("datasets") or {}):
            cfg["datasets"] = {**cfg["datasets"], dataset: {**cfg["datasets"][dataset], "layers": {}, "alignment": []}}
    return nconfig.analysis(cfg, dataset)


def resolved_config(image, config=None, t: int = 0, c: int = 0, spacing=None, dataset: str | None = None,
                    psf=None, mask: dict | None = None, layers: bool = True) -> dict:
    """The analysis sections with every data-derived default as the number this frame gets.

    Meshes the frame (nothing is written); per surface and per layer where a default depends
    on the mesh (curvature radius, director patch radius, pixel and count, averaging radius,
    defect suppression and contour radii, tracking distance). With several objects
    (``mesh.keep: all``) each layer's ``objects`` lists every object's lengths. ``layers``: as
    :func:`run_frame`'s (False: the morphology's sections only).
    """
    from nemo.defects import CONTOUR_PER_AVERAGING
    from nemo.io import read_stack

    cfg = nconfig.load(config) if not isinstance(config, dict) else nconfig.validate(config)
    frame = frame_setup(cfg, dataset, image, spacing, psf, mask)
    check_selection(cfg, frame, t, c)
    sections = _analysis(cfg, frame["dataset"], layers)
    sp = tuple(frame["spacing"]) if frame["spacing"] else None
    volume, info = read_stack(frame["image"], t, frame["seg"], spacing=sp)
    mask, mask_regions = _mesh_source(frame, t, volume.shape, sections, info.spacing)  # as run_frame's
    meshes, sections["mesh"] = _mesh_or_import(volume, info, mask, sections["mesh"],
                                               psf=channel_psf(frame["psf"], frame["seg"]), mask_regions=mask_regions)
    del volume, mask
    if sections["curvature"] is not None:
        sections["curvature"] = {s: stages.curvature_defaults(meshes[s], sections["curvature"])
                                 for s in sections["surfaces"]}
    def lengths(dp: dict) -> dict:
        radius = sections["order"]["radius"] or stages.ORDER_PER_PATCH * dp["nominal_radius"]
        fp = nconfig.section("defects", sections["defects"])
        fp["min_distance"] = fp["min_distance"] or radius
        fp["contour_radius"] = fp["contour_radius"] or CONTOUR_PER_AVERAGING * radius
        return {"directors": dp, "order": {**sections["order"], "radius": radius}, "defects": fp}

    per_layer = {}
    for name, layer in (sections["layers"] or {}).items():
        dp = stages.directors_defaults(meshes[layer["surface"]], sections["directors"])
        per_layer[name] = lengths(dp)  # several objects: the first's here, each object's in `objects`
        if dp.get("objects"):
            per_layer[name]["objects"] = [{"object": o["object"], **lengths(o)} for o in dp["objects"]]
    sections["resolved_per_layer"] = per_layer
    if per_layer:
        sections["tracking"] = stages.tracking_distance(sections["tracking"],
                                                        [v["defects"] for v in per_layer.values()])
    sections.update(image=frame["image"], t=t, c=c, spacing=list(info.spacing), unit=info.unit,
                    psf=channel_psf(frame["psf"], c))
    return json.loads(json.dumps(sections, default=atomic.json_default))


def _mesh_source(frame: dict, t: int, shape: tuple, sections: dict, spacing):
    """The frame's mask and the voxels of its merged labels (:func:`nemo.io.read_mask`), or (None, None);
    a user's surface is noted in ``sections["mesh"]``."""
    from nemo.io import read_mask

    if frame["surface_mesh"]:
        sections["mesh"] = {**sections["mesh"], "surface_mesh": layout.surface_mesh_path(frame["surface_mesh"], t),
                            "mesh_unit": frame["mesh_unit"]}
    if not frame["mask"]:
        return None, None
    return read_mask(frame["mask"], t, frame["seg"], shape, labels=frame["mask_labels"],
                     threshold=frame["mask_threshold"], channel=frame["mask_channel"],
                     apart=stages.mask_label_gap(shape, spacing, sections.get("mesh")), with_regions=True)


def _mesh_or_import(volume, info, mask, section: dict, psf=None, deconvolved=None, mask_regions=None):
    """The frame's meshes: reconstructed from the image, or a user's surface checked against it."""
    section = dict(section)
    path, mesh_unit = section.pop("surface_mesh", None), section.pop("mesh_unit", None)
    if path is None:
        return stages.mesh(volume, info.spacing, section, mask=mask, unit=info.unit, psf=psf, deconvolved=deconvolved,
                           mask_regions=mask_regions)
    return stages.import_mesh(path, volume, info.spacing, section, unit=info.unit, mesh_unit=mesh_unit)


def morphology_frame(volume, info, mask, sections, out: Path, written: list, timed, final: Path | None = None,
                     psf=None, deconvolved=None, frame: dict | None = None, mask_regions=None):
    """Mesh, measure, curvature and thickness of a time point (the workflow's mesh/morphology rules).

    Files go to ``out``; provenance names them in ``final`` (default ``out``), where they end up.
    ``frame``: the time point and channel meshed (``t``, ``c``), recorded in the meshes' parameters.
    ``mask_regions``: :func:`nemo.stages.mesh`'s (the voxels of a mask's merged labels).
    """
    final = final or out
    from nemo.mesh import load_mesh, save_mesh
    from nemo.tables import write_table

    with timed("mesh"):
        meshes, params = _mesh_or_import(volume, info, mask, sections["mesh"], psf=psf, deconvolved=deconvolved,
                                         mask_regions=mask_regions)
        params.update(frame or {})
        stages.stamp_walls(meshes, params)  # again, with the frame's t and c
        for name, m in meshes.items():
            save_mesh(m, out / layout.MESH[name])
            written.append(layout.MESH[name])
        # read back, as the workflow's next jobs do (PLY stores float32 vertices)
        meshes = {name: load_mesh(out / layout.MESH[name]) for name in meshes}
    for surface in sections["measure"]["surfaces"] or sections["surfaces"]:
        with timed("measure"):
            atomic.write_json(out / layout.measure_file(surface), stages.measure(meshes[surface]))
        written.append(layout.measure_file(surface))
    if sections["curvature"] is not None:
        done = {}  # an object of one wall has inner = outer = whole: its curvature is computed once
        for surface in sections["surfaces"]:
            same = next((k for k in done if _same_mesh(meshes[k], meshes[surface])), None)
            with timed("curvature"):
                df, cp = done[same] if same else stages.curvature(meshes[surface], sections["curvature"])
            done[surface] = (df, cp)
            write_table(df, out / layout.curvature_file(surface), command="curvature",
                        mesh=str(final / layout.MESH[surface]), n_vertices=len(df), parameters=cp,
                        unit=info.unit)
            written.append(layout.curvature_file(surface))
            params[f"curvature_{surface}"] = cp
    th = sections["thickness"]
    if th is not None:
        with timed("thickness"):
            df, tp = stages.thickness(meshes[th["from"]], meshes[th["to"]], th)
        write_table(df, out / layout.THICKNESS, command="thickness", mesh=str(final / layout.MESH[th["from"]]),
                    n_vertices=len(df), parameters=tp, unit=info.unit)
        written.append(layout.THICKNESS)
    return meshes, params


def _same_mesh(a, b) -> bool:
    """Whether two meshes have the same vertices and faces (the walls of a one-wall object)."""
    return np.array_equal(a.faces, b.faces) and np.array_equal(a.vertices, b.vertices)


def layer_frame(name, layer, volume, info, meshes, sections, out: Path, written: list, timed, prov,
                final: Path | None = None, dataset: str | None = None, psf=None, deconvolved=None) -> dict:
    """Peel → directors → order → defects of one layer (the workflow's per-layer rules).

    A layer with ``directors_from`` imports its directors from that file instead of peel →
    directors (the workflow's ``directors_import`` rule). Files go to ``out``; provenance names
    them in ``final`` (default ``out``), where they end up. ``psf``: the PSF the peel deconvolves
    the volume by; ``deconvolved``: that deconvolved volume and its record, when already made.
    """
    from nemo.mesh import mean_edge_length
    from nemo.tables import field_on_vertices, read_provenance, read_table, write_table

    surface = layer["surface"]
    mesh = meshes[surface]
    n = len(mesh.vertices)
    prov = {**prov, "mesh": str((final or out) / layout.MESH[surface]), "n_vertices": n}

    def save(kind, df, **extra):
        path = out / (layout.refined_file(name) if kind == "refined" else layout.layer_file(kind, name))
        write_table(df, path, command=kind, layer_name=name, **prov, **extra)
        written.append(path.name)
        return path

    if layer.get("directors_from"):
        ddf, dp, points = _imported_directors(name, layer, mesh, prov["t"], prov["c"], dataset, timed)
        dir_path = save("directors", ddf, parameters=dp, points=points)
        lp, intensity = None, None  # no layer table, no refinement pass (as the workflow's rules)
    else:
        shift = shift_out = None
        if layer["shift"]:
            th = read_table(out / layout.THICKNESS, "thickness", n_vertices=n)
            shift = field_on_vertices(th, "thickness", n, layout.THICKNESS, exact=True)
            shift_out = field_on_vertices(th, "beyond_view", n, layout.THICKNESS) == 1.0 if "beyond_view" in th else None
        with timed("peel"):
            ldf, lp = stages.peel(volume, info.spacing, mesh, layer, shift=shift, psf=psf, deconvolved=deconvolved,
                                  shift_beyond_view=shift_out)
        layer_path = save("layer", ldf, parameters=lp)
        intensity = field_on_vertices(read_table(layer_path, "layer", n_vertices=n), "intensity", n, layer_path,
                                      exact=True)
        with timed("directors"):
            ddf, dp = stages.directors(mesh, intensity, sections["directors"])
        dir_path = save("directors", ddf, parameters=dp)
    ddf, dp = read_table(dir_path, "directors", n_vertices=n), read_provenance(dir_path)["parameters"]
    with timed("order"):
        odf, op = stages.order(mesh, ddf, sections["order"], patch_radius=objects.values(dp, "nominal_radius"))
    order_path = save("order", odf, parameters=op, radius=op["radius"])
    odf = read_table(order_path, "order", n_vertices=n)
    k = None
    dsec = sections["defects"]
    if dsec["curvature_source"] == "table" and sections["curvature"] is not None:
        k = field_on_vertices(read_table(out / layout.curvature_file(surface), "curvature", n_vertices=n), "K",
                              n, layout.curvature_file(surface), exact=True)
    with timed("defects"):
        fdf, extra, fp = stages.defects(mesh, odf, ddf, dsec, avg_radius=objects.values(op, "radius"), curvature=k,
                                        intensity=intensity, director_params=dp)
    save("defects", fdf, euler_check=fdf.attrs["euler_check"], parameters=fp,
         find_parameters=fdf.attrs["parameters"])
    if dsec["refine_directors"] > 0:
        save("refined", extra if extra is not None else ddf.iloc[:0], parameters=dp)
    s = odf["S"].to_numpy()
    s = s[np.isfinite(s)]  # a layer without directors has no S anywhere (None in the JSON)
    return {"surface": surface, "vertices": n, "mean_edge": mean_edge_length(mesh),
            "peel": lp, "directors": dp, "order": op, "defects_parameters": fp,
            "n_directors": int(len(ddf)), "S": {"mean": float(s.mean()) if s.size else None,
                                          "median": float(np.median(s)) if s.size else None},
            "defects": fdf[["x", "y", "z", "charge", "charge_rounded", "S"]].to_dict(orient="records"),
            "euler_check": fdf.attrs["euler_check"]}


def _imported_directors(name, layer, mesh, t: int, c: int, dataset: str | None, timed):
    """Directors of a layer with ``directors_from`` (the workflow's ``directors_import`` rule).

    Returns the directors table, its parameters and the file they came from.
    """
    from nemo.import_directors import read_points

    path = nconfig.directors_from_path(layer["directors_from"], f"layers.{name}.directors_from",
                                       dataset=dataset or "", t=t, c=c, layer=name)
    with timed("directors"):
        ddf, dp = stages.import_directors(mesh, read_points(path), layer.get("import"), source=path)
    return ddf, dp, path


def align_frame(a: str, b: str, mesh_a, out: Path, written: list) -> None:
    """c = cos 2Δθ between the directors of layers a and b, and c_avg between their averaged
    directors (the workflow's align rule), written to the frame's ``align_A_B.parquet``."""
    from nemo.order import alignment
    from nemo.tables import read_table, write_table

    n = len(mesh_a.vertices)
    da = read_table(out / layout.layer_file("directors", a), "directors", n_vertices=n)
    db = read_table(out / layout.layer_file("directors", b), "directors")
    orders = {f"order_{k}": read_table(out / layout.layer_file("order", name), "order") for k, name in (("a", a), ("b", b))}
    df = alignment(da, db, mesh_a=mesh_a, **orders)
    write_table(df, out / layout.align_file(a, b), command="align", n_vertices=n, max_distance=None)
    written.append(layout.align_file(a, b))


def _remove_stale(out: Path, written: list[str]) -> None:
    """Remove result files of an earlier run that this (successful) run did not write."""
    keep = set(written) | {layout.SUMMARY_JSON}
    for path in out.iterdir():
        name = path.name
        suffix = Path(name).suffix
        ours = (name in layout.MESH.values() or name == layout.THICKNESS
                or (name.startswith("measure_") and suffix == ".json")
                or (suffix == ".parquet" and (name.startswith(("curvature_", "refined_", "align_"))
                                              or any(name.startswith(kind + "_") for kind in layout.LAYER_KINDS))))
        if ours and path.is_file() and name not in keep and not name.startswith("."):
            path.unlink()
