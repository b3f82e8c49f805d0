"""Cases of the validation protocol: the ``validation:`` config section expanded into cases.

A case is ``nemo synth`` options (the volume) plus per-dataset overrides of the workflow's
analysis sections (``run``), or a configured synthetic dataset analysed as one point. Cases
that differ only in their analysis share their volume (:func:`volume_id`).
"""

from __future__ import annotations

import copy
import hashlib
import json
from typing import Any

from nemo.errors import NemoError
from nemo.validation.shapes import SHAPES


def _set_dotted(d: dict, key: str, value: Any) -> None:
    parts = key.split(".")
    if parts[0] not in ("synth", "run") or len(parts) < 2:
        raise NemoError(f"validation sweep key {key!r} must start with 'synth.' or 'run.' "
                        "(e.g. synth.noise, run.order.radius)")
    cur = d
    for p in parts[:-1]:
        cur = cur.setdefault(p, {})
        if not isinstance(cur, dict):
            raise NemoError(f"validation sweep key {key!r}: {p!r} is not a section")
    cur[parts[-1]] = copy.deepcopy(value)


def _slug(value: Any) -> str:
    if isinstance(value, (list, tuple)):
        return "x".join(_slug(v) for v in value)
    if isinstance(value, float) and value.is_integer():
        value = int(value)
    return str(value).replace(".", "p").replace("-", "m") if isinstance(value, (int, float)) else str(value)


def volume_id(synth: dict) -> str:
    """Stable short id of a volume from its ``nemo synth`` options."""
    text = json.dumps(synth, sort_keys=True)
    return "v" + hashlib.sha1(text.encode()).hexdigest()[:10]


def _sweep_point(name: str, key: str, item: Any, settable: bool) -> tuple[Any, dict]:
    """A sweep value and the extra options of that point (``{value: V, set: {...}}``)."""
    if isinstance(item, dict):
        if "value" not in item:
            raise NemoError(f"validation.sweeps.{name}: a value given as a mapping needs 'value' "
                            "(and 'set': the options of that point)")
        return item["value"], dict(item.get("set") or {})
    if not settable:
        raise NemoError(f"validation.sweeps.{name}: key {key!r} is a label (not synth.* or run.*): "
                        "give each value as {value: V, set: {...}}")
    return item, {}


def expand_cases(section: dict) -> dict[str, dict]:
    """Expand a ``validation:`` config section into cases.

    Parameters
    ----------
    section : dict
        ``base`` (``synth``: ``nemo synth`` options, ``run``: overrides of the analysis sections),
        ``rotations`` (seeds of random rotations of the defect set; also the fibre/noise seed),
        ``sweeps`` (name -> ``{key: "synth.noise", values: [...], set: {dotted: value}}``; a
        value may be ``{value: V, set: {dotted: ...}}``, the options of that point, and then
        ``key`` may be a plain label such as ``snr``) and
        ``cases`` (name -> ``{synth: ..., run: ..., rotations: [...]}`` or
        ``{dataset: NAME, run: ...}`` to analyse a workflow dataset's image as one point).

    Returns
    -------
    dict
        ``case id -> {case, sweep, parameter, value, rotation, synth, run, volume, dataset}``;
        ``volume`` is :func:`volume_id` of ``synth`` (None for dataset cases).
    """
    base = section.get("base") or {}
    base = {"synth": dict(base.get("synth") or {}), "run": copy.deepcopy(base.get("run") or {})}
    rotations = list(section.get("rotations") or [0])
    cases: dict[str, dict] = {}

    def add(cid, sweep, key, value, rot, spec, dataset=None):
        synth = dict(spec["synth"])
        if dataset is None:
            synth.setdefault("seed", int(rot))
            if rot is not None:
                synth["rotate_random"] = int(rot)
        if cid in cases:
            raise NemoError(f"validation: two cases are called {cid!r}; rename a sweep or case")
        cases[cid] = {
            "case": cid, "sweep": sweep, "parameter": key, "value": value,
            "value_label": _slug(value) if value is not None else "", "rotation": rot,
            "synth": synth, "run": spec["run"], "dataset": dataset,
            "volume": None if dataset is not None else volume_id(synth),
        }

    for name, sw in (section.get("sweeps") or {}).items():
        if "key" not in sw or not sw.get("values"):
            raise NemoError(f"validation.sweeps.{name} needs 'key' (e.g. synth.noise) and 'values'")
        settable = str(sw["key"]).startswith(("synth.", "run."))
        for item in sw["values"]:
            # a value, or {value: V, set: {dotted: ...}} (a point set by several options, e.g.
            # an SNR reached by photons and Gaussian noise; then 'key' may be a plain label)
            value, extra = _sweep_point(name, sw["key"], item, settable)
            for rot in sw.get("rotations", rotations):
                spec = copy.deepcopy(base)
                sets = {**(sw.get("set") or {}), **extra, **({sw["key"]: value} if settable else {})}
                for k, v in sets.items():
                    _set_dotted(spec, k, v)
                add(f"{name}-{_slug(value)}-r{rot}", name, sw["key"], value, rot, spec)
    for name, c in (section.get("cases") or {}).items():
        spec = copy.deepcopy(base)
        if c.get("dataset"):
            spec = {"synth": {}, "run": copy.deepcopy(c.get("run") or {})}
            add(name, name, None, None, None, spec, dataset=c["dataset"])
            continue
        spec["synth"].update(c.get("synth") or {})
        for k, v in (c.get("run") or {}).items():
            spec["run"].setdefault(k, {}).update(v)
        for rot in c.get("rotations", rotations):
            add(f"{name}-r{rot}", name, None, None, rot, spec)
    if not cases:
        raise NemoError("validation: no cases (give 'sweeps' and/or 'cases')")
    return cases


def expand_shapes(section: dict) -> dict[str, dict]:
    """``validation.shapes`` (name -> :func:`nemo.validation.shapes.shape_volume` spec) with defaults filled in."""
    out = {}
    for name, spec in (section.get("shapes") or {}).items():
        s = dict(spec)
        if s.get("kind") not in SHAPES:
            raise NemoError(f"validation.shapes.{name}.kind must be one of {', '.join(SHAPES)}")
        s.setdefault("spacing", [1.0, 1.0, 1.0])
        s.setdefault("radius_edges", [5.0])
        s.setdefault("mesh", {})
        out[name] = s
    return out

