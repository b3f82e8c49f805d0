"""Snakemake script of rule report_tables: HTML previews of a dataset's summary tables.

The Parquet files stay the data; these pages are what `snakemake --report` shows (it previews
HTML, not Parquet). Each column header carries its unit (docs/workflow.md, "Summaries").
"""

import html
import math
import sys

import pandas as pd

from nemo.atomic import write_text

sm = snakemake  # noqa: F821 (injected by Snakemake)

#: unit of every summary column that has one (lengths in the image's unit, µm)
UNITS = {
    # frames.parquet
    "area": "µm²",
    "volume": "µm³",
    "H_mean": "1/µm",
    "K_mean": "1/µm²",
    "H_fit_mean": "1/µm",
    "K_fit_mean": "1/µm²",
    "thickness_mean": "µm",
    "thickness_median": "µm",
    # defects.parquet
    "x": "µm",
    "y": "µm",
    "z": "µm",
    "contour_radius": "µm",
    "max_step_deg": "°",
    "shift": "µm",
    "min_distance": "µm",
    # tracks.parquet
    "path_length": "µm",
    "mean_speed": "µm per time point",
}

STYLE = """
body { font-family: sans-serif; font-size: 13px; margin: 1em; }
table { border-collapse: collapse; }
th, td { border: 1px solid #ccc; padding: 2px 6px; text-align: right; white-space: nowrap; }
th { background: #f0f0f0; position: sticky; top: 0; }
tr:nth-child(even) td { background: #fafafa; }
p.note { color: #555; }
"""


def number(value):
    """Six significant digits, without an exponent between 0.001 and 10⁹."""
    if not math.isfinite(value) or value == 0:
        return "NaN" if math.isnan(value) else f"{value:g}"
    if 1e-3 <= abs(value) < 1e9:
        return f"{value:.{max(0, 5 - math.floor(math.log10(abs(value))))}f}"
    return f"{value:.5e}"


def header(column):
    unit = UNITS.get(column)
    return f"{column} ({unit})" if unit else column


def page(name, table, dataset, max_rows):
    shown = table.head(max_rows).rename(columns=header)
    note = f"{len(table)} rows × {table.shape[1]} columns"
    if len(table) > max_rows:
        note += f"; the first {max_rows} rows are shown, all are in {name}.parquet"
    body = shown.to_html(index=False, na_rep="NaN", float_format=number, border=0)
    title = html.escape(f"{name}.parquet — dataset {dataset}")
    return (f"<!DOCTYPE html>\n<html><head><meta charset='utf-8'><title>{title}</title>"
            f"<style>{STYLE}</style></head><body>\n<h3>{title}</h3>\n<p class='note'>{html.escape(note)}; "
            f"units in the column headers.</p>\n{body}\n</body></html>\n")


with open(sm.log[0], "w") as log:
    sys.stderr = log
    for name in ("frames", "defects", "tracks", "alignment"):
        table = pd.read_parquet(sm.input[name])
        write_text(sm.output[name], page(name, table, sm.wildcards.dataset, int(sm.params.max_rows)))
        print(f"{name}: {len(table)} rows -> {sm.output[name]}", file=log)
