"""Score one case's run against its truth -> one table row (JSON) and an evaluation page."""
import sys

from knockgs_core.discrepancy import evaluate_files

sys.stderr = open(snakemake.log[0], "w")
evaluate_files(snakemake.input.result.rsplit("/", 1)[0], snakemake.input.truth.rsplit("/", 1)[0], snakemake.output.row,
               markdown=snakemake.output.page)
