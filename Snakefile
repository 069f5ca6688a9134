# KnockGS workflow: Probe-A calibration of (s_E, s_rho), frozen write-back, Probe-B prediction.
#
# Path grammar. Every output of a run lies under P = results/{profile} (its logs under
# logs/{profile}), so two profiles never write the same file. theta = sE{s_E:.6f}_sR{s_rho:.6f}.
#
#   P/assets/{object}.ply                                 normalized 3DGS asset (rendered Gaussians)
#   P/assets/{object}.particles.npz                       simulated particles (GS first, then fill)
#   P/assets/{object}.scene.npz, .summary.json            render scene data, asset summary
#   P/rollouts/{object}/lib/chunk{chunk}/{theta}.parquet  candidate library rollouts, Probe A only
#                                                         (+ .F.parquet), one folder per library job;
#                                                         also the candidates' Probe-A evaluation rollouts
#   P/rollouts/{object}/eval/{theta}/{probe}.parquet      evaluation rollouts (+ .F.parquet), one folder
#                                                         per evaluation job: a target's or an estimate's
#                                                         theta under every evaluation probe (a candidate's:
#                                                         the held-out probes only), so every method that
#                                                         lands on the same theta shares them
#   P/rollouts/{object}/diag/{split}/{set}/{theta}__{probe}.parquet   a diagnostics' set's rollout (probe
#                                                         shifts, ladder rungs), one job a set
#   P/descriptors/{object}/library.csv                    candidate descriptors + labels
#   P/descriptors/{object}/queries_{split}.csv            target Probe-A descriptors, no labels
#   P/estimates/{object}/{split}/{method}.json            frozen estimates (checkpoint)
#   P/metrics/{object}/{split}/{method}.csv               write-back evaluation rows
#   P/frames/{object}/{theta}/{probe}.npz                 rendered frames (float16 RGB + alpha), one folder
#                                                         per render job
#   P/render_metrics/{object}/{split}/{method}.csv        image metrics of the rendered frames
#   P/tables/{name}.csv, P/tables/{name}.md               reported tables: main_{object}, targetwise_{object},
#                                                         render_{object}, objects, discrepancy,
#                                                         convergence_{object} (Probe-A dt and n_grid study),
#                                                         boundaries_{object}, loo_object (library boundaries)
#                                                         verification_fem (MPM vs finite-element reference),
#                                                         discrepancy_worlds (target discrepancy_worlds),
#                                                         splits_{object}, sensitivity_size_{object},
#                                                         sensitivity_k_alpha_{object}, identifiability_{object}
#                                                         (+ _pairs_): the paper's diagnostics (diagnostics.smk),
#                                                         duration_{object}, contact_{object},
#                                                         passive_active_{object} (+ _targets_): probe
#                                                         shifts, passive vs active (probe_shifts.smk),
#                                                         ladder_{object} (ladder.smk), cmaes_{object} (cmaes.smk),
#                                                         floor_{object} (MPM levels vs the FEM reference, floor.smk)
#   P/figures/{name}.png|gif                              reported figures: main_{object}, fill_{object},
#                                                         qualitative_{object}, compare_{object} (gif),
#                                                         objects, discrepancy, convergence_{object},
#                                                         boundaries_{object}, discrepancy_worlds,
#                                                         splits_{object}, sensitivity_{object},
#                                                         identifiability_{object}, passive_active_{object},
#                                                         floor_{object}
#   P/audits/{name}.json                                  audit verdicts ({"passed": bool, ...})
#   P/ladder/...                                          the observation ladder's observations, descriptors and
#                                                         estimates (grammar at the top of workflow/rules/ladder.smk)
#   P/cmaes/...                                           the CMA-ES video route's frozen estimates, one file per
#                                                         (object, split, seed) (grammar at the top of
#                                                         workflow/rules/cmaes.smk); its table tables/cmaes_{object}
#   P/passive/...                                         passive protocol, descriptors and estimates (grammar at
#                                                         the top of workflow/rules/probe_shifts.smk)
#   P/discrepancy/...                                     discrepancy cases, runs and reports (grammar at
#                                                         the top of workflow/rules/discrepancy.smk)
#   P/boundaries/...                                      boundary conditions' assets, rollouts, estimates and
#                                                         metrics, leave-one-object-out (grammar at the top of
#                                                         workflow/rules/boundaries.smk)
#   P/calibration/{object}/...                            one's own object calibrated from a measured Probe-A
#                                                         observation (config calibration; grammar at the top of
#                                                         workflow/rules/calibration.smk)
#   P/benchmarks/...                                      time and memory of the expensive jobs (.tsv)
#
# Wildcards: object, probe, split, case (names), theta (above), method (knockgs_core.calibration
# METHOD_NAMES), chunk (library job index), res (a profile: the discrepancy cases' resolution),
# condition, library (boundaries.smk), rung (ladder.smk), seed (cmaes.smk), prediction (calibration.smk).

from snakemake.utils import min_version

min_version("8.10")


configfile: "config/config.yaml"


include: "workflow/rules/common.smk"
include: "workflow/rules/assets.smk"
include: "workflow/rules/simulate.smk"
include: "workflow/rules/describe.smk"
include: "workflow/rules/calibrate.smk"
include: "workflow/rules/evaluate.smk"
include: "workflow/rules/render.smk"
include: "workflow/rules/report.smk"
include: "workflow/rules/discrepancy.smk"
include: "workflow/rules/diagnostics.smk"
include: "workflow/rules/probe_shifts.smk"
include: "workflow/rules/ladder.smk"
include: "workflow/rules/cmaes.smk"
include: "workflow/rules/convergence.smk"
include: "workflow/rules/boundaries.smk"
include: "workflow/rules/verification.smk"
include: "workflow/rules/floor.smk"
include: "workflow/rules/calibration.smk"
include: "workflow/rules/audit.smk"


# Rules that read a few small tables and write one: on a cluster (profiles/slurm) they run on
# the submitting host instead of waiting in the queue; a local run is the same either way.
localrules:
    estimate,
    oracle_estimate,
    main_table,
    main_figure,
    objects_table,
    render_table,


rule all:
    default_target: True
    input:
        REPORT_OUTPUTS,
        RENDER_OUTPUTS,
        AUDIT_OUTPUTS,
        studies_in_all(),  # every study's outputs that its config switches put in `all` (register_study)
