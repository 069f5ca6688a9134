# The observation ladder (docs/ladder.md): from simulator particles to ID-free video tracks.
#   P/ladder/observations/{object}/lib/chunk{chunk}.csv     every rung's descriptor of one library chunk
#                                                           (rendered RGB-D, tracked, not stored)
#   P/ladder/observations/{object}/targets_{split}.csv      the same for the split's targets
#   P/ladder/descriptors/{object}/{rung}/library.csv, queries_{split}.csv   one rung's tables
#   P/ladder/estimates/{object}/{split}/{rung}/{method}.json   every deployable estimator per rung
#   P/tables/ladder_{object}.csv|md, P/figures/ladder_{object}.png   joint error and Probe-B
#                                                           trajectory RMSE per rung and method
# Probe-B rollouts of the rungs' estimates: P/rollouts/{object}/diag/{split}/ladder-{rung}
# (rule rollout_diag_set, a job a rung).
# Not in `all` unless config ladder.in_all: `snakemake --cores 2 ladder` (its cost: docs/results.md).

from knockgs_core.experiments import LadderSettings, ladder_rungs

LADDER = config["ladder"]
LADDER_SETTINGS = LadderSettings(depth_noise=tuple(LADDER["depth_noise"]), depth_tol=LADDER["depth_tol"],
                                 track=dict(LADDER["track"]), seed=LADDER["seed"])
LADDER_RUNGS = ladder_rungs(LADDER_SETTINGS)


def ladder_library_runs(wc):
    """The library rollouts of chunk ``wc.chunk``, with the deformation gradients the video
    rungs render (a library written without them cannot be observed)."""
    if not LIBRARY_F:
        raise WorkflowError(f"config render.library_deformation_gradients is false (profile {PROFILE}), but the "
                            "observation ladder renders the library's rollouts: set it to true")
    return library_runs(wc.chunk, calibration_probe(wc.object), library_root(wc.object), export_F=True)


def ladder_target_runs(wc):
    """The split's targets as the ladder observes them: name, theta, Probe-A rollout and its
    deformation gradients (one run)."""
    need_eval_F("the observation ladder")
    probe = calibration_probe(wc.object)
    return [{"case_name": name, "theta": th, "rollout": eval_rollout(wc.object, probe, th, with_F=True),
             "F": eval_rollout(wc.object, probe, th, ".F.parquet")} for name, th in target_thetas(wc.split).items()]


def ladder_set_cases(obj, rung):
    """(probes, thetas) of a rung's diagnostics' set: its estimates under the first Probe B,
    each theta once, but those of a target (its evaluation rollout has it)."""
    targets = {theta_tag(th) for th in target_thetas(SPLIT).values()}
    thetas = {}
    for m in CONFIG_DEPLOYABLE:
        est = thetas_of(checkpoints.ladder_estimate.get(object=obj, split=SPLIT, rung=rung, method=m).output.json)
        thetas.update({theta_tag(th): th for th in est.values() if theta_tag(th) not in targets})
    return [heldout_probes(obj)[0]], list(thetas.values())


def ladder_probe_b_rollouts(wc):
    """{"theta tag": rollout} under the first Probe B of every rung's estimates (the rungs'
    diagnostics' sets) and of the targets (their evaluation rollouts)."""
    probe = heldout_probes(wc.object)[0]
    out = {theta_tag(th): eval_rollout(wc.object, probe, th) for th in target_thetas(SPLIT).values()}
    for rung in LADDER_RUNGS:
        for key, path in diag_set_rollouts(wc.object, f"ladder-{rung}").items():
            out.setdefault(key.split("/", 1)[1], path)
    return out


def ladder_table_inputs(wc):
    rollouts = ladder_probe_b_rollouts(wc)
    return {
        "estimates": [f"{P}/ladder/estimates/{wc.object}/{SPLIT}/{rung}/{m}.json" for rung in LADDER_RUNGS
                      for m in CONFIG_DEPLOYABLE],
        "observations": [f"{P}/ladder/observations/{wc.object}/lib/chunk{k}.csv" for k in range(len(LIBRARY_CHUNKS))]
        + [f"{P}/ladder/observations/{wc.object}/targets_{SPLIT}.csv"],
        "targets": "config/targets.csv",
        "rollouts": folders(rollouts.values()),
    }


def ladder_estimates(obj, rung):
    """Every deployable method's estimate file of a rung (through its checkpoint)."""
    return [checkpoints.ladder_estimate.get(object=obj, split=SPLIT, rung=rung, method=m).output.json
            for m in CONFIG_DEPLOYABLE]


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
    """A deployable estimator on one rung's tables."""
    conda:
        "../envs/knockgs.yaml"
    input:
        library=f"{P}/ladder/descriptors/{{object}}/{{rung}}/library.csv",
        queries=f"{P}/ladder/descriptors/{{object}}/{{rung}}/queries_{{split}}.csv",
    output:
        json=f"{P}/ladder/estimates/{{object}}/{{split}}/{{rung}}/{{method}}.json",
    log:
        f"logs/{PROFILE}/ladder/estimates/{{object}}/{{split}}/{{rung}}/{{method}}.log",
    wildcard_constraints:
        method="|".join(DEPLOYABLE_METHODS),
    params:
        method=lambda wc: wc.method,
        options=lambda wc: config["method_params"].get(wc.method, {}),
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
