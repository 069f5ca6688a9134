# Audits: separate rules, each writing a machine-readable verdict; a failed audit fails the run
# (its verdict is kept in logs/{profile}/audits/NAME.failed.json).

rule audit_leakage:
    conda:
        "../envs/knockgs.yaml"
    input:
        estimates=_all_estimates(),
        library=lambda wc: [lib_rollout(o, c) for o in OBJECTS for c in CANDIDATES.case_name],
    output:
        "results/audits/leakage.json",
    log:
        f"logs/{PROFILE}/audits/leakage.log",
    params:
        calibration={o: calibration_probe(o) for o in OBJECTS},
        split=SPLIT,
    script:
        "../scripts/audit.py"


rule audit_nonfinite:
    conda:
        "../envs/knockgs.yaml"
    input:
        tables=_reported_tables(),
    output:
        "results/audits/nonfinite.json",
    log:
        f"logs/{PROFILE}/audits/nonfinite.log",
    params:
        rollout_dirs=[f"{P}/rollouts/{o}" for o in OBJECTS],
    script:
        "../scripts/audit.py"


rule audit_missing_frames:
    conda:
        "../envs/knockgs.yaml"
    input:
        tables=_reported_tables(),
    output:
        "results/audits/missing_frames.json",
    log:
        f"logs/{PROFILE}/audits/missing_frames.log",
    params:
        rollout_dirs=[f"{P}/rollouts/{o}" for o in OBJECTS],
    script:
        "../scripts/audit.py"


rule audit_duplicates:
    conda:
        "../envs/knockgs.yaml"
    input:
        libraries=[f"{P}/descriptors/{o}/library.csv" for o in OBJECTS],
    output:
        "results/audits/duplicates.json",
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
        tables=_reported_tables(),
    output:
        "results/audits/completion.json",
    log:
        f"logs/{PROFILE}/audits/completion.log",
    params:
        expected=lambda wc: [f for f in all_outputs() if not f.startswith("results/audits/")],
        methods=METHODS,
        mains=[f"results/tables/main_{o}.csv" for o in OBJECTS],
    script:
        "../scripts/audit.py"
