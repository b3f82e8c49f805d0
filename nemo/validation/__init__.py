"""Validation protocol: how accurate NEMO is, measured against a known ground truth.

A microscopy image has no ground truth, so the protocol analyses images whose answer is known
and scores what the analysis finds against it:

* synthetic nematic vesicles (``nemo synth``: an analytic director field with known defects),
  swept over image quality (noise, voxel anisotropy) and over the analysis parameters
  (marching-cubes step, director patch radius and scale, averaging radius, curvature radius),
  each with several random rotations of the defect set — scored for defect detection,
  localisation and charge, director angle, order parameter and curvature; realistic images add
  a confocal-like PSF (σz > σxy), shot + Gaussian noise at a stated SNR
  (``nemo.synthetic.snr``) and vesicles cut open by the top of the stack;
* analytic solids (ellipsoid, torus, concentric shells) written as blurred stacks — scored for
  curvature and thickness against their closed-form values.

The protocol runs through the Snakemake workflow (``workflow/rules/validation.smk``, enabled by a
``validation:`` config section, e.g. ``config/validation.yaml``): every vesicle case becomes a
one-frame dataset analysed by the workflow's ordinary per-frame rules, so the scores are those
of what users run. This package holds everything the rules compute and nothing about Snakemake;
the rules call it through ``nemo validate {shape,score,score-shape,aggregate}``
(``nemo/cli/validate.py``). The measured results are in ``docs/validation.md``.

Modules, by responsibility:

* :mod:`nemo.validation.cases` — the ``validation:`` section expanded into cases
  (:func:`expand_cases`, :func:`expand_shapes`, :func:`volume_id`);
* :mod:`nemo.validation.shapes` — analytic shapes: signed distances, :func:`shape_volume`,
  exact curvature (:func:`ellipsoid_curvature`, :func:`torus_curvature`) and
  :func:`shell_thickness`;
* :mod:`nemo.validation.scoring` — results against the truth (:func:`score_shape`,
  :func:`match_defects`, :func:`score_defects`, :func:`director_errors`, :func:`score_vesicle`,
  :func:`truth_defects`);
* :mod:`nemo.validation.aggregate` — every score and Snakemake's per-job ``benchmark:`` files
  (time, memory) into summary tables, a markdown report and plots (:func:`aggregate`).

Speed and memory of the stages are a different question, answered by the scripts in
``benchmarks/`` (``benchmarks/README.md``).
"""

from __future__ import annotations

from nemo.validation.aggregate import SWEEP_COLUMNS, aggregate, markdown, plot, read_snakemake_benchmark, stage_record
from nemo.validation.cases import expand_cases, expand_shapes, volume_id
from nemo.validation.scoring import (
    MATCH_FRACTION,
    director_errors,
    match_defects,
    score_defects,
    score_shape,
    score_vesicle,
    truth_defects,
)
from nemo.validation.shapes import (
    SHAPES,
    ellipsoid_curvature,
    shape_sdf,
    shape_volume,
    shell_thickness,
    torus_curvature,
)

__all__ = [
    "MATCH_FRACTION", "SHAPES", "SWEEP_COLUMNS", "aggregate", "director_errors", "ellipsoid_curvature",
    "expand_cases", "expand_shapes", "markdown", "match_defects", "plot", "read_snakemake_benchmark",
    "score_defects", "score_shape", "score_vesicle", "shape_sdf", "shape_volume", "shell_thickness",
    "stage_record", "torus_curvature", "truth_defects", "volume_id",
]
