# NEMO workflow: nematic order and morphology of curved surfaces in time-lapse hyperstacks.
#
#   snakemake --cores 2                                   # bundled default (synthetic demo)
#   snakemake --cores 8 --configfile config/paper.yaml    # the paper's vesicle
#   snakemake --workflow-profile workflow/profiles/slurm --configfile my.yaml
#
# Per frame: mesh -> morphology (measure, curvature, thickness) -> peel (layers) -> directors
# -> order -> defects, align; per dataset: aggregate -> track. Every rule calls the `nemo`
# command line; configuration and outputs are documented in docs/workflow.md.

import os

from snakemake.utils import min_version

min_version("9.0")

# The bundled default unless config files are given on the command line (--configfile
# replaces it instead of being merged into it; --config KEY=VALUE still overrides).
if not workflow.overwrite_configfiles:

    configfile: os.path.join(workflow.basedir, "config", "config.yaml")


report: "workflow/report/workflow.rst"


include: "workflow/rules/common.smk"


# validation protocol (docs/validation.md): only with a `validation:` section; its cases are
# datasets analysed by the rules below, so it comes before them
VALIDATION_TARGETS = []
if config.get("validation"):

    include: "workflow/rules/validation.smk"


include: "workflow/rules/synth.smk"
include: "workflow/rules/mesh.smk"
include: "workflow/rules/morphology.smk"
include: "workflow/rules/peel.smk"
include: "workflow/rules/directors.smk"
include: "workflow/rules/order.smk"
include: "workflow/rules/defects.smk"
include: "workflow/rules/align.smk"
include: "workflow/rules/aggregate.smk"
include: "workflow/rules/track.smk"
include: "workflow/rules/report.smk"


onstart:
    # the warm worker serves local runs only: a cluster's jobs start their own interpreters
    if not workflow.local_exec and os.environ.get(WORKER_ENV, "off") != "off":
        stop_worker()


rule all:
    default_target: True
    input:
        [summary_targets(name) for name in config["datasets"]],
        [report_targets(name) for name in config["datasets"]],
        [render_targets(name) for name in config["datasets"]],
        VALIDATION_TARGETS,
