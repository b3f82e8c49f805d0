"""pyproject.toml is the one source of the dependency pins: environment.yml installs the
checkout (pins from pyproject), workflow/envs/nemo.yaml is generated from it and pins the same."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
REQ = re.compile(r"^\s*([A-Za-z0-9][A-Za-z0-9._-]*)\s*(\[[^\]]*\])?\s*(==|>=|<=|~=|!=|>|<|=)?\s*([^;\s]*)\s*(;.*)?$")


def _canon(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _parse(spec: str) -> tuple[str, str, str, str]:
    """``name[extra]==1.0; marker`` -> (canonical name, operator, version, marker)."""
    m = REQ.match(spec)
    assert m, f"cannot parse requirement {spec!r}"
    name, _extra, op, version, marker = m.groups()
    return _canon(name), op or "", version or "", (marker or "").lstrip("; ").strip()


def _pyproject():
    with open(ROOT / "pyproject.toml", "rb") as fh:
        return tomllib.load(fh)["project"]


def _env_requirements(path: Path) -> dict[str, tuple[str, str, str]]:
    """Packages of a conda env file: pip entries and conda ``name=version`` entries."""
    env = yaml.safe_load(path.read_text())
    out: dict[str, tuple[str, str, str]] = {}
    for dep in env.get("dependencies", []):
        if isinstance(dep, dict):
            for spec in dep.get("pip", []):
                if spec.startswith("-"):
                    continue  # -e ., -r file
                name, op, version, marker = _parse(spec)
                out[name] = (op, version, marker)
        else:
            name, *rest = re.split(r"\s*=+\s*|\s+", dep.strip(), maxsplit=1)
            # conda pins use "=" (or "=="): compare as "=="
            out[_canon(name)] = ("==", rest[0], "") if rest else ("", "", "")
    return out


WORKFLOW_ENVS = sorted((ROOT / "workflow" / "envs").glob("*.yaml"))
ENV_FILES = [ROOT / "environment.yml", *WORKFLOW_ENVS]


def test_env_files_exist():
    assert (ROOT / "environment.yml").exists()
    assert len(ENV_FILES) >= 2, "workflow/envs/ has no environment file"


@pytest.mark.parametrize("path", WORKFLOW_ENVS, ids=lambda p: str(p.relative_to(ROOT)))
def test_env_pins_match_pyproject(path):
    project = _pyproject()
    env = _env_requirements(path)
    problems = []
    for spec in project["dependencies"]:
        name, op, version, marker = _parse(spec)
        if name not in env:
            problems.append(f"{name} (pyproject {spec!r}) missing")
            continue
        e_op, e_version, e_marker = env[name]
        if (op, version) != (e_op, e_version):
            problems.append(f"{name}: pyproject {op}{version}, {path.name} {e_op}{e_version}")
        if marker and marker.replace('"', "'") != e_marker.replace('"', "'"):
            problems.append(f"{name}: marker {marker!r} in pyproject, {e_marker!r} in {path.name}")
    # anything else an env pins must agree with pyproject's optional extras
    extras = {}
    for specs in project.get("optional-dependencies", {}).values():
        for spec in specs:
            name, op, version, _ = _parse(spec)
            extras[name] = (op, version)
    known = {_parse(s)[0] for s in project["dependencies"]} | {"python", "pip"}
    for name, (op, version, _) in env.items():
        if name in known:
            continue
        if name not in extras:
            problems.append(f"{name} is pinned in {path.name} but not in pyproject.toml")
        elif extras[name][1] and (op, version) != extras[name]:
            problems.append(f"{name}: pyproject extra {extras[name]}, {path.name} {op}{version}")
    assert not problems, "\n".join(problems)


def test_env_python_satisfies_requires_python():
    floor = re.search(r">=\s*(\d+)\.(\d+)", _pyproject()["requires-python"])
    for path in ENV_FILES:
        env = yaml.safe_load(path.read_text())
        pins = [d for d in env["dependencies"] if isinstance(d, str) and d.startswith("python")]
        assert pins, f"{path.name} does not pin python"
        major, minor = map(int, re.search(r"(\d+)\.(\d+)", pins[0]).groups())
        assert (major, minor) >= tuple(map(int, floor.groups())), path.name


def test_parser_catches_a_mismatch(tmp_path):
    # the check must be able to fail: a wrong version is reported
    bad = tmp_path / "env.yaml"
    bad.write_text("dependencies:\n  - python=3.11\n  - pip:\n      - numpy==1.0\n")
    env = _env_requirements(bad)
    numpy_pin = next(s for s in _pyproject()["dependencies"] if s.startswith("numpy"))
    assert env["numpy"][:2] != _parse(numpy_pin)[1:3]


def test_environment_yml_takes_its_pins_from_pyproject():
    env = yaml.safe_load((ROOT / "environment.yml").read_text())
    pip = next(d["pip"] for d in env["dependencies"] if isinstance(d, dict))
    assert pip == ["-e .[slurm]"], "environment.yml should install the checkout, not pin packages itself"
    assert not set(_env_requirements(ROOT / "environment.yml")) - {"python", "pip"}


def test_workflow_env_is_generated_from_pyproject(tmp_path):
    """workflow/envs/nemo.yaml is exactly what workflow/envs/update.py writes, and the
    generator follows a change of pyproject.toml (so the check can fail)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("update_env", ROOT / "workflow" / "envs" / "update.py")
    update = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(update)
    assert (ROOT / "workflow" / "envs" / "nemo.yaml").read_text() == update.render()
    changed = tmp_path / "pyproject.toml"
    changed.write_text((ROOT / "pyproject.toml").read_text().replace('"numpy==', '"numpy>='))
    assert "numpy>=" in update.render(changed) and "numpy>=" not in update.render()
