# The observation ladder (docs/ladder.md): from simulator particles to ID-free video tracks.
#   P/ladder/observations/{object}/lib/chunk{chunk}.csv     every rung's descriptor of one library chunk
#                                                           (rendered RGB-D, tracked, not stored)
#   P/ladder/observations/{object}/targets_{split}.csv      the same for the split's targets
#   P/ladder/descriptors/{object}/{rung}/library.csv, queries_{split}.csv   one rung's tables
#   P/ladder/estimates/{object}/{split}/{rung}/{method}.json   every deployable estimator per rung (a job a rung)
#   P/tables/ladder_{object}.csv|md, P/figures/ladder_{object}.png   joint error and Probe-B
#                                                           trajectory RMSE per rung and method
# Probe-B rollouts of the rungs' estimates: P/rollouts/{object}/diag/{split}/ladder-{rung}
# (rule rollout_diag_set, a job a rung).
# Not in `all` unless config ladder.in_all: `snakemake --cores 2 ladder` (its cost: docs/results.md).

from knockgs_core.experiments import LadderSettings, ladder_rungs

include: "inputs/ladder.smk"


LADDER = config["ladder"]
LADDER_SETTINGS = LadderSettings(depth_noise=tuple(LADDER["depth_noise"]), depth_tol=LADDER["depth_tol"],
                                 track=dict(LADDER["track"]), seed=LADDER["seed"])
LADDER_RUNGS = ladder_rungs(LADDER_SETTINGS)


for _rung in LADDER_RUNGS:  # a diagnostics' set a rung: its estimates' Probe-B rollouts
    DIAG_SETS[f"ladder-{_rung}"] = (lambda obj, rung=_rung: ladder_set_cases(obj, rung),
                                    lambda obj, rung=_rung: ladder_estimates(obj, rung))
LADDER_OUTPUTS = [
    path for o in OBJECTS for path in (f"{P}/tables/ladder_{o}.csv", f"{P}/tables/ladder_{o}.md", f"{P}/figures/ladder_{o}.png")
]
LADDER_IN_ALL = register_study("ladder", LADDER_OUTPUTS, LADDER_OUTPUTS if LADDER["in_all"] else [])


wildcard_constraints:
    rung="|".join(re.escape(r) for r in LADDER_RUNGS),


rule ladder_observe_library:
    """Every rung's descriptor of one chunk of library rollouts (rendered with depth at the
    profile's render size, tracked, observed)."""
    conda:
        "../envs/knockgs.yaml"
    input:
        ply=f"{P}/assets/{{object}}.ply",
        scene=f"{P}/assets/{{object}}.scene.npz",
        rollouts=lambda wc: folders(run["rollout"] for run in ladder_library_runs(wc)),
    output:
        table=f"{P}/ladder/observations/{{object}}/lib/chunk{{chunk}}.csv",
    log:
        f"logs/{PROFILE}/ladder/observations/{{object}}/lib/chunk{{chunk}}.log",
    benchmark:
        f"{P}/benchmarks/ladder/{{object}}/lib/chunk{{chunk}}.tsv"
    params:
        runs=lambda wc: [{"case_name": case, **run} for case, run in
                         zip(LIBRARY_CHUNKS[int(wc.chunk)], ladder_library_runs(wc))],
        camera=lambda wc: contract(wc.object).camera,
        width=RENDER["width"],
        height=RENDER["height"],
        settings=LADDER,
        device=DEVICE,
    resources:
        gpu=1 if ON_GPU else 0,
    script:
        "../scripts/ladder_observe.py"


rule ladder_observe_targets:
    """Every rung's descriptor of the split's targets (their Probe-A evaluation rollouts)."""
    conda:
        "../envs/knockgs.yaml"
    input:
        ply=f"{P}/assets/{{object}}.ply",
        scene=f"{P}/assets/{{object}}.scene.npz",
        rollouts=lambda wc: folders(run["rollout"] for run in ladder_target_runs(wc)),
        F=lambda wc: temp_F_folders(ladder_target_runs(wc)),
    output:
        table=f"{P}/ladder/observations/{{object}}/targets_{{split}}.csv",
    log:
        f"logs/{PROFILE}/ladder/observations/{{object}}/targets_{{split}}.log",
    benchmark:
        f"{P}/benchmarks/ladder/{{object}}/targets_{{split}}.tsv"
    params:
        runs=ladder_target_runs,
        camera=lambda wc: contract(wc.object).camera,
        width=RENDER["width"],
        height=RENDER["height"],
        settings=LADDER,
        device=DEVICE,
    resources:
        gpu=1 if ON_GPU else 0,
    script:
        "../scripts/ladder_observe.py"


rule ladder_library_descriptors:
    """One library table (labels + descriptors) per rung."""
    conda:
        "../envs/knockgs.yaml"
    input:
        observations=lambda wc: [f"{P}/ladder/observations/{wc.object}/lib/chunk{k}.csv" for k in range(len(LIBRARY_CHUNKS))],
    output:
        tables=[f"{P}/ladder/descriptors/{{object}}/{rung}/library.csv" for rung in LADDER_RUNGS],
    log:
        f"logs/{PROFILE}/ladder/descriptors/{{object}}/library.log",
    params:
        rungs=LADDER_RUNGS,
        labels=True,
    script:
        "../scripts/ladder_descriptors.py"


rule ladder_query_descriptors:
    """One query table (descriptors only, no labels) per rung."""
    conda:
        "../envs/knockgs.yaml"
    input:
        observations=f"{P}/ladder/observations/{{object}}/targets_{{split}}.csv",
    output:
        tables=[f"{P}/ladder/descriptors/{{object}}/{rung}/queries_{{split}}.csv" for rung in LADDER_RUNGS],
    log:
        f"logs/{PROFILE}/ladder/descriptors/{{object}}/queries_{{split}}.log",
    params:
        rungs=LADDER_RUNGS,
        labels=False,
    script:
        "../scripts/ladder_descriptors.py"


checkpoint ladder_estimate:
    """Every deployable estimator on one rung's tables (one job: an estimate costs less than the
    job's start)."""
    conda:
        "../envs/knockgs.yaml"
    input:
        library=f"{P}/ladder/descriptors/{{object}}/{{rung}}/library.csv",
        queries=f"{P}/ladder/descriptors/{{object}}/{{rung}}/queries_{{split}}.csv",
    output:
        json=[f"{P}/ladder/estimates/{{object}}/{{split}}/{{rung}}/{m}.json" for m in CONFIG_DEPLOYABLE],
    log:
        f"logs/{PROFILE}/ladder/estimates/{{object}}/{{split}}/{{rung}}.log",
    params:
        methods=CONFIG_DEPLOYABLE,
        options={m: config["method_params"].get(m, {}) for m in CONFIG_DEPLOYABLE},
        config_hash=config_hash(),
    script:
        "../scripts/estimate.py"


rule ladder_table:
    """Joint error and Probe-B trajectory RMSE per rung and method."""
    conda:
        "../envs/knockgs.yaml"
    input:
        unpack(ladder_table_inputs),
    output:
        csv=report(f"{P}/tables/ladder_{{object}}.csv", caption="../report/ladder.rst", category="Tables", subcategory="{object}"),
        md=f"{P}/tables/ladder_{{object}}.md",
        png=report(f"{P}/figures/ladder_{{object}}.png", caption="../report/ladder.rst", category="Figures",
                   subcategory="{object}"),
    log:
        f"logs/{PROFILE}/tables/ladder_{{object}}.log",
    params:
        rungs=LADDER_RUNGS,
        methods=CONFIG_DEPLOYABLE,
        split=SPLIT,
        probe_b=lambda wc: heldout_probes(wc.object)[0],
        rollouts=ladder_probe_b_rollouts,
    script:
        "../scripts/ladder_table.py"


rule ladder:
    """Named target: the observation ladder of every object."""
    input:
        LADDER_OUTPUTS,
