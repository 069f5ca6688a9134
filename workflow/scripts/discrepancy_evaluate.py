"""Score one case's run against its truth -> one table row (JSON) and an evaluation page."""
import sys
from pathlib import Path

from knockgs_core.discrepancy import evaluate_files

sys.stderr = open(snakemake.log[0], "w")
evaluate_files(Path(snakemake.input.result).parent, Path(snakemake.input.truth).parent, snakemake.output.row,
               markdown=snakemake.output.page)
