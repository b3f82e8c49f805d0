# Parse-time helpers of the NEMO workflow: config validation, dataset checks (read from the
# hyperstack headers, before any job starts), paths and command-line options.
# No science here: every number is computed by the `nemo` commands the rules call.

import os
import sys
import warnings
from pathlib import Path

import yaml
from snakemake.exceptions import WorkflowError
from snakemake.utils import validate

SCHEMA = os.path.join(workflow.basedir, "workflow", "schemas", "config.schema.yaml")


def _fail(message):
    """Stop before any job starts with a one-paragraph message (no traceback)."""
    raise SystemExit(f"NEMO workflow: configuration error\n  {message}")


def config_error(key, message):
    _fail(f"config key '{key}': {message}")


def _validate_config():
    try:
        validate(config, SCHEMA)
    except WorkflowError:
        # re-validate to list every problem with the path of its key (dotted)
        import jsonschema

        with open(SCHEMA) as fh:
            schema = yaml.safe_load(fh)
        errors = sorted(
            jsonschema.Draft202012Validator(schema).iter_errors(config),
            key=lambda e: list(map(str, e.absolute_path)),
        )
        lines = []
        for e in errors:
            key = ".".join(str(p) for p in e.absolute_path) or "(top level)"
            msg = e.message
            if e.validator == "oneOf" and e.context:
                msg = f"{e.instance!r} is not valid: " + "; or ".join(sorted({c.message for c in e.context}))
            if e.validator == "pattern" and e.schema_path and "propertyNames" in e.schema_path:
                msg = (f"the name {e.instance!r} is not allowed: use letters, digits, '-' "
                       f"(and '_', '.' in dataset names), starting with a letter or digit")
            lines.append(f"config key '{key}': {msg}")
        _fail("\n  ".join(lines or ["unknown schema error"])
              + "\n  (schema: workflow/schemas/config.schema.yaml; keys: docs/workflow.md)")


_validate_config()

# `nemo` subprocesses: the interpreter running Snakemake first on PATH (so `.venv/bin/snakemake`
# works without activating the venv), this checkout importable (conda envs via --use-conda).
_bindir = os.path.dirname(sys.executable)
if _bindir not in os.environ.get("PATH", "").split(os.pathsep)[:1]:
    os.environ["PATH"] = _bindir + os.pathsep + os.environ.get("PATH", "")
os.environ["PYTHONPATH"] = os.pathsep.join(
    p for p in (workflow.basedir, os.environ.get("PYTHONPATH")) if p
)
# each job gets `threads` BLAS/OpenMP threads, so --cores N runs N single-threaded frames in parallel
NEMO = (
    "OMP_NUM_THREADS={threads} OPENBLAS_NUM_THREADS={threads} MKL_NUM_THREADS={threads} "
    "python -m nemo"
)

RESULTS = config["results"].rstrip("/")
SURFACE_FILE = {"whole": "mesh.ply", "inner": "mesh.inner.ply", "outer": "mesh.outer.ply"}
FRAME = RESULTS + "/{dataset}/t{t}/c{c}"
LOGS = RESULTS + "/{dataset}/logs"
BENCH = RESULTS + "/{dataset}/benchmarks"
SUMMARY = RESULTS + "/{dataset}/summary"
LAYERS = config["layers"]
ALIGN_PAIRS = [tuple(p) for p in config["alignment"]]
CURVATURE = config["curvature"]
THICKNESS = config["thickness"]

wildcard_constraints:
    dataset=r"[A-Za-z0-9][A-Za-z0-9_.-]*",
    t=r"\d+",
    c=r"\d+",
    layer="|".join(map(str, LAYERS)) or "NONE",
    a="|".join(map(str, LAYERS)) or "NONE",
    b="|".join(map(str, LAYERS)) or "NONE",
    surface="whole|inner|outer",


# ----------------------------------------------------------------------------- options
def cli_opts(options, skip=()):
    """``{key: value}`` -> ``--key value`` (None/False omitted, True = flag, lists spread).

    Keys are sorted, so the order of keys in a config file never changes a command line
    (Snakemake reruns a job when its params change).
    """
    parts = []
    for key, value in sorted(options.items()):
        if key in skip or value is None or value is False:
            continue
        flag = "--" + str(key).replace("_", "-")
        if value is True:
            parts.append(flag)
        elif isinstance(value, (list, tuple)):
            parts.append(flag + " " + " ".join(str(v) for v in value))
        else:
            parts.append(f"{flag} {value}")
    return " ".join(parts)


# ----------------------------------------------------------------------------- layers, surfaces
def _check_layers():
    split = config["mesh"]["split"]
    for name, layer in LAYERS.items():
        dmin, dmax = layer["range"]
        if not dmax > dmin:
            config_error(f"layers.{name}.range", f"[{dmin}, {dmax}] needs d_max > d_min (µm)")
        if layer["shift"]:
            if THICKNESS is None:
                config_error(f"layers.{name}.shift",
                             "shifting by a fraction of the thickness needs a 'thickness' section")
            if layer["surface"] != THICKNESS["from"]:
                config_error(
                    f"layers.{name}.shift",
                    f"the thickness is measured on the '{THICKNESS['from']}' surface but this "
                    f"layer is peeled from '{layer['surface']}'; set thickness.from to "
                    f"'{layer['surface']}' or shift: 0",
                )
    needed = {layer["surface"] for layer in LAYERS.values()}
    if THICKNESS is not None:
        needed |= {THICKNESS["from"], THICKNESS["to"]}
        if THICKNESS["from"] == THICKNESS["to"]:
            config_error("thickness.to", f"must differ from thickness.from ('{THICKNESS['from']}')")
    if config["measure"]["surfaces"]:
        needed |= set(config["measure"]["surfaces"])
    if split == "none" and needed & {"inner", "outer"}:
        config_error("mesh.split", f"is 'none' but the surfaces {sorted(needed - {'whole'})} are used "
                                   "by layers/thickness: set mesh.split: centre (or axis)")
    if split == "axis" and not config["mesh"]["axis"]:
        config_error("mesh.axis", "mesh.split: axis needs mesh.axis: [x, y, z]")
    for i, pair in enumerate(ALIGN_PAIRS):
        for name in pair:
            if name not in LAYERS:
                config_error(f"alignment.{i}", f"layer '{name}' is not defined under 'layers' "
                                               f"(defined: {', '.join(LAYERS)})")
        if pair[0] == pair[1]:
            config_error(f"alignment.{i}", f"aligns layer '{pair[0]}' with itself")
    return sorted(needed)


def _check_required():
    """Options the commands need but that have no data-independent default."""
    if config["directors"]["patch_radius"] is None and config["directors"]["patch_k"] is None:
        config_error("directors.patch_radius", "give directors.patch_radius (µm) or directors.patch_k")
    if config["order"]["radius"] is None:
        config_error("order.radius", "the averaging radius (µm) is required, e.g. 2-3 x directors.patch_radius")
    if CURVATURE is not None and CURVATURE["radius"] is None:
        config_error("curvature.radius", "the fitting radius (µm) is required (or curvature: null)")


_check_required()
SURFACES = _check_layers()
MEASURED = sorted(set(config["measure"]["surfaces"] or SURFACES))


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
        except ImportError as exc:  # a Snakemake environment without nemo: trust the config
            warnings.warn(f"cannot import nemo ({exc}); not checking {path}'s header")
            return None
        try:
            info = read_info(path)
        except NemoError as exc:
            config_error(f"{key}.path", str(exc))
        if not info.calibrated and d["spacing"] is None:
            warnings.warn(f"{path} has no spatial calibration; set {key}.spacing: [dz, dy, dx] (µm)")
        return info.shape
    if synth is None:
        config_error(f"{key}.path", f"file not found: {path} (relative to {os.getcwd()}); give an "
                                    "existing hyperstack, or a 'synthetic:' section to generate it")
    return {"T": int(synth.get("frames", 1)), "C": int(synth.get("channels", 1)), "Z": None}


def _indices(name, d, axis, size):
    key = f"datasets.{name}.{axis.lower()}"
    values = d[axis.lower()]
    if values == "all":
        return list(range(size))
    bad = [v for v in values if v >= size]
    if bad:
        what = "time points" if axis == "T" else "channels"
        config_error(key, f"{bad} out of range: {d['path']} has {size} {what} (valid: 0 to {size - 1})")
    return sorted(values)


def _datasets():
    out = {}
    for name, d in config["datasets"].items():
        shape = _dataset_info(name, d)
        seg = d["segment_channel"] if d["segment_channel"] is not None else config["segment_channel"]
        entry = {"path": d["path"], "spacing": d["spacing"], "mask": d["mask"],
                 "synthetic": d["synthetic"], "seg": seg, "stack_mb": None}
        if shape is None:
            if d["t"] == "all" or d["c"] == "all":
                config_error(f"datasets.{name}", "cannot read the header: give t and c as lists")
            entry["t"], entry["c"] = sorted(d["t"]), sorted(d["c"])
        else:
            entry["t"] = _indices(name, d, "T", shape["T"])
            entry["c"] = _indices(name, d, "C", shape["C"])
            if seg >= shape["C"]:
                key = f"datasets.{name}.segment_channel" if d["segment_channel"] is not None else "segment_channel"
                config_error(key, f"channel {seg} is not in {d['path']}, which has {shape['C']} "
                                  f"channel{'s' if shape['C'] != 1 else ''} (valid: 0 to {shape['C'] - 1})")
            if shape.get("Z"):
                entry["stack_mb"] = shape["Z"] * shape["Y"] * shape["X"] * 4 / 1e6
        if d["mask"] is not None and not Path(d["mask"]).exists():
            config_error(f"datasets.{name}.mask", f"file not found: {d['mask']}")
        out[name] = entry
    paths = [e["path"] for e in out.values()]
    for p in set(paths):
        if paths.count(p) > 1 and any(e["synthetic"] for e in out.values() if e["path"] == p):
            config_error("datasets", f"two datasets generate/read the same synthetic file {p}")
    return out


DATA = _datasets()


def _check_layer_channels():
    analysed = "; ".join(f"{n}: {DATA[n]['c']}" for n in DATA)
    for layer in LAYERS:
        if not any(layer_channels(name, layer) for name in DATA):
            config_error(f"layers.{layer}.channels",
                         f"{LAYERS[layer]['channels']} holds none of the analysed channels ({analysed})")
    for i, (a, b) in enumerate(ALIGN_PAIRS):
        if not any(align_frames(name) for name in DATA):
            config_error(f"alignment.{i}", f"layers '{a}' and '{b}' share no analysed channel")



# ----------------------------------------------------------------------------- resources
def res(rule, key):
    table = config["resources"]
    defaults = {"mem_mb": 2000, "runtime": 30, "threads": 1}
    value = table.get(rule, {}).get(key, table.get("default", {}).get(key, defaults[key]))
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
    return f"{RESULTS}/{wildcards.dataset}/t{wildcards.t}/c{DATA[wildcards.dataset]['seg']}"


def surface_mesh(wildcards, surface):
    return f"{seg_dir(wildcards)}/{SURFACE_FILE[surface]}"


def layer_mesh(wildcards, layer=None):
    return surface_mesh(wildcards, LAYERS[layer or wildcards.layer]["surface"])


def spacing_opt(wildcards):
    sp = DATA[wildcards.dataset]["spacing"]
    return "--spacing " + " ".join(str(v) for v in sp) if sp else ""


def layer_channels(name, layer):
    """Analysed channels of dataset ``name`` that hold ``layer``."""
    chans = LAYERS[layer]["channels"]
    return [c for c in DATA[name]["c"] if chans == "all" or c in chans]


def layer_frames(name):
    """(t, c, layer) triples analysed in a dataset."""
    # sorted: params built from this list must not depend on the order of keys in the config
    return sorted((t, c, layer) for t in DATA[name]["t"] for layer in LAYERS
                  for c in layer_channels(name, layer))


def align_frames(name):
    """(t, c, a, b): alignment pairs in the channels that hold both layers."""
    return sorted((t, c, a, b) for t in DATA[name]["t"] for a, b in ALIGN_PAIRS
                  for c in layer_channels(name, a) if c in layer_channels(name, b))


def summary_targets(name):
    s = SUMMARY.format(dataset=name)
    return [f"{s}/frames.parquet", f"{s}/defects.parquet", f"{s}/tracks.parquet",
            f"{s}/alignment.parquet"]


_check_layer_channels()
