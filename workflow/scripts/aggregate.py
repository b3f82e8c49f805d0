"""Snakemake script of the aggregate rules: collect per-frame tables into the summaries.

Called with ``script:``; ``snakemake.params.records`` lists the frames (see nemo.summary).
"""

import sys

import pandas as pd

from nemo.summary import alignment_summary, collect_defects, frame_summary
from nemo.tables import write_table

sm = snakemake  # noqa: F821 (injected by Snakemake)
KINDS = {"frames": frame_summary, "defects": collect_defects, "alignment": alignment_summary}

with open(sm.log[0], "w") as log:
    sys.stderr = log
    kind = sm.params.kind
    if kind in ("defects", "alignment"):  # each defect, each layer pair with its frames' quality control
        table = KINDS[kind](sm.params.records, pd.read_parquet(sm.input.frames))
    else:
        table = KINDS[kind](sm.params.records)
    write_table(table, sm.output[0], command=f"workflow aggregate {kind}", dataset=sm.wildcards.dataset,
                inputs=[str(p) for p in sm.input])
    print(f"{kind}: {len(table)} rows -> {sm.output[0]}", file=log)
