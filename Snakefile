# KnockGS workflow: Probe-A calibration of (s_E, s_rho), frozen write-back, Probe-B prediction.
#
# Path grammar (P = results/{profile}):
#   P/assets/{object}.ply                              normalized 3DGS asset (rendered Gaussians)
#   P/assets/{object}.particles.npz                    simulated particles (GS first, then fill)
#   P/rollouts/{object}/lib/{theta}.parquet            candidate library rollouts, Probe A only
#                                                      (+ .F.parquet); also the candidates' Probe-A
#                                                      evaluation rollouts
#   P/rollouts/{object}/eval/{probe}/{theta}.parquet   evaluation rollouts (+ .F.parquet), keyed by
#                                                      theta = sE{s_E:.6f}_sR{s_rho:.6f}, so every
#                                                      method that lands on the same theta shares one
#   P/descriptors/{object}/library.csv                 candidate descriptors + labels
#   P/descriptors/{object}/queries_{split}.csv         target Probe-A descriptors, no labels
#   P/estimates/{object}/{split}/{method}.json         frozen estimates (checkpoint)
#   P/metrics/{object}/{split}/{method}.csv            write-back evaluation rows
#   P/render/{object}/{split}/{method}.csv             rendered-frame metrics
#   results/tables/*.csv|md, results/figures/*.png     reported tables and figures
#   results/audits/{name}.json                         audit verdicts ({"passed": bool, ...})
#   P/discrepancy/...                                  discrepancy cases (workflow/rules/discrepancy.smk);
#                                                      at config discrepancy.resolution when it differs
#                                                      from the profile: P/discrepancy/{res}/assets|library

from snakemake.utils import min_version, validate

min_version("8.10")


configfile: "config/config.yaml"


validate(config, "workflow/schemas/config.schema.yaml")


include: "workflow/rules/common.smk"
include: "workflow/rules/assets.smk"
include: "workflow/rules/simulate.smk"
include: "workflow/rules/describe.smk"
include: "workflow/rules/calibrate.smk"
include: "workflow/rules/evaluate.smk"
include: "workflow/rules/render.smk"
include: "workflow/rules/report.smk"
include: "workflow/rules/audit.smk"
include: "workflow/rules/discrepancy.smk"


rule all:
    default_target: True
    input:
        all_outputs(),
