"""Audit: no discrepancy run read the truth; write the verdict, fail the job if it did."""
import json
import sys
from pathlib import Path

from knockgs_core.io import write_text
from knockgs_core.discrepancy import audit_truth_separation

sys.stderr = open(snakemake.log[0], "w")
verdict = audit_truth_separation(snakemake.input.results, snakemake.input.measured, snakemake.params.truth_dirs,
                                 snakemake.params.declared)
verdict["audit"] = Path(snakemake.output[0]).stem
text = json.dumps(verdict, indent=1)
write_text(snakemake.output[0], text)
if not verdict["passed"]:
    failed = Path(snakemake.log[0]).with_suffix(".failed.json")
    write_text(failed, text)
    raise SystemExit(f"audit {verdict['audit']} failed: {verdict['problems'][:5]} (verdict in {failed})")
