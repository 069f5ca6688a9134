# Probe-A descriptors: the candidate library and the targets' queries (no labels).


rule library_descriptors:
    conda:
        "../envs/knockgs.yaml"
    input:
        rollouts=lambda wc: [lib_rollout(wc.object, c) for c in CANDIDATES.case_name],
    output:
        table=f"{P}/descriptors/{{object}}/library.csv",
    log:
        f"logs/{PROFILE}/descriptors/{{object}}/library.log",
    params:
        cases=list(CANDIDATES.case_name),
    script:
        "../scripts/library_descriptors.py"


rule query_descriptors:
    conda:
        "../envs/knockgs.yaml"
    input:
        rollouts=lambda wc: [eval_rollout(wc.object, calibration_probe(wc.object), th) for th in target_thetas(wc.split).values()],
    output:
        table=f"{P}/descriptors/{{object}}/queries_{{split}}.csv",
    log:
        f"logs/{PROFILE}/descriptors/{{object}}/queries_{{split}}.log",
    params:
        names=lambda wc: list(target_thetas(wc.split)),
    script:
        "../scripts/query_descriptors.py"
