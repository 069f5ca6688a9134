# Discretization and object boundaries of a frozen library (knockgs_core.experiments, its boundaries study;
# paper Sec. "Discretization, object and identifiability boundaries"). Per object, one contract
# component is changed at a time (config boundaries.conditions); the five targets are
# re-simulated under the changed specification, and local ridge estimates them from Probe A with
# the ORIGINAL (main) library and, for the kinds in boundaries.rebuild, with a REBUILT library
# (the candidates re-simulated under the changed specification). Leave-one-object-out: a shared
# library of the other objects' candidates estimates the held-out object's targets.
#
# Paths (B = P/boundaries; the rollout folders follow the main library and evaluation jobs):
#   B/{object}/{condition}/asset.particles.npz, asset.json    the condition's particles, counts, force factors
#   B/{object}/{condition}/lib/chunk{chunk}/{theta}.parquet   rebuilt library rollouts (Probe A)
#   B/{object}/{condition}/eval/{theta}/{probe}.parquet       a target's (Probe A and B) or an estimate's
#                                                             (Probe B) rollouts under the condition
#   B/{object}/{condition}/descriptors/library.csv, queries.csv
#   B/{object}/{condition}/estimates/{library}.json            frozen local-ridge estimates (checkpoint)
#   B/{object}/{condition}/metrics/{library}.csv               write-back evaluation rows (Probe B)
#   B/loo/{object}/library.csv, estimate.json, metrics.csv    leave-one-object-out
#   P/tables/boundaries_{object}.csv|md, P/figures/boundaries_{object}.png, P/tables/loo_object.csv|md
# Wildcards: condition (reference, fill_density, fill_density_equal_force, fill_seed{k}, grid, resolution),
# library (original, rebuilt). `snakemake boundaries` makes every table and figure; `all`
# includes them when config boundaries.enabled is true.

# Helpers (paths, input functions): inputs/boundaries.smk.

from knockgs_core.experiments import BOUNDARY_LIBRARIES, BoundarySettings, boundary_condition, boundary_conditions

include: "inputs/boundaries.smk"


BOUNDARIES = config["boundaries"]
BOUNDARY_SETTINGS = BoundarySettings.from_config(BOUNDARIES)
BOUNDARY_METHOD = "local_ridge"
BB = f"{P}/boundaries"


BOUNDARY_OUTPUTS = [
    path for o in OBJECTS
    for path in (f"{P}/tables/boundaries_{o}.csv", f"{P}/tables/boundaries_{o}.md", f"{P}/figures/boundaries_{o}.png")
] + ([f"{P}/tables/loo_object.csv", f"{P}/tables/loo_object.md"] if loo_objects() else [])
BOUNDARIES_IN_ALL = register_study("boundaries", BOUNDARY_OUTPUTS, BOUNDARY_OUTPUTS if BOUNDARIES["enabled"] else [])


wildcard_constraints:
    condition="reference|fill_density|fill_density_equal_force|fill_seed[0-9]+|grid|resolution",
    library="|".join(BOUNDARY_LIBRARIES),


rule boundary_asset:
    """The condition's particles (the changed contract's asset), counts and probe force factors."""
    conda:
        "../envs/knockgs.yaml"
    output:
        particles=f"{BB}/{{object}}/{{condition}}/asset.particles.npz",
        summary=f"{BB}/{{object}}/{{condition}}/asset.json",
    log:
        f"logs/{PROFILE}/boundaries/{{object}}/{{condition}}/asset.log",
    params:
        profile=PROFILE,
        object=lambda wc: wc.object,
        condition=lambda wc: wc.condition,
        settings=BOUNDARIES,
    resources:
        mem_mb=8000 if PROFILE == "paper" else 2000,
        runtime=30,
    threads: 1
    script:
        "../scripts/boundaries_asset.py"


rule boundary_rollout_library:
    """Probe-A rollouts of one chunk of candidates under the condition (a rebuilt library)."""
    conda:
        "../envs/knockgs.yaml"
    input:
        particles=f"{BB}/{{object}}/{{condition}}/asset.particles.npz",
        summary=f"{BB}/{{object}}/{{condition}}/asset.json",
    output:
        folder=directory(f"{BB}/{{object}}/{{condition}}/lib/chunk{{chunk}}"),
    log:
        f"logs/{PROFILE}/boundaries/{{object}}/{{condition}}/lib/chunk{{chunk}}.log",
    benchmark:
        f"{P}/benchmarks/boundaries/{{object}}/{{condition}}/lib/chunk{{chunk}}.tsv"
    params:
        profile=PROFILE,
        object=lambda wc: wc.object,
        condition=lambda wc: wc.condition,
        settings=BOUNDARIES,
        runs=lambda wc: library_runs(wc.chunk, calibration_probe(wc.object), boundary_library_root(wc.object, wc.condition),
                                     export_F=False),
        device=DEVICE,
        deterministic=DETERMINISTIC,
    resources:
        mem_mb=16000 if PROFILE == "paper" else 2000,
        runtime=rollout_minutes(LIBRARY_CHUNK),
        gpu=1 if ON_GPU else 0,
    threads: 1
    script:
        "../scripts/boundaries_rollout.py"


rule boundary_rollout_eval:
    """Rollouts of one theta (a target or a frozen estimate) under the condition."""
    conda:
        "../envs/knockgs.yaml"
    input:
        particles=f"{BB}/{{object}}/{{condition}}/asset.particles.npz",
        summary=f"{BB}/{{object}}/{{condition}}/asset.json",
    output:
        folder=directory(f"{BB}/{{object}}/{{condition}}/eval/{{theta}}"),
    log:
        f"logs/{PROFILE}/boundaries/{{object}}/{{condition}}/eval/{{theta}}.log",
    benchmark:
        f"{P}/benchmarks/boundaries/{{object}}/{{condition}}/eval/{{theta}}.tsv"
    params:
        profile=PROFILE,
        object=lambda wc: wc.object,
        condition=lambda wc: wc.condition,
        settings=BOUNDARIES,
        runs=boundary_eval_runs,
        device=DEVICE,
        deterministic=DETERMINISTIC,
    resources:
        mem_mb=16000 if PROFILE == "paper" else 2000,
        runtime=lambda wc: rollout_minutes(len(boundary_eval_runs(wc))),
        gpu=1 if ON_GPU else 0,
    threads: 1
    script:
        "../scripts/boundaries_rollout.py"


rule boundary_library_descriptors:
    conda:
        "../envs/knockgs.yaml"
    input:
        rollouts=lambda wc: folders(
            library_rollout(boundary_library_root(wc.object, wc.condition), c) for c in CANDIDATES.case_name
        ),
    output:
        table=f"{BB}/{{object}}/{{condition}}/descriptors/library.csv",
    log:
        f"logs/{PROFILE}/boundaries/{{object}}/{{condition}}/descriptors/library.log",
    params:
        rollouts=lambda wc: {c: library_rollout(boundary_library_root(wc.object, wc.condition), c) for c in CANDIDATES.case_name},
    script:
        "../scripts/library_descriptors.py"


rule boundary_query_descriptors:
    conda:
        "../envs/knockgs.yaml"
    input:
        rollouts=lambda wc: folders(boundary_query_rollouts(wc)),
    output:
        table=f"{BB}/{{object}}/{{condition}}/descriptors/queries.csv",
    log:
        f"logs/{PROFILE}/boundaries/{{object}}/{{condition}}/descriptors/queries.log",
    params:
        names=lambda wc: list(target_thetas()),
        rollouts=boundary_query_rollouts,
    script:
        "../scripts/query_descriptors.py"


checkpoint boundary_estimate:
    """Local ridge from Probe A: the condition's queries against the original or the rebuilt library."""
    conda:
        "../envs/knockgs.yaml"
    input:
        library=boundary_library_csv,
        queries=f"{BB}/{{object}}/{{condition}}/descriptors/queries.csv",
    output:
        json=[f"{BB}/{{object}}/{{condition}}/estimates/{{library}}.json"],
    log:
        f"logs/{PROFILE}/boundaries/{{object}}/{{condition}}/estimates/{{library}}.log",
    params:
        methods=[BOUNDARY_METHOD],
        options={BOUNDARY_METHOD: config["method_params"].get(BOUNDARY_METHOD, {})},
        config_hash=config_hash(),
    script:
        "../scripts/estimate.py"


rule boundary_evaluate:
    """Joint error and Probe-B write-back trajectory RMSE of the frozen estimates, under the condition."""
    conda:
        "../envs/knockgs.yaml"
    input:
        estimate=f"{BB}/{{object}}/{{condition}}/estimates/{{library}}.json",
        targets="config/targets.csv",
        rollouts=lambda wc: folders(boundary_writeback_rollouts(wc).values()),
    output:
        table=f"{BB}/{{object}}/{{condition}}/metrics/{{library}}.csv",
    log:
        f"logs/{PROFILE}/boundaries/{{object}}/{{condition}}/metrics/{{library}}.log",
    params:
        split=SPLIT,
        probes=lambda wc: [boundary_probe_b(wc.object)],
        rollouts=boundary_writeback_rollouts,
        labels=lambda wc: {"object": wc.object, "condition": wc.condition, "library": wc.library},
    resources:
        mem_mb=READ_MEM_MB,
    threads: READ_THREADS
    script:
        "../scripts/evaluate.py"


rule boundary_table:
    conda:
        "../envs/knockgs.yaml"
    input:
        metrics=lambda wc: boundary_metrics(wc.object),
        summaries=lambda wc: [f"{BB}/{wc.object}/{c}/asset.json" for c in boundary_condition_names(wc.object)],
    output:
        csv=report(f"{P}/tables/boundaries_{{object}}.csv", caption="../report/boundaries.rst", category="Tables", subcategory="{object}"),
        md=f"{P}/tables/boundaries_{{object}}.md",
    log:
        f"logs/{PROFILE}/tables/boundaries_{{object}}.log",
    params:
        profile=PROFILE,
        probe_a=lambda wc: calibration_probe(wc.object),
        probe_b=boundary_probe_b,
    script:
        "../scripts/boundaries_table.py"


rule boundary_figure:
    conda:
        "../envs/knockgs.yaml"
    input:
        csv=f"{P}/tables/boundaries_{{object}}.csv",
    output:
        report(f"{P}/figures/boundaries_{{object}}.png", caption="../report/boundaries_figure.rst", category="Figures", subcategory="{object}"),
    log:
        f"logs/{PROFILE}/figures/boundaries_{{object}}.log",
    params:
        profile=PROFILE,
    script:
        "../scripts/boundaries_figure.py"


rule loo_library:
    """The shared library of every other object's candidates."""
    conda:
        "../envs/knockgs.yaml"
    input:
        libraries=lambda wc: [f"{P}/descriptors/{o}/library.csv" for o in OBJECTS if o != wc.object],
    output:
        table=f"{BB}/loo/{{object}}/library.csv",
    log:
        f"logs/{PROFILE}/boundaries/loo/{{object}}/library.log",
    params:
        objects=lambda wc: [o for o in OBJECTS if o != wc.object],
    script:
        "../scripts/boundaries_loo_library.py"


checkpoint loo_estimate:
    """Local ridge from Probe A: the held-out object's queries against the shared library."""
    conda:
        "../envs/knockgs.yaml"
    input:
        library=f"{BB}/loo/{{object}}/library.csv",
        queries=f"{P}/descriptors/{{object}}/queries_{SPLIT}.csv",
    output:
        json=[f"{BB}/loo/{{object}}/estimate.json"],
    log:
        f"logs/{PROFILE}/boundaries/loo/{{object}}/estimate.log",
    params:
        methods=[BOUNDARY_METHOD],
        options={BOUNDARY_METHOD: config["method_params"].get(BOUNDARY_METHOD, {})},
        config_hash=config_hash(),
    script:
        "../scripts/estimate.py"


rule loo_evaluate:
    conda:
        "../envs/knockgs.yaml"
    input:
        estimate=f"{BB}/loo/{{object}}/estimate.json",
        targets="config/targets.csv",
        rollouts=lambda wc: folders(loo_writeback_rollouts(wc).values()),
    output:
        table=f"{BB}/loo/{{object}}/metrics.csv",
    log:
        f"logs/{PROFILE}/boundaries/loo/{{object}}/metrics.log",
    params:
        split=SPLIT,
        probes=lambda wc: [boundary_probe_b(wc.object)],
        rollouts=loo_writeback_rollouts,
        labels=lambda wc: {"object": wc.object, "condition": "leave_one_object_out", "library": "shared"},
    resources:
        mem_mb=READ_MEM_MB,
    threads: READ_THREADS
    script:
        "../scripts/evaluate.py"


rule loo_table:
    conda:
        "../envs/knockgs.yaml"
    input:
        metrics=[f"{BB}/loo/{o}/metrics.csv" for o in loo_objects()],
        own=[f"{P}/metrics/{o}/{SPLIT}/{BOUNDARY_METHOD}.csv" for o in loo_objects()],
    output:
        csv=report(f"{P}/tables/loo_object.csv", caption="../report/boundaries_loo.rst", category="Tables"),
        md=f"{P}/tables/loo_object.md",
    log:
        f"logs/{PROFILE}/tables/loo_object.log",
    params:
        profile=PROFILE,
        objects=loo_objects(),
        probes={o: boundary_probe_b(o) for o in loo_objects()},
        trained_on={o: [x for x in OBJECTS if x != o] for o in loo_objects()},
    script:
        "../scripts/boundaries_loo_table.py"


rule boundaries:
    """Named target: every object's boundaries table and figure, and the leave-one-object-out table."""
    input:
        BOUNDARY_OUTPUTS,
