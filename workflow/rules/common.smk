# Parse-time helpers of the NEMO workflow: config validation, dataset checks (read from the
# hyperstack headers, before any job starts), paths and command-line options.
# No science here: every number is computed by the `nemo` commands the rules call.

import os
import re
import shlex
import sys
from pathlib import Path

import yaml


def _fail(message):
    """Stop before any job starts with a one-paragraph message (no traceback)."""
    raise SystemExit(f"NEMO workflow: configuration error\n  {message}")


def config_error(key, message):
    _fail(f"config key '{key}': {message}")


def _warn(message):
    """A parse-time warning the user sees (Snakemake hides `warnings.warn` from a Snakefile)."""
    print(f"NEMO workflow: warning: {message}", file=sys.stderr)


# the one parameter schema (nemo/schemas/config.schema.yaml), shared with `nemo run` and the
# step commands: validated, defaults filled, analysis sections resolved per dataset
sys.path.insert(0, workflow.basedir)
from nemo import config as nconfig  # noqa: E402
from nemo import layout  # noqa: E402
from nemo.errors import NemoError  # noqa: E402
from nemo.psf import channel_psf, is_per_channel, meshes_deconvolved  # noqa: E402

try:
    _validated = nconfig.validate(config)
except NemoError as exc:
    _fail(str(exc).replace("invalid configuration\n  ", ""))
config.clear()
config.update(_validated)
if not config["datasets"]:
    config_error(
        "datasets",
        "no dataset to analyse: add one under datasets (see config/config.yaml)",
    )

# `nemo` subprocesses: the interpreter running Snakemake first on PATH (so `.venv/bin/snakemake`
# works without activating the venv), this checkout importable (conda envs via --use-conda).
sys.path.insert(0, os.path.join(workflow.basedir, "workflow", "lib"))
import job_env  # noqa: E402

job_env.prepare(workflow.basedir)
# One warm worker for the many short `python -m nemo` jobs of a local run (nemo/worker.py):
# numpy, scipy, pandas and trimesh are imported once instead of once per job. Started while
# the workflow is parsed, so its imports overlap with building the DAG; not for dry runs,
# linting or reports, and stopped in `onstart` when the jobs go to a cluster.
from nemo.worker import ENV as WORKER_ENV  # noqa: E402

_NO_JOBS = {
    "-n",
    "--dry-run",
    "--dryrun",
    "--lint",
    "--report",
    "--list-rules",
    "-l",
    "--summary",
    "--detailed-summary",
    "--dag",
    "--rulegraph",
    "--filegraph",
    "--unlock",
    "--cleanup-metadata",
}


def start_worker():
    from nemo.worker import start

    if (
        config["worker"]
        and workflow.exec_mode.name == "DEFAULT"
        and WORKER_ENV not in os.environ
        and not _NO_JOBS & set(sys.argv)
    ):
        os.environ[WORKER_ENV] = start(wait=False)


def stop_worker():
    from nemo.worker import stop

    stop(os.environ[WORKER_ENV])
    os.environ[WORKER_ENV] = "off"


start_worker()

# each job gets `threads` BLAS/OpenMP threads, so --cores N runs N single-threaded frames in parallel
NEMO = (
    "OMP_NUM_THREADS={threads} OPENBLAS_NUM_THREADS={threads} MKL_NUM_THREADS={threads} "
    "python -m nemo"
)

RESULTS = config["results"].rstrip("/")
SURFACE_FILE = layout.MESH
FRAME = layout.frame_dir(RESULTS, "{dataset}", "{t}", "{c}")
LOGS = layout.dataset_dir(RESULTS, "{dataset}", layout.LOG_DIR)
BENCH = layout.dataset_dir(RESULTS, "{dataset}", layout.BENCH_DIR)
SUMMARY = layout.dataset_dir(RESULTS, "{dataset}", layout.SUMMARY_DIR)


# ----------------------------------------------------------------------------- path patterns
# Wildcard patterns of the rules' files ({dataset}, {t}, {c} ... kept for Snakemake to fill).
def frame_path(name):
    """A file of one frame: ``results/{dataset}/t{t}/c{c}/NAME``."""
    return f"{FRAME}/{name}"


def log_path(name):
    """A job's log: ``results/{dataset}/logs/NAME``."""
    return f"{LOGS}/{name}"


def bench_path(name):
    """A job's Snakemake benchmark file: ``results/{dataset}/benchmarks/NAME``."""
    return f"{BENCH}/{name}"


def summary_path(name):
    """A file of a dataset's summary: ``results/{dataset}/summary/NAME``."""
    return f"{SUMMARY}/{name}"


def truth_path(image_path):
    """The ground truth written by `nemo synth` beside its image (``X.tif`` -> ``X.truth.json``)."""
    return f"{os.path.splitext(image_path)[0]}.truth.json"


def nemo_shell(arguments):
    """Shell command running ``nemo ARGUMENTS`` with the job's threads for BLAS/OpenMP."""
    return f"{NEMO} {arguments}"


def optional_file(flag, input, name, suffix=""):
    """``FLAG 'path'`` for an optional named input of a job; "" when the job has none."""
    path = getattr(input, name) if name in input.keys() else None
    return f"{flag} {shlex.quote(path + suffix)}" if path else ""


def _sections():
    out = {}
    for name in config["datasets"]:
        try:
            out[name] = nconfig.analysis(config, name)
        except NemoError as exc:
            _fail(f"dataset '{name}': {exc}")
    return out


#: analysis sections of each dataset (per-dataset overrides merged, surfaces resolved)
SECTIONS = _sections()


def sec(dataset, name):
    return SECTIONS[dataset][name]


def _names(key):
    names = sorted({n for s in SECTIONS.values() for n in (s[key] or {})})
    return "|".join(names) or "NONE"


wildcard_constraints:
    dataset=r"[A-Za-z0-9][A-Za-z0-9_.-]*",
    t=r"\d+",
    c=r"\d+",
    layer=_names("layers"),
    a=_names("layers"),
    b=_names("layers"),
    surface="whole|inner|outer",


# ----------------------------------------------------------------------------- options
#: Boolean keys whose command-line option is --KEY / --no-KEY (the command may default them otherwise): False is
#: spelled ``--no-KEY``, so a config's false always reaches the command.
NEGATABLE = ("adaptive", "refine")


def cli_opts(options, skip=()):
    """``{key: value}`` -> ``--key value`` (None/False omitted, True = flag, lists spread;
    False = ``--no-KEY`` for the keys of :data:`NEGATABLE`).

    Keys are sorted, so the order of keys in a config file never changes a command line
    (Snakemake reruns a job when its params change).
    """
    parts = []
    for key, value in sorted((options or {}).items()):
        if value is False and key in NEGATABLE and key not in skip:
            parts.append(f"--no-{str(key).replace('_', '-')}")
        if key in skip or value is None or value is False:
            continue
        flag = f"--{str(key).replace('_', '-')}"
        if value is True:
            parts.append(flag)
        elif isinstance(value, (list, tuple)):
            parts.append(f"{flag} {' '.join(str(v) for v in value)}")
        else:
            parts.append(f"{flag} {value}")
    return " ".join(parts)


def opts(name, skip=()):
    """Input function: the command-line options of a dataset's section ``name``."""
    return lambda wc: cli_opts(sec(wc.dataset, name), skip)


def layer_cfg(wc, layer=None):
    return sec(wc.dataset, "layers")[layer or wc.layer]


# ----------------------------------------------------------------------------- datasets
def _dataset_info(name, d):
    """Sizes of T and C: from the file's header, or from the synthetic options."""
    key = f"datasets.{name}"
    path = Path(d["path"])
    synth = d.get("synthetic")
    if path.exists():
        try:
            from nemo.io import read_info
            from nemo.errors import NemoError
        except (
            ImportError
        ) as exc:  # a Snakemake environment without nemo: trust the config
            _warn(f"cannot import nemo ({exc}); not checking {path}'s header")
            return None
        try:
            info = read_info(path)
        except NemoError as exc:
            config_error(f"{key}.path", str(exc))
        if not info.calibrated and d["spacing"] is None:
            _warn(
                f"{path} has no spatial calibration (the analysis runs in pixels); "
                f"set {key}.spacing: [dz, dy, dx] (µm)"
            )
        return info.shape
    if synth is None:
        config_error(
            f"{key}.path",
            f"file not found: {path} (relative to {os.getcwd()}); give an "
            "existing hyperstack, or a 'synthetic:' section to generate it",
        )
    return {
        "T": int(synth.get("frames", 1)),
        "C": int(synth.get("channels", 1)),
        "Z": None,
    }


def _indices(name, d, axis, size):
    try:
        return nconfig.selected_indices(name, d, axis, size)
    except NemoError as exc:
        _fail(str(exc))


def _check_surface_meshes(name, pattern, times):
    """Every analysed time point has its surface file (before any job starts)."""
    try:
        missing = [
            t for t in times if not Path(layout.surface_mesh_path(pattern, t)).exists()
        ]
    except NemoError as exc:
        config_error(f"datasets.{name}.surface_mesh", str(exc))
    if missing:
        config_error(
            f"datasets.{name}.surface_mesh",
            f"no surface file for time point(s) {missing[:10]} "
            f"(e.g. {layout.surface_mesh_path(pattern, missing[0])})",
        )


def _check_mask_header(name, path, shape, times, seg, mask_channel):
    """The mask's (Z, Y, X) size is the image's, and a mask of several time points has every analysed
    one (read from its header, before any job starts; one time point serves them all).
    """
    from nemo.io import read_info

    try:
        m = read_info(path).shape
    except NemoError as exc:
        config_error(f"datasets.{name}.mask", str(exc))
    if (m["Z"], m["Y"], m["X"]) != (shape["Z"], shape["Y"], shape["X"]):
        config_error(
            f"datasets.{name}.mask",
            f"{path} has (Z, Y, X) = {(m['Z'], m['Y'], m['X'])} but the image has "
            f"{(shape['Z'], shape['Y'], shape['X'])}; give a mask of the same size",
        )
    missing = [t for t in times if t >= m["T"]] if m["T"] > 1 else []
    if missing:
        config_error(
            f"datasets.{name}.mask",
            f"{path} has {m['T']} time points, so none for the analysed time point(s) "
            f"{missing[:10]}; give a mask of every time point (or of one, for all)",
        )
    # the mask's channel: mask_channel, else the segmented one when the mask has channels
    channel = seg if mask_channel is None else mask_channel
    if (m["C"] > 1 or mask_channel is not None) and channel >= m["C"]:
        config_error(
            f"datasets.{name}.mask_channel",
            f"{path} has {m['C']} channels (0 to {m['C'] - 1}), none is {channel}: give "
            "mask_channel, the mask's channel of the object",
        )


def _check_psf_channels(name, psf, channels, n_channels=None):
    """A per-channel psf list must cover the analysed and the segmented channels; one longer than
    the image's channels is named (often a list in the wrong order)."""
    for c in channels:
        try:
            channel_psf(psf, c)
        except NemoError as exc:
            config_error(f"datasets.{name}.psf", str(exc))
    if is_per_channel(psf) and n_channels is not None and len(psf) > n_channels:
        _warn(
            f"datasets.{name}.psf lists {len(psf)} PSFs but the image has {n_channels} "
            f"channel{'s' if n_channels != 1 else ''}: the list is in channel order, one per channel"
        )


def _datasets():
    out = {}
    for name, d in config["datasets"].items():
        shape = _dataset_info(name, d)
        seg = (
            d["segment_channel"]
            if d["segment_channel"] is not None
            else config["segment_channel"]
        )
        entry = {
            "path": d["path"],
            "spacing": d["spacing"],
            "psf": d["psf"],
            "mask": d["mask"],
            "mask_labels": d["mask_labels"],
            "mask_threshold": d["mask_threshold"],
            "mask_channel": d["mask_channel"],
            "surface_mesh": d["surface_mesh"],
            "mesh_unit": d["mesh_unit"],
            "synthetic": d["synthetic"],
            "seg": seg,
            "stack_mb": None,
        }
        if shape is None:
            if d["t"] == "all" or d["c"] == "all":
                config_error(
                    f"datasets.{name}", "cannot read the header: give t and c as lists"
                )
            entry["t"], entry["c"] = sorted(d["t"]), sorted(d["c"])
        else:
            entry["t"] = _indices(name, d, "T", shape["T"])
            entry["c"] = _indices(name, d, "C", shape["C"])
            if seg >= shape["C"]:
                key = (
                    f"datasets.{name}.segment_channel"
                    if d["segment_channel"] is not None
                    else "segment_channel"
                )
                config_error(
                    key,
                    f"channel {seg} is not in {d['path']}, which has {shape['C']} "
                    f"channel{'s' if shape['C'] != 1 else ''} (valid: 0 to {shape['C'] - 1})",
                )
            if shape.get("Z"):
                entry["stack_mb"] = shape["Z"] * shape["Y"] * shape["X"] * 4 / 1e6
        _check_psf_channels(
            name, d["psf"], sorted({*entry["c"], seg}), shape and shape.get("C")
        )
        if d["mask"] is not None and not Path(d["mask"]).exists():
            config_error(f"datasets.{name}.mask", f"file not found: {d['mask']}")
        if d["mask"] is not None and shape is not None and shape.get("Z"):
            _check_mask_header(
                name,
                d["mask"],
                shape,
                entry["t"],
                seg,
                d["mask_channel"],
            )
        if d["surface_mesh"] is not None:
            _check_surface_meshes(name, d["surface_mesh"], entry["t"])
        out[name] = entry
    paths = [e["path"] for e in out.values()]
    for p in set(paths):
        if paths.count(p) > 1 and any(
            e["synthetic"] for e in out.values() if e["path"] == p
        ):
            config_error(
                "datasets", f"two datasets generate/read the same synthetic file {p}"
            )
    return out


DATA = _datasets()


def _check_layer_channels():
    for name in DATA:
        analysed = DATA[name]["c"]
        layers = sec(name, "layers") or {}
        for layer in layers:
            if not layer_channels(name, layer):
                config_error(
                    f"layers.{layer}.channels",
                    f"{layers[layer]['channels']} holds none of the "
                    f"channels analysed in dataset '{name}' ({analysed})",
                )


# ----------------------------------------------------------------------------- resources
def res(rule, key):
    table = config["resources"]
    defaults = {"mem_mb": 2000, "runtime": 30, "threads": 1}
    value = table.get(rule, {}).get(
        key, table.get("default", {}).get(key, defaults[key])
    )
    return value


def mem_image(rule):
    """mem_mb for rules that hold one (Z, Y, X) stack: the configured value, at least 8 stacks."""

    def mem(wildcards):
        stack = DATA[wildcards.dataset]["stack_mb"] or 0
        return max(int(res(rule, "mem_mb")), int(8 * stack) + 500)

    return mem


# ----------------------------------------------------------------------------- paths
def image(wildcards):
    return DATA[wildcards.dataset]["path"]


def seg_dir(wildcards):
    return layout.frame_dir(
        RESULTS, wildcards.dataset, wildcards.t, DATA[wildcards.dataset]["seg"]
    )


def surface_mesh(wildcards, surface):
    return f"{seg_dir(wildcards)}/{layout.MESH[surface]}"


def layer_mesh(wildcards, layer=None):
    return surface_mesh(wildcards, layer_cfg(wildcards, layer)["surface"])


def frame_file(wildcards, name):
    return f"{FRAME.format(**wildcards)}/{name}"


def calibration_opts(wildcards):
    """The dataset's --spacing, if set, and the frame's channel's --psf (none where it has none: the
    commands' default is auto, as the dataset's)."""
    d = DATA[wildcards.dataset]
    psf = channel_psf(d["psf"], int(wildcards.c))
    values = {"spacing": d["spacing"], "psf": "none" if psf is None else psf}
    return " ".join(
        f"--{key} {value if isinstance(value, str) else ' '.join(str(v) for v in value)}"
        for key, value in values.items()
        if value
    )


def layer_channels(name, layer):
    """Analysed channels of dataset ``name`` that hold ``layer``."""
    chans = sec(name, "layers")[layer]["channels"]
    return [c for c in DATA[name]["c"] if chans == "all" or c in chans]


def layer_frames(name):
    """(t, c, layer) triples analysed in a dataset."""
    # sorted: params built from this list must not depend on the order of keys in the config
    return sorted(
        (t, c, layer)
        for t in DATA[name]["t"]
        for layer in (sec(name, "layers") or {})
        for c in layer_channels(name, layer)
    )


def align_frames(name):
    """(t, c, a, b): alignment pairs in the channels that hold both layers."""
    return sorted(
        (t, c, a, b)
        for t in DATA[name]["t"]
        for a, b in (sec(name, "alignment") or [])
        for c in layer_channels(name, a)
        if c in layer_channels(name, b)
    )


def morphology_files(name, t):
    """Files of the morphology of time point t: measure, curvature per surface, thickness."""
    d = layout.frame_dir(RESULTS, name, t, DATA[name]["seg"])
    s = SECTIONS[name]
    files = [
        f"{d}/{layout.measure_file(x)}"
        for x in (s["measure"]["surfaces"] or s["surfaces"])
    ]
    if s["curvature"] is not None:
        files += [f"{d}/{layout.curvature_file(x)}" for x in s["surfaces"]]
    if s["thickness"] is not None:
        files.append(f"{d}/{layout.THICKNESS}")
    return files


def summary_targets(name):
    s = SUMMARY.format(dataset=name)
    return [f"{s}/{table}" for table in layout.SUMMARY_TABLES]


_check_layer_channels()


# ----------------------------------------------------------------------------- imported directors
# A layer with `directors_from` takes its directors from another tool's files (nemo directors
# import) instead of peel + directors: no layer table, the same directors table path, so the
# order, defects, align and track rules run unchanged on it (docs/workflow.md).
def imported(dataset, layer):
    """True when the dataset's layer takes its directors from files (layers.NAME.directors_from)."""
    return bool(sec(dataset, "layers")[layer].get("directors_from"))


def directors_source(wc):
    """Input function: the file holding a frame's directors of an imported layer."""
    return nconfig.directors_from_path(
        layer_cfg(wc)["directors_from"],
        dataset=wc.dataset,
        t=int(wc.t),
        c=int(wc.c),
        layer=wc.layer,
    )


def layer_regex(names):
    return "|".join(map(re.escape, sorted(names))) or "(?!)"  # (?!): matches nothing


def _split_layer_names():
    """(imported, measured) layer names; one name is either imported or measured in every dataset,
    so that exactly one rule writes its directors tables."""
    kinds = {}
    for name in DATA:
        for layer in sec(name, "layers") or {}:
            kinds.setdefault(layer, {})[imported(name, layer)] = name
    both = {layer: k for layer, k in kinds.items() if len(k) == 2}
    for layer, k in both.items():
        config_error(
            f"layers.{layer}.directors_from",
            f"layer '{layer}' takes its directors from files in "
            f"dataset '{k[True]}' but is peeled in dataset '{k[False]}': give one of them another name",
        )
    return (
        {layer for layer, k in kinds.items() if True in k},
        {layer for layer, k in kinds.items() if False in k},
    )


def _check_directors_files():
    """Every file an imported layer needs exists (checked before any job starts)."""
    from nemo.import_directors import SUFFIXES

    for name in DATA:
        for layer, cfg in nconfig.imported_layers(SECTIONS[name]).items():
            over = "layers" in (config["datasets"][name] or {})
            prefix = f"datasets.{name}." if over else ""
            key = f"{prefix}layers.{layer}.directors_from"
            pattern = cfg["directors_from"]
            if not pattern.lower().endswith(SUFFIXES):
                config_error(
                    key,
                    f"{pattern!r}: directors are read from {', '.join(SUFFIXES)} files",
                )
            frames = [(t, c) for t, c, lay in layer_frames(name) if lay == layer]
            try:
                paths = {
                    (t, c): nconfig.directors_from_path(
                        pattern, key, dataset=name, t=t, c=c, layer=layer
                    )
                    for t, c in frames
                }
            except NemoError as exc:
                _fail(str(exc))
            missing = [
                f"{p} (t={t}, c={c})"
                for (t, c), p in paths.items()
                if not Path(p).is_file()
            ]
            if missing:
                config_error(
                    key,
                    f"{len(missing)} of {len(paths)} director file(s) of dataset '{name}' not found "
                    f"(relative to {os.getcwd()}): {', '.join(missing[:3])}{', ...' if len(missing) > 3 else ''}",
                )
            if len(set(paths.values())) < len(paths):
                _warn(
                    f"{key}: {pattern!r} names the same file for several frames (no {{t}} or {{c}}): "
                    "every frame gets the same directors"
                )


IMPORTED_LAYERS, MEASURED_LAYERS = _split_layer_names()
_check_directors_files()


# ----------------------------------------------------------------------------- per-rule inputs and options
SYNTHETIC = [name for name in DATA if DATA[name]["synthetic"]]
#: datasets whose mesh is split into inner/outer walls (rule mesh) or not (rule mesh_single)
SPLIT_MESH = [name for name in DATA if sec(name, "mesh")["split"] != "none"]
SINGLE_MESH = [name for name in DATA if name not in SPLIT_MESH]

MESH_SHELL = nemo_shell(
    "mesh {input.image:q} -o {output.whole:q} --t {wildcards.t} --c {wildcards.c}"
    " {params.calibration} {params.deconvolved} {params.source} {params.opts} > {log:q} 2>&1"
)


def dataset_regex(names):
    return "|".join(map(re.escape, names))


def mask_file(wc):
    return DATA[wc.dataset]["mask"] or []


def surface_file(wc):
    """The user's surface of this time point (datasets.NAME.surface_mesh), or none."""
    pattern = DATA[wc.dataset]["surface_mesh"]
    return layout.surface_mesh_path(pattern, int(wc.t)) if pattern else []


def mesh_source_opts(wc, input):
    """Options naming where the mesh comes from: a mask (and its labels or threshold) or a
    user's surface (and its unit)."""
    d = DATA[wc.dataset]
    out = [
        optional_file("--mask", input, "mask"),
        optional_file("--from-mesh", input, "surface"),
    ]
    if d["mask_labels"]:
        out.append("--mask-labels " + " ".join(str(int(v)) for v in d["mask_labels"]))
    if d["mask_threshold"] is not None:
        out.append(f"--mask-threshold {float(d['mask_threshold'])!r}")
    if d["mask_channel"] is not None:
        out.append(f"--mask-channel {int(d['mask_channel'])}")
    if d["surface_mesh"] and d["mesh_unit"]:
        out.append(f"--mesh-unit {shlex.quote(d['mesh_unit'])}")
    return " ".join(o for o in out if o)


def thickness_mesh(wc, end):
    """Mesh of the thickness's `from` or `to` surface."""
    return frame_file(wc, layout.MESH[sec(wc.dataset, "thickness")[end]])


def deconvolved_file(wc):
    """This frame deconvolved by the dataset's PSF (rule deconvolve), or none without a PSF.

    Not ancient(): with it Snakemake 9 reruns neither the mesh nor the peels after a new PSF
    (the deconvolve job hides their changed --psf parameter), measured."""
    psf = channel_psf(DATA[wc.dataset]["psf"], int(wc.c))
    return frame_file(wc, layout.DECONVOLVED) if psf else []


def deconvolved_opts(wc, input):
    """``--deconvolved FILE`` when the job has the deconvolved frame as an input."""
    return optional_file("--deconvolved", input, "deconvolved")


def mesh_deconvolved(wc):
    """The deconvolved frame to mesh (none from a mask, a user's surface, or psf: auto under
    mesh.edge: profile: nemo.psf.meshes_deconvolved)."""
    d = DATA[wc.dataset]
    psf = channel_psf(d["psf"], int(wc.c))
    if (
        d["mask"]
        or d["surface_mesh"]
        or not meshes_deconvolved(psf, sec(wc.dataset, "mesh")["edge"])
    ):
        return []
    return deconvolved_file(wc)


def peel_inputs(wc):
    inputs = {
        "image": image(wc),
        "mesh": layer_mesh(wc),
        "deconvolved": deconvolved_file(wc),
    }
    if layer_cfg(wc)["shift"]:
        inputs["shift"] = f"{seg_dir(wc)}/{layout.THICKNESS}"
    return inputs


def peel_opts(wc):
    layer = layer_cfg(wc)
    opts = cli_opts(
        {k: layer[k] for k in ("range", "reduce", "samples", "interp", "inward")}
    )
    if layer["shift"]:
        opts += f" --shift-fraction {layer['shift']}"
    return opts


def import_opts(wc):
    return cli_opts(nconfig.section("directors_import", layer_cfg(wc).get("import")))


def defects_inputs(wc):
    inputs = {
        "mesh": layer_mesh(wc),
        "order": frame_file(wc, layout.layer_file("order", wc.layer)),
        "directors": frame_file(wc, layout.layer_file("directors", wc.layer)),
    }
    if not imported(
        wc.dataset, wc.layer
    ):  # imported directors: no layer, no refinement pass
        inputs["layer"] = frame_file(wc, layout.layer_file("layer", wc.layer))
    d = sec(wc.dataset, "defects")
    if d["curvature_source"] == "table" and d["curvature_correction"]:
        inputs["curvature"] = (
            f"{seg_dir(wc)}/{layout.curvature_file(layer_cfg(wc)['surface'])}"
        )
    return inputs


def defects_opts(wc):
    d = sec(wc.dataset, "defects")
    return cli_opts(d, skip=("curvature_correction",)) + (
        "" if d["curvature_correction"] else " --no-curvature-correction"
    )


# ----------------------------------------------------------------------------- aggregation records
def frame_records(name):
    """One record per (t, c, layer); a dataset without layers: one per (t, surface)."""
    d = DATA[name]
    s = SECTIONS[name]

    def seg(t):
        return layout.frame_dir(RESULTS, name, t, d["seg"])

    if not s["layers"]:
        return [
            layout.frame_record(s, t, d["seg"], "", seg(t), surface=surface)
            for t in d["t"]
            for surface in s["surfaces"]
        ]
    return [
        layout.frame_record(
            s, t, c, layer, seg(t), layout.frame_dir(RESULTS, name, t, c)
        )
        for t, c, layer in layer_frames(name)
    ]


def defect_records(name):
    return [
        {k: r[k] for k in ("t", "c", "layer", "defects")}
        for r in frame_records(name)
        if r.get("defects")
    ]


def record_files(records, keys):
    return sorted({r[k] for r in records for k in keys if r.get(k)})


def align_records(name):
    return [
        {
            "t": t,
            "c": c,
            "layer_a": a,
            "layer_b": b,
            "align": f"{layout.frame_dir(RESULTS, name, t, c)}/{layout.align_file(a, b)}",
        }
        for t, c, a, b in align_frames(name)
    ]


# ----------------------------------------------------------------------------- figures and report
REPORT = config["report"]
#: summary tables previewed as HTML in the report (the Parquet files are the data)
REPORT_TABLES = ("frames", "defects", "tracks", "alignment")


def render_inputs(wc):
    seg = seg_dir(wc)
    s = SECTIONS[wc.dataset]
    surface = layer_cfg(wc)["surface"]
    kinds = [
        k
        for k in layout.LAYER_KINDS
        if k != "layer" or not imported(wc.dataset, wc.layer)
    ]
    inputs = [layer_mesh(wc)] + [
        frame_file(wc, layout.layer_file(kind, wc.layer)) for kind in kinds
    ]
    if s["curvature"] is not None:
        inputs.append(f"{seg}/{layout.curvature_file(surface)}")
    if s["thickness"] is not None and s["thickness"]["from"] == surface:
        inputs.append(f"{seg}/{layout.THICKNESS}")
    return inputs


def rendered_times(name):
    """Time points of a dataset whose frames are rendered (config key report.frames)."""
    times, choice = DATA[name]["t"], REPORT["frames"]
    if choice is False or not times:
        return []
    if choice is True or choice == "all":
        return list(times)
    if choice == "ends":
        return sorted({times[0], times[-1]})
    missing = sorted(set(choice) - set(times))
    if missing:
        config_error(
            "report.frames",
            f"time point(s) {missing} are not analysed in dataset '{name}' "
            f"(analysed: {times})",
        )
    return sorted(choice)


def _canonical(value):
    """Mappings with sorted keys (the order of keys in a config file reruns nothing)."""
    if isinstance(value, dict):
        return {k: _canonical(value[k]) for k in sorted(value)}
    if isinstance(value, list):
        return [_canonical(v) for v in value]
    return value


def report_config(name):
    """The validated configuration of one dataset (defaults filled), as written to the report:
    sections in the schema's order, keys within them sorted; the analysis keys only, so that
    changing resources or the worker reruns nothing."""
    skip = ("resources", "worker", "validation")
    cfg = {**config, "datasets": {name: config["datasets"][name]}}
    order = [k for k in nconfig.schema()["properties"] if k in cfg and k not in skip]
    return {k: _canonical(cfg[k]) for k in order}


def render_targets(name):
    targets = []
    if REPORT["summary"] and layer_frames(name):
        targets.append(summary_path("figures").format(dataset=name))
    times = rendered_times(name)
    targets += [
        frame_path(f"figures/{layer}").format(dataset=name, t=t, c=c)
        for t, c, layer in layer_frames(name)
        if t in times
    ]
    return targets


def report_targets(name):
    """The report items of a dataset besides the figures: the table previews and the config."""
    return [
        summary_path(f"{table}.html").format(dataset=name) for table in REPORT_TABLES
    ] + [summary_path("config.html").format(dataset=name)]
