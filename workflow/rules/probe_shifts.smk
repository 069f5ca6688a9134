# Probe shifts and passive versus active observation (docs/probe_shifts.md):
#   P/rollouts/{object}/diag/{split}/duration|contact/{theta}__{probe}.parquet
#                                                       the targets and their frozen estimates under
#                                                       the shift probes (rule rollout_diag_set, simulate.smk)
#   P/tables/duration_{object}.csv|md                   every deployable method's frozen Probe-A estimates
#                                                       under the duration-shift probe, five targets
#   P/tables/contact_{object}.csv|md                    the same under two contact locations, one target
#   P/passive/protocols/{object}.json                   the passive protocol (gravity, no force) and its
#                                                       invariance check
#   P/rollouts/{object}/passive/chunk{chunk}/{theta}.parquet   candidates under the passive protocol
#   P/rollouts/{object}/passive/targets_{split}/{theta}.parquet  the split's targets under it
#   P/passive/descriptors/{object}/library.csv, queries_{split}.csv   passive descriptors
#   P/passive/estimates/{object}/{split}/{method}.json  every deployable estimator from passive responses
#   P/tables/passive_active_{object}.csv|md (+ passive_active_targets_{object}.csv),
#   P/figures/passive_active_{object}.png               both routes compared
# The shift tables exist for objects whose contract declares the shift probes (the Pillow).
# Only Probe A feeds an estimator of the active route, only the passive protocol one of the
# passive route (leakage audit).

from knockgs_core.experiments import PASSIVE_PROBE

include: "inputs/probe_shifts.smk"


DIAG_SETS["duration"] = (lambda obj: shift_cases(obj, [SHIFTS["duration"]], list(target_thetas())),
                         lambda obj: list(shift_estimates(obj).values()))
DIAG_SETS["contact"] = (lambda obj: shift_cases(obj, SHIFTS["contact"], [SHIFTS["contact_target"]]),
                        lambda obj: list(shift_estimates(obj).values()))

SHIFT_OBJECTS = [o for o in OBJECTS if SHIFTS["duration"] in contract(o).probes]
CONTACT_OBJECTS = [o for o in OBJECTS if all(p in contract(o).probes for p in SHIFTS["contact"])]
SHIFT_OUTPUTS = [f"{P}/tables/duration_{o}.{ext}" for o in SHIFT_OBJECTS for ext in ("csv", "md")] + [
    f"{P}/tables/contact_{o}.{ext}" for o in CONTACT_OBJECTS for ext in ("csv", "md")
]


PASSIVE_OUTPUTS = passive_outputs(OBJECTS)
SHIFTS_IN_ALL = register_study("probe_shifts", SHIFT_OUTPUTS, SHIFT_OUTPUTS if SHIFTS["enabled"] else []) \
    + register_study("passive_active", PASSIVE_OUTPUTS,
                     passive_outputs([o for o in OBJECTS if o in SHIFTS["passive_in_all"]]) if SHIFTS["enabled"] else [])
PASSIVE_LIBRARY = {o: [f"{P}/rollouts/{o}/passive/chunk{k}" for k in range(len(LIBRARY_CHUNKS))] for o in OBJECTS}


rule duration_table:
    """Every deployable method's frozen estimates under the duration-shift probe."""
    conda:
        "../envs/knockgs.yaml"
    input:
        unpack(duration_inputs),
    output:
        csv=report(f"{P}/tables/duration_{{object}}.csv", caption="../report/probe_shifts.rst", category="Tables",
                   subcategory="{object}"),
        md=f"{P}/tables/duration_{{object}}.md",
    log:
        f"logs/{PROFILE}/tables/duration_{{object}}.log",
    params:
        kind="duration",
        probes=[SHIFTS["duration"]],
        probe_a=lambda wc: calibration_probe(wc.object),
        split=SPLIT,
        methods=lambda wc: list(shift_estimates(wc.object)),
        rollouts=lambda wc: diag_set_rollouts(wc.object, "duration"),
        probe_a_rollouts=lambda wc: {theta_tag(th): eval_rollout(wc.object, calibration_probe(wc.object), th)
                                     for th in target_thetas().values()},
        targets=lambda wc: list(target_thetas()),
    resources:
        mem_mb=READ_MEM_MB,
    threads: READ_THREADS
    script:
        "../scripts/shift_table.py"


rule contact_table:
    """Every deployable method's frozen estimates of one target under two contact locations."""
    conda:
        "../envs/knockgs.yaml"
    input:
        unpack(contact_inputs),
    output:
        csv=report(f"{P}/tables/contact_{{object}}.csv", caption="../report/probe_shifts.rst", category="Tables",
                   subcategory="{object}"),
        md=f"{P}/tables/contact_{{object}}.md",
    log:
        f"logs/{PROFILE}/tables/contact_{{object}}.log",
    params:
        kind="contact",
        probes=SHIFTS["contact"],
        split=SPLIT,
        methods=lambda wc: list(shift_estimates(wc.object)),
        rollouts=lambda wc: diag_set_rollouts(wc.object, "contact"),
        targets=[SHIFTS["contact_target"]],
    resources:
        mem_mb=READ_MEM_MB,
    threads: READ_THREADS
    script:
        "../scripts/shift_table.py"


rule passive_protocol:
    """The object's passive protocol (gravity along the camera's down direction, no force) and
    the check that it cannot tell (a s_E, a s_rho) from (s_E, s_rho)."""
    conda:
        "../envs/knockgs.yaml"
    input:
        particles=f"{P}/assets/{{object}}.particles.npz",
    output:
        json=f"{P}/passive/protocols/{{object}}.json",
    log:
        f"logs/{PROFILE}/passive/protocols/{{object}}.log",
    params:
        profile=PROFILE,
        object=lambda wc: wc.object,
        device=DEVICE,
        deterministic=DETERMINISTIC,
    resources:
        gpu=1 if ON_GPU else 0,
    script:
        "../scripts/passive_protocol.py"


rule rollout_passive_library:
    """One chunk of candidates under the passive protocol."""
    conda:
        "../envs/knockgs.yaml"
    input:
        particles=f"{P}/assets/{{object}}.particles.npz",
        protocol=f"{P}/passive/protocols/{{object}}.json",
    output:
        folder=directory(f"{P}/rollouts/{{object}}/passive/chunk{{chunk}}"),
    log:
        f"logs/{PROFILE}/rollouts/{{object}}/passive/chunk{{chunk}}.log",
    benchmark:
        f"{P}/benchmarks/rollouts/{{object}}/passive/chunk{{chunk}}.tsv"
    params:
        profile=PROFILE,
        object=lambda wc: wc.object,
        runs=lambda wc: library_runs(wc.chunk, PASSIVE_PROBE, f"{P}/rollouts/{wc.object}/passive", export_F=False),
        device=DEVICE,
        deterministic=DETERMINISTIC,
    resources:
        mem_mb=16000 if PROFILE == "paper" else 2000,
        runtime=rollout_minutes(LIBRARY_CHUNK),
        gpu=1 if ON_GPU else 0,
    threads: 1
    script:
        "../scripts/rollout.py"


rule rollout_passive_targets:
    """The split's targets under the passive protocol (their hidden thetas stay in this job)."""
    conda:
        "../envs/knockgs.yaml"
    input:
        particles=f"{P}/assets/{{object}}.particles.npz",
        protocol=f"{P}/passive/protocols/{{object}}.json",
    output:
        folder=directory(f"{P}/rollouts/{{object}}/passive/targets_{{split}}"),
    log:
        f"logs/{PROFILE}/rollouts/{{object}}/passive/targets_{{split}}.log",
    benchmark:
        f"{P}/benchmarks/rollouts/{{object}}/passive/targets_{{split}}.tsv"
    params:
        profile=PROFILE,
        object=lambda wc: wc.object,
        runs=lambda wc: [{"theta": th, "probe": PASSIVE_PROBE, "rollout": passive_target_rollouts(wc.object, wc.split)[name],
                          "F": None} for name, th in target_thetas(wc.split).items()],
        device=DEVICE,
        deterministic=DETERMINISTIC,
    resources:
        mem_mb=16000 if PROFILE == "paper" else 2000,
        runtime=rollout_minutes(5),
        gpu=1 if ON_GPU else 0,
    threads: 1
    script:
        "../scripts/rollout.py"


rule passive_library_descriptors:
    conda:
        "../envs/knockgs.yaml"
    input:
        rollouts=lambda wc: PASSIVE_LIBRARY[wc.object],
    output:
        table=f"{P}/passive/descriptors/{{object}}/library.csv",
    log:
        f"logs/{PROFILE}/passive/descriptors/{{object}}/library.log",
    params:
        rollouts=lambda wc: {case: library_rollout(f"{P}/rollouts/{wc.object}/passive", case) for case in _CANDIDATE_NAMES},
    script:
        "../scripts/library_descriptors.py"


rule passive_query_descriptors:
    conda:
        "../envs/knockgs.yaml"
    input:
        rollouts=f"{P}/rollouts/{{object}}/passive/targets_{{split}}",
    output:
        table=f"{P}/passive/descriptors/{{object}}/queries_{{split}}.csv",
    log:
        f"logs/{PROFILE}/passive/descriptors/{{object}}/queries_{{split}}.log",
    params:
        names=lambda wc: list(target_thetas(wc.split)),
        rollouts=lambda wc: list(passive_target_rollouts(wc.object, wc.split).values()),
    script:
        "../scripts/query_descriptors.py"


rule passive_estimate:
    """Every deployable method of the config from the passive library and the targets' passive
    queries, one file a method (one job)."""
    conda:
        "../envs/knockgs.yaml"
    input:
        library=f"{P}/passive/descriptors/{{object}}/library.csv",
        queries=f"{P}/passive/descriptors/{{object}}/queries_{{split}}.csv",
    output:
        json=[f"{P}/passive/estimates/{{object}}/{{split}}/{m}.json" for m in CONFIG_DEPLOYABLE],
    log:
        f"logs/{PROFILE}/passive/estimates/{{object}}/{{split}}.log",
    params:
        methods=CONFIG_DEPLOYABLE,
        options={m: config["method_params"].get(m, {}) for m in CONFIG_DEPLOYABLE},
        config_hash=config_hash(),
    script:
        "../scripts/estimate.py"


rule passive_active_table:
    """Both routes, every deployable method: joint, ratio- and scale-direction errors."""
    conda:
        "../envs/knockgs.yaml"
    input:
        active=lambda wc: [f"{P}/estimates/{wc.object}/{SPLIT}/{m}.json" for m in CONFIG_DEPLOYABLE],
        passive=lambda wc: [f"{P}/passive/estimates/{wc.object}/{SPLIT}/{m}.json" for m in CONFIG_DEPLOYABLE],
        protocol=f"{P}/passive/protocols/{{object}}.json",
        targets="config/targets.csv",
    output:
        csv=report(f"{P}/tables/passive_active_{{object}}.csv", caption="../report/probe_shifts.rst", category="Tables",
                   subcategory="{object}"),
        md=f"{P}/tables/passive_active_{{object}}.md",
        rows=f"{P}/tables/passive_active_targets_{{object}}.csv",
        png=report(f"{P}/figures/passive_active_{{object}}.png", caption="../report/probe_shifts.rst", category="Figures",
                   subcategory="{object}"),
    log:
        f"logs/{PROFILE}/tables/passive_active_{{object}}.log",
    params:
        methods=CONFIG_DEPLOYABLE,
        split=SPLIT,
        object=lambda wc: wc.object,
    script:
        "../scripts/passive_active_table.py"


rule probe_shifts:
    """Named target: the duration and contact tables of every object that declares the probes."""
    input:
        SHIFT_OUTPUTS,


rule passive_active:
    """Named target: passive versus active identifiability for every object."""
    input:
        PASSIVE_OUTPUTS,
