"""The results layout: folder and file names shared by the workflow, ``nemo run``, ``nemo render``
and the napari reader.

One frame (time point ``t``, channel ``c``) of a dataset lives in ``{results}/{dataset}/t{t}/c{c}/``;
the meshes and morphology of a time point in the folder of the segmented channel; the summaries
of a dataset in ``{results}/{dataset}/summary/``. ``nemo run -o OUTDIR`` writes one frame's files
under the same names into OUTDIR.
"""

from __future__ import annotations

#: Mesh file of each surface.
MESH = {"whole": "mesh.ply", "inner": "mesh.inner.ply", "outer": "mesh.outer.ply"}
#: Per-layer tables, in the order of the analysis.
LAYER_KINDS = ("layer", "directors", "order", "defects")
THICKNESS = "thickness.parquet"
SUMMARY_JSON = "summary.json"
#: Per-dataset folders below ``{results}/{dataset}``.
SUMMARY_DIR, LOG_DIR, BENCH_DIR = "summary", "logs", "benchmarks"
#: Summary tables of a dataset.
SUMMARY_TABLES = ("frames.parquet", "defects.parquet", "tracks.parquet", "alignment.parquet")
UNTRACKED_DEFECTS = "defects_untracked.parquet"


def frame_dir(results: str, dataset: str, t: int | str, c: int | str) -> str:
    """``{results}/{dataset}/t{t}/c{c}`` (wildcard strings such as ``"{t}"`` are kept)."""
    return f"{results.rstrip('/')}/{dataset}/t{t}/c{c}"


def dataset_dir(results: str, dataset: str, sub: str = "") -> str:
    """``{results}/{dataset}`` or a folder below it (``summary``, ``logs``, ``benchmarks``)."""
    return f"{results.rstrip('/')}/{dataset}" + (f"/{sub}" if sub else "")


def measure_file(surface: str) -> str:
    return f"measure_{surface}.json"


def curvature_file(surface: str) -> str:
    return f"curvature_{surface}.parquet"


def layer_file(kind: str, layer: str) -> str:
    """``{kind}_{layer}.parquet`` for kind in :data:`LAYER_KINDS`."""
    return f"{kind}_{layer}.parquet"


def refined_file(layer: str) -> str:
    """The refinement directors measured near each defect of a layer."""
    return f"refined_{layer}.parquet"


def align_file(a: str, b: str) -> str:
    return f"align_{a}_{b}.parquet"
