"""Write workflow/envs/nemo.yaml from pyproject.toml, the one source of NEMO's dependency pins.

The workflow's conda environment cannot install NEMO from the checkout (Snakemake builds it
from a copy of the YAML file elsewhere), so it lists the pinned packages itself; this script
writes them from ``[project].dependencies``. tests/test_env_consistency.py fails when the file
differs from what this script writes.

    python workflow/envs/update.py          # rewrite nemo.yaml
    python workflow/envs/update.py --check  # exit 1 if nemo.yaml is out of date
"""

from __future__ import annotations

import re
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
ENV = Path(__file__).with_name("nemo.yaml")

HEADER = """\
# Conda environment of the workflow's rules (snakemake --use-conda / --sdm conda).
# GENERATED from pyproject.toml by `python workflow/envs/update.py`: edit the pins there.
# NEMO itself is not installed here: the Snakefile puts this checkout on PYTHONPATH and the
# rules run `python -m nemo`.
channels:
  - conda-forge
  - nodefaults
dependencies:
  - python={python}
  - pip
  - pip:
"""


def render(pyproject: Path = ROOT / "pyproject.toml") -> str:
    """The text of nemo.yaml for the pins of ``pyproject``."""
    with open(pyproject, "rb") as fh:
        project = tomllib.load(fh)["project"]
    python = re.search(r">=\s*(\d+\.\d+)", project["requires-python"]).group(1)
    lines = [f'      - "{spec}"' if ";" in spec else f"      - {spec}" for spec in project["dependencies"]]
    return HEADER.format(python=python) + "\n".join(lines) + "\n"


def main(argv: list[str]) -> int:
    text = render()
    if "--check" in argv:
        if ENV.read_text() != text:
            print(f"{ENV} is out of date: run python workflow/envs/update.py", file=sys.stderr)
            return 1
        return 0
    ENV.write_text(text)
    print(f"wrote {ENV}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
