"""The one parameter schema of NEMO and its defaults.

The workflow's config file, ``nemo run --config`` and the step commands share one schema,
``nemo/schemas/config.schema.yaml`` (``workflow/schemas/config.schema.yaml`` links to it). Its
*analysis sections* (:data:`ANALYSIS_SECTIONS`) hold the parameters of the paper's steps under
the names of the step commands' options (``order.radius`` is ``nemo order --radius``). A null
length is derived from the data by :mod:`nemo.stages` and recorded there as a number.

* :func:`validate` checks a whole config (every problem listed with its dotted key) and fills
  the schema's defaults;
* :func:`load` reads and validates a YAML file;
* :func:`section` merges the options of one step over the section's defaults (used by the
  stage functions, so a notebook call, a command and a rule start from the same values);
* :func:`analysis` gives the analysis sections of one dataset (per-dataset overrides merged)
  with the surfaces resolved (:func:`resolve_surfaces`).
"""

from __future__ import annotations

import copy
import functools
import json
import math
import os
from collections.abc import Mapping
from importlib import resources
from pathlib import Path
from typing import Any

from nemo.errors import NemoError

#: Sections that describe the analysis (may be overridden per dataset).
ANALYSIS_SECTIONS = ("mesh", "measure", "curvature", "thickness", "layers", "directors", "order",
                     "defects", "alignment", "tracking")

#: Path of the schema (package data).
SCHEMA_PATH = Path(str(resources.files("nemo.schemas") / "config.schema.yaml"))


@functools.cache
def schema() -> dict:
    """The parsed JSON schema (draft 2020-12)."""
    import yaml

    return yaml.safe_load(SCHEMA_PATH.read_text())


def _deref(node: dict) -> dict:
    """A schema node with a local ``$ref`` replaced by its target (sibling keys kept)."""
    while isinstance(node, dict) and "$ref" in node:
        target = schema()["$defs"][node["$ref"].rsplit("/", 1)[-1]]
        node = {**target, **{k: v for k, v in node.items() if k != "$ref"}}
    return node


def _fill_defaults(instance: Any, node: dict, path: tuple = ()) -> None:
    """Set the schema's defaults in ``instance`` (in place); dataset overrides stay as given."""
    node = _deref(node)
    if not isinstance(instance, dict):
        return
    props = node.get("properties", {})
    for key, sub in props.items():
        if path[:1] == ("datasets",) and key in ANALYSIS_SECTIONS:
            continue  # a per-dataset override holds only what the user changed
        sub_d = _deref(sub)
        if key not in instance and "default" in sub_d:
            instance[key] = copy.deepcopy(sub_d["default"])
        if key in instance:
            _fill_defaults(instance[key], sub, (*path, key))
    extra = node.get("additionalProperties")
    if isinstance(extra, dict):
        for key in instance:
            if key not in props:
                _fill_defaults(instance[key], extra, (*path, key))


def _messages(errors) -> list[str]:
    lines = []
    for e in sorted(errors, key=lambda e: list(map(str, e.absolute_path))):
        key = ".".join(str(p) for p in e.absolute_path) or "(top level)"
        msg = e.message
        if e.validator == "oneOf" and e.context:
            msg = f"{e.instance!r} is not valid: " + "; or ".join(sorted({c.message for c in e.context}))
        if e.validator == "anyOf" and e.absolute_path and e.absolute_path[-1] == "psf":
            msg = (f"{json.dumps(e.instance, default=str)} is not a PSF: give three numbers [σz, σy, σx] ≥ 0 (the image's "
                   "unit), auto (its z blur estimated from the image, the default), none (not deconvolved), or a list of them "
                   "per channel in channel order")
        if e.validator == "pattern" and "propertyNames" in e.schema_path:
            msg = (f"the name {e.instance!r} is not allowed: use letters, digits, '-' "
                   f"(and '_', '.' in dataset names), starting with a letter or digit")
        lines.append(f"config key '{key}': {msg}")
    return lines


#: Keys of the former ``nemo run`` config and what replaced them (named in the error).
RENAMED = {
    "peel": "layers.NAME (range, samples, reduce, interp, inward)",
    "mesh.step_um": "mesh.step (voxels)", "mesh.smooth_iter": "mesh.smooth",
    "mesh.surface": "layers.NAME.surface", "curvature.enabled": "curvature: null to switch it off",
    "peel.n_samples": "layers.NAME.samples",
}


def _renamed_hint(instance: Any) -> list[str]:
    if not isinstance(instance, dict):
        return []
    hints = []
    for old, new in RENAMED.items():
        section, _, key = old.partition(".")
        value = instance.get(section)
        if (not key and section in instance) or (key and isinstance(value, dict) and key in value):
            hints.append(f"'{old}' is now {new}")
    return hints


@functools.cache
def _validator(ref: str | None):
    """A validator of the whole schema (None) or of one ``$defs`` entry, built once."""

    node = schema() if ref is None else {"$ref": f"#/$defs/{ref}", "$defs": schema()["$defs"]}
    return _strict_validator_class()(node)


@functools.cache
def _strict_validator_class():
    """Draft 2020-12 with strict types: a number is finite (no NaN, no infinity) and not a
    boolean; an integer is a whole-number int, not ``1.0`` (the steps use it as a count or seed)."""
    import jsonschema

    def number(checker, value) -> bool:  # noqa: ARG001
        return isinstance(value, int | float) and not isinstance(value, bool) and (
            isinstance(value, int) or math.isfinite(value))

    def integer(checker, value) -> bool:  # noqa: ARG001
        return isinstance(value, int) and not isinstance(value, bool)

    base = jsonschema.Draft202012Validator
    types = base.TYPE_CHECKER.redefine_many({"number": number, "integer": integer})
    return jsonschema.validators.extend(base, type_checker=types)


def _check(instance: Any, ref: str | None, where: str = "") -> None:
    validator = _validator(ref)
    lines = _messages(validator.iter_errors(instance))
    if where:
        lines = [line.replace("config key '", f"config key '{where}.", 1).replace(f"'{where}.(top level)'",
                                                                                  f"'{where}'")
                 for line in lines]
    if lines:
        lines += _renamed_hint(instance) if not where else []
        raise NemoError("invalid configuration\n  " + "\n  ".join(lines)
                        + "\n  (schema: nemo/schemas/config.schema.yaml; keys: docs/workflow.md)")


def validate(config: Mapping | None) -> dict:
    """Check a whole config against the schema and fill its defaults.

    Parameters
    ----------
    config : mapping or None
        A workflow config (or any subset of its sections; None = all defaults).

    Returns
    -------
    dict
        A validated deep copy with every default filled in (per-dataset overrides as given).

    Raises
    ------
    NemoError
        Listing every invalid key with its dotted path and the reason.
    """
    cfg = copy.deepcopy(dict(config or {}))
    _check(cfg, None)
    _fill_defaults(cfg, schema())
    _check_profile_psf(cfg)
    return cfg


def dataset_default(key: str) -> Any:
    """The schema's default of the dataset key ``key`` (a frame given without a dataset takes it)."""
    node = _deref(schema()["properties"]["datasets"])["additionalProperties"]
    return copy.deepcopy(_deref(_deref(node)["properties"][key]).get("default"))


def _check_profile_psf(cfg: Mapping) -> None:
    """Refuse ``mesh.edge: profile`` on a dataset with a PSF given as numbers (:func:`nemo.stages.mesh`
    says why; ``auto``, the default, meshes such a frame from the image itself)."""
    from nemo.psf import is_auto, is_none, is_per_channel

    edge = (cfg.get("mesh") or {}).get("edge")
    for name, dataset in (cfg.get("datasets") or {}).items():
        dataset = dataset or {}
        psf = dataset.get("psf")
        given = [p for p in (psf if is_per_channel(psf) else [psf]) if not (is_none(p) or is_auto(p))]
        if given and ((dataset.get("mesh") or {}).get("edge") or edge) == "profile":
            raise NemoError(f"invalid configuration\n  config key 'datasets.{name}.psf': mesh.edge: profile and a psf "
                            "do not go together (the deconvolved walls overshoot at their edges); drop one")


def load(path: str | os.PathLike | None) -> dict:
    """Read a YAML config file (the workflow's own) and :func:`validate` it."""
    if path is None:
        return validate(None)
    import yaml

    path = Path(path)
    if not path.is_file():
        raise NemoError(f"config file not found: {path}")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError:
        raise NemoError(f"{path} is not a text file in UTF-8: give the YAML config file") from None
    except yaml.YAMLError as exc:
        raise NemoError(f"{path} is not valid YAML ({str(exc).splitlines()[0]})") from None
    if data is not None and not isinstance(data, dict):
        raise NemoError(f"{path} must hold a mapping of config keys, not a {type(data).__name__}")
    return validate(data)


def section_defaults(name: str) -> dict:
    """The defaults of one analysis section (``layer`` for one layer's keys)."""
    props = _deref({"$ref": f"#/$defs/{name}"})["properties"]
    return {key: copy.deepcopy(_deref(node).get("default")) for key, node in props.items()}


def section(name: str, params: Mapping | None = None) -> dict:
    """``params`` of one section merged over its defaults and checked.

    Keys with the value None take the default (as a command's unset option does), so the
    result holds every key of the section.
    """
    merged = section_defaults(name)
    for key, value in (params or {}).items():
        if key not in merged:
            raise NemoError(f"unknown key '{name}.{key}'; valid keys: {', '.join(merged)}")
        if value is not None:
            merged[key] = value
    _check(merged, name, where=name)
    if name == "layer" and merged.get("directors_from"):  # the layer section is what peeling takes
        raise NemoError(f"a layer with directors_from ({merged['directors_from']!r}) is not peeled: its "
                        "directors are imported ('nemo directors import'); remove directors_from to peel it")
    return merged


def _merge(base: Any, override: Any) -> Any:
    if isinstance(base, dict) and isinstance(override, dict):
        out = dict(base)
        for key, value in override.items():
            out[key] = _merge(base.get(key), value)
        return out
    return copy.deepcopy(override)


def analysis(cfg: Mapping, dataset: str | None = None) -> dict:
    """The analysis sections for one dataset: top level, then ``datasets.NAME`` overrides.

    Sections are deep-merged key by key; ``layers`` and ``alignment`` given for a dataset
    replace the top-level ones; a null section (``curvature: null``) switches that step off.
    Surfaces are then resolved (:func:`resolve_surfaces`).
    """
    out = {key: copy.deepcopy(cfg.get(key)) for key in ANALYSIS_SECTIONS}
    if dataset is not None:
        datasets = cfg.get("datasets") or {}
        if dataset not in datasets:
            raise NemoError(f"dataset {dataset!r} is not in the config (datasets: {', '.join(datasets) or 'none'})")
        for key in ANALYSIS_SECTIONS:
            if key not in datasets[dataset]:
                continue
            value = datasets[dataset][key]
            if key in ("layers", "alignment") or value is None or out[key] is None:
                out[key] = copy.deepcopy(value)
            else:
                out[key] = _merge(out[key], value)
        for name, layer in (out["layers"] or {}).items():
            out["layers"][name] = {**section_defaults("layer"), **layer}
    return resolve_surfaces(out)


def selected_indices(name: str, dataset: Mapping, axis: str, size: int) -> list[int]:
    """The time points (``axis`` "T") or channels ("C") that ``datasets.NAME`` selects from an
    image with ``size`` of them, sorted: the workflow's frames and ``nemo run``'s check.

    Raises
    ------
    NemoError
        An index the image does not have, naming the config key.
    """
    values = dataset.get(axis.lower(), "all")
    if values in (None, "all"):
        return list(range(size))
    bad = [v for v in values if v >= size]
    if bad:
        what = "time points" if axis == "T" else "channels"
        raise NemoError(f"config key 'datasets.{name}.{axis.lower()}': {bad} out of range: {dataset['path']} has "
                        f"{size} {what} (valid: 0 to {size - 1})")
    return sorted(values)


def resolve_surfaces(sections: dict) -> dict:
    """Resolve the null surfaces and check that every surface used is written by the mesh step.

    A layer's null ``surface`` is ``inner`` when the mesh is split, else ``whole``; a
    thickness with null ``from``/``to`` is inner → outer when split, and off otherwise.
    ``sections["surfaces"]`` lists the surfaces used (measured and fitted for curvature).
    """
    split = sections["mesh"]["split"] != "none"
    layers = sections["layers"] or {}
    for name, layer in layers.items():
        if layer.get("surface") is None:
            layer["surface"] = "inner" if split else "whole"
        if layer.get("directors_from"):
            _check_imported(name, layer)
            continue
        dmin, dmax = layer["range"]
        if not dmax > dmin:
            raise NemoError(f"config key 'layers.{name}.range': [{dmin}, {dmax}] needs d_max > d_min")
    th = sections["thickness"] = _resolve_thickness(sections["thickness"], split)
    _check_shifts(layers, th)
    used = {layer["surface"] for layer in layers.values()} | set(sections["measure"]["surfaces"] or [])
    used |= {th["from"], th["to"]} if th is not None else set()
    if not split and used & {"inner", "outer"}:
        raise NemoError(f"config key 'mesh.split': is 'none' but the surfaces {sorted(used - {'whole'})} are "
                        "used (layers, thickness or measure): set mesh.split: auto (or centre, axis), or use the "
                        "whole surface only (layers on surface: whole, thickness: null)")
    if sections["mesh"]["split"] == "axis" and not sections["mesh"]["axis"]:
        raise NemoError("config key 'mesh.axis': mesh.split: axis needs mesh.axis: [x, y, z]")
    _check_alignment(sections["alignment"] or [], layers)
    sections["surfaces"] = sorted(used or {"whole"})
    return sections


def _resolve_thickness(th: dict | None, split: bool) -> dict | None:
    if th is None or (th["from"] is None and th["to"] is None and not split):
        return None
    th["from"] = th["from"] or "inner"
    th["to"] = th["to"] or "outer"
    if th["from"] == th["to"]:
        raise NemoError(f"config key 'thickness.to': must differ from thickness.from ('{th['from']}')")
    return th


#: Placeholders of a layer's ``directors_from`` pattern.
DIRECTORS_FROM_FIELDS = ("dataset", "t", "c", "layer")


def _check_imported(name: str, layer: dict) -> None:
    """A layer whose directors come from files (``directors_from``) is not peeled."""
    key = f"config key 'layers.{name}"
    if layer.get("range") is not None:
        raise NemoError(f"{key}.range': the layer takes its directors from files (directors_from), so it is "
                        "not peeled: remove range (or directors_from to peel and measure it)")
    if layer.get("shift"):
        raise NemoError(f"{key}.shift': the layer takes its directors from files (directors_from), so it is "
                        "not peeled: remove shift")
    directors_from_path(layer["directors_from"], f"layers.{name}.directors_from", dataset="d", t=0, c=0, layer=name)
    imp = section("directors_import", layer.get("import"))
    problem = None
    if imp["basis"] == "axis" and (imp["axis"] is None or not any(imp["axis"])):
        problem = "axis': basis: axis measures the angles from the projection of a fixed axis: give axis: [x, y, z]"
    elif imp["axis"] is not None and imp["basis"] != "axis":
        problem = "axis': is only used with basis: axis; remove it"
    elif imp["basis"] is not None and imp["angle_unit"] is None:
        problem = "angle_unit': angles (basis given) need their unit: degrees or radians"
    elif imp["angle_unit"] is not None and imp["basis"] is None:
        problem = "basis': angles (angle_unit given) need their tangent basis: axis, local or frames"
    if problem:
        raise NemoError(f"{key}.import.{problem}")


def directors_from_path(pattern: str, key: str = "directors_from", **fields) -> str:
    """A layer's ``directors_from`` pattern with ``{dataset}``, ``{t}``, ``{c}``, ``{layer}`` filled.

    ``t`` and ``c`` are integers, so a format spec pads them (``{t:03d}`` gives ``007``).

    Raises
    ------
    NemoError
        Another placeholder, or a malformed pattern (naming ``key``).
    """
    import string

    try:
        used = {f for _, f, _, _ in string.Formatter().parse(pattern) if f is not None}
    except ValueError as exc:
        raise NemoError(f"config key '{key}': {pattern!r} is not a valid pattern ({exc}); write braces "
                        "only around the placeholders {t}, {c}, {dataset}, {layer}") from None
    unknown = sorted(used - set(DIRECTORS_FROM_FIELDS))
    if unknown:
        raise NemoError(f"config key '{key}': unknown placeholder(s) {', '.join('{' + u + '}' for u in unknown)} "
                        f"in {pattern!r}; use {{t}}, {{c}}, {{dataset}}, {{layer}}")
    try:
        return pattern.format(**{f: fields[f] for f in used})
    except (ValueError, TypeError) as exc:  # a format spec that does not fit, e.g. {layer:03d}
        raise NemoError(f"config key '{key}': cannot fill {pattern!r} ({exc}); {{t}} and {{c}} are whole "
                        "numbers (e.g. {t:03d} for 000, 001, ...), {dataset} and {layer} names") from None


def imported_layers(sections: dict) -> dict[str, dict]:
    """The layers of resolved analysis sections that take their directors from files."""
    return {name: layer for name, layer in (sections.get("layers") or {}).items() if layer.get("directors_from")}


def _check_shifts(layers: dict, th: dict | None) -> None:
    for name, layer in layers.items():
        if not layer["shift"] or layer.get("directors_from"):
            continue
        if th is None:
            raise NemoError(f"config key 'layers.{name}.shift': shifting by a fraction of the "
                            "thickness needs a thickness section")
        if layer["surface"] != th["from"]:
            raise NemoError(
                f"config key 'layers.{name}.shift': the thickness is measured on '{th['from']}' but "
                f"this layer is peeled from '{layer['surface']}'; set thickness.from: "
                f"{layer['surface']} or shift: 0")


def _check_alignment(pairs: list, layers: dict) -> None:
    for i, pair in enumerate(pairs):
        for name in pair:
            if name not in layers:
                raise NemoError(f"config key 'alignment.{i}': layer '{name}' is not defined under 'layers' "
                                f"(defined: {', '.join(layers) or 'none'})")
        if pair[0] == pair[1]:
            raise NemoError(f"config key 'alignment.{i}': aligns layer '{pair[0]}' with itself")


def reaches_out_of_one_wall(layer: Mapping) -> bool:
    """A layer (its resolved section: ``surface``, ``inward``, ``range``) that, on an object of one
    wall (whose ``inner`` and ``outer`` are its whole outline), samples mostly outside the object:
    the middle of its range lies outward (a membrane layer straddling the outline, [−1, 1], does not).
    ``surface: whole`` is the outline by choice (``split: none``), not a shell's wall: not counted."""
    d_min, d_max = (float(v) for v in (layer.get("range") or (0.0, 0.0)))
    return layer.get("surface") in ("inner", "outer") and not layer.get("inward") and d_min + d_max > 0
