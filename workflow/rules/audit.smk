# Audits: separate rules, each writing a machine-readable verdict; a failed audit fails the run
# (its verdict is kept in logs/{profile}/audits/NAME.failed.json).

AUDITS = ["leakage", "nonfinite", "missing_frames", "rollout_metadata", "duplicates", "completion"]
AUDIT_OUTPUTS = [f"{P}/audits/{name}.json" for name in AUDITS]
# the reported tables, checked for non-finite cells
REPORTED_TABLES = (
    [f"{P}/tables/main_{o}.csv" for o in OBJECTS]
    + [f"{P}/tables/targetwise_{o}.csv" for o in OBJECTS]
    + [f"{P}/tables/objects.csv"]
    + ([f"{P}/tables/render_{o}.csv" for o in OBJECTS] if RENDER["enabled"] else [])
)
LIBRARY_ROLLOUTS = [path for o in OBJECTS for path in library_rollouts(o).values()]
# the descriptor tables between the rollouts and the estimators, checked for non-finite cells too
DESCRIPTOR_TABLES = [f"{P}/descriptors/{o}/{name}.csv" for o in OBJECTS for name in ("library", f"queries_{SPLIT}")]
# the splits whose deployable estimates the leakage audit reads: the main one and, with the
# splits in `all`, the alternative splits (diagnostics.smk, included before this file)
AUDITED_SPLITS = DIAGNOSTIC_SPLITS if DIAGNOSTICS["enabled"] and DIAGNOSTICS["splits_in_all"] else [SPLIT]
# the studies whose tables (in `all`, by their config switches) the non-finite audit reads besides
# the main ones: every cell a number, or a word by design (the convergence tables' "not in the
# asymptotic range")
NONFINITE_STUDIES = ("diagnostics", "probe_shifts", "passive_active", "ladder", "cmaes", "convergence")
STUDY_TABLES = [path for name in NONFINITE_STUDIES for path in STUDIES[name]["in_all"] if path.endswith(".csv")]
# the objects whose passive route is in `all` (probe_shifts.smk): their passive estimates and
# library are audited like the active ones
PASSIVE_AUDITED = [o for o in OBJECTS if f"{P}/tables/passive_active_{o}.csv" in SHIFTS_IN_ALL]



rule audit_leakage:
    conda:
        "../envs/knockgs.yaml"
    input:
        estimates=[f"{P}/estimates/{o}/{s}/{m}.json" for o in OBJECTS for s in AUDITED_SPLITS for m in METHODS]
        + [f"{P}/passive/estimates/{o}/{SPLIT}/{m}.json" for o in PASSIVE_AUDITED for m in CONFIG_DEPLOYABLE]
        + [f"{P}/ladder/estimates/{o}/{SPLIT}/{rung}/{m}.json" for o in (OBJECTS if LADDER["in_all"] else [])
           for rung in LADDER_RUNGS for m in CONFIG_DEPLOYABLE],
        library=folders(LIBRARY_ROLLOUTS),
        passive_library=[folder for o in PASSIVE_AUDITED for folder in PASSIVE_LIBRARY[o]],
        sensitivity=[path for path in DIAGNOSTICS_IN_ALL
                     if os.path.basename(path).startswith("sensitivity_k_alpha_") and path.endswith(".csv")],
    output:
        f"{P}/audits/leakage.json",
    log:
        f"logs/{PROFILE}/audits/leakage.log",
    params:
        calibration={o: calibration_probe(o) for o in OBJECTS},
        library=LIBRARY_ROLLOUTS,
        passive_library=[library_rollout(f"{P}/rollouts/{o}/passive", case) for o in PASSIVE_AUDITED for case in _CANDIDATE_NAMES],
        split=SPLIT,
        frozen=config["method_params"].get("local_ridge", {}),
    script:
        "../scripts/audit.py"


rule audit_nonfinite:
    conda:
        "../envs/knockgs.yaml"
    input:
        tables=REPORTED_TABLES + DESCRIPTOR_TABLES + STUDY_TABLES,
    output:
        f"{P}/audits/nonfinite.json",
    log:
        f"logs/{PROFILE}/audits/nonfinite.log",
    params:
        rollout_dirs=[f"{P}/rollouts/{o}" for o in OBJECTS],
    resources:
        mem_mb=READ_MEM_MB,
    threads: READ_THREADS
    script:
        "../scripts/audit.py"


rule audit_missing_frames:
    conda:
        "../envs/knockgs.yaml"
    input:
        tables=REPORTED_TABLES,
    output:
        f"{P}/audits/missing_frames.json",
    log:
        f"logs/{PROFILE}/audits/missing_frames.log",
    params:
        rollout_dirs=[f"{P}/rollouts/{o}" for o in OBJECTS],
    resources:
        mem_mb=READ_MEM_MB,
    threads: READ_THREADS
    script:
        "../scripts/audit.py"


rule audit_rollout_metadata:
    """Every cached rollout is the one its path names (object, profile, contract hash, theta,
    probe, particle and frame counts) and every F file belongs to its rollout: a rollout
    copied over another's path, or truncated with its old time stamp, fails the run."""
    conda:
        "../envs/knockgs.yaml"
    input:
        tables=REPORTED_TABLES,
        particles=[f"{P}/assets/{o}.particles.npz" for o in OBJECTS],
    output:
        f"{P}/audits/rollout_metadata.json",
    log:
        f"logs/{PROFILE}/audits/rollout_metadata.log",
    params:
        objects=OBJECTS,
        profile=PROFILE,
        rollout_dirs=[f"{P}/rollouts/{o}" for o in OBJECTS],
    script:
        "../scripts/audit.py"


rule audit_duplicates:
    conda:
        "../envs/knockgs.yaml"
    input:
        libraries=[f"{P}/descriptors/{o}/library.csv" for o in OBJECTS],
    output:
        f"{P}/audits/duplicates.json",
    log:
        f"logs/{PROFILE}/audits/duplicates.log",
    params:
        split=SPLIT,
    script:
        "../scripts/audit.py"


rule audit_completion:
    conda:
        "../envs/knockgs.yaml"
    input:
        tables=REPORTED_TABLES,
        studies=studies_in_all(),
    output:
        f"{P}/audits/completion.json",
    log:
        f"logs/{PROFILE}/audits/completion.log",
    params:
        expected=[path for path in REPORT_OUTPUTS + RENDER_OUTPUTS + studies_in_all() if not path.startswith(f"{P}/audits/")],
        methods=METHODS,
        mains=[f"{P}/tables/main_{o}.csv" for o in OBJECTS],
        results=lambda wc, output: os.path.dirname(os.path.dirname(output[0])),  # the profile's results folder
    script:
        "../scripts/audit.py"
