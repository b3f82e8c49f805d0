"""Snakemake script of rule report_config: a dataset's validated configuration, as YAML (beside
the summaries) and as an HTML page for `snakemake --report`."""

import html

import yaml

from nemo.atomic import write_text

sm = snakemake  # noqa: F821 (injected by Snakemake)

config = dict(sm.params.config)
text = yaml.safe_dump(config, sort_keys=False, allow_unicode=True, default_flow_style=None)
write_text(sm.output.yaml, f"# NEMO: configuration of dataset {sm.wildcards.dataset} (validated, defaults filled)\n"
           + text)
title = html.escape(f"Configuration of dataset {sm.wildcards.dataset}")
write_text(sm.output.html,
           f"<!DOCTYPE html>\n<html><head><meta charset='utf-8'><title>{title}</title></head>"
           f"<body style='font-family: sans-serif; font-size: 13px'>\n<h3>{title}</h3>\n"
           "<p>Validated, every default filled in (config.yaml beside the summaries); "
           "lengths in µm, <code>null</code> lengths derived from the data per frame.</p>\n"
           f"<pre>{html.escape(text)}</pre>\n</body></html>\n")
with open(sm.log[0], "w") as log:
    print(f"{len(config)} top-level keys -> {sm.output.yaml}, {sm.output.html}", file=log)
