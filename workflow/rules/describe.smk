# Probe-A descriptors: the candidate library and the targets' queries (no labels).


rule library_descriptors:
    conda:
        "../envs/knockgs.yaml"
    input:
        rollouts=lambda wc: folders(library_rollouts(wc.object).values()),
    output:
        table=f"{P}/descriptors/{{object}}/library.csv",
    log:
        f"logs/{PROFILE}/descriptors/{{object}}/library.log",
    params:
        rollouts=lambda wc: library_rollouts(wc.object),
    resources:
        mem_mb=READ_MEM_MB,
    threads: READ_THREADS
    script:
        "../scripts/library_descriptors.py"


rule query_descriptors:
    conda:
        "../envs/knockgs.yaml"
    input:
        rollouts=lambda wc: folders(query_rollouts(wc)),
    output:
        table=f"{P}/descriptors/{{object}}/queries_{{split}}.csv",
    log:
        f"logs/{PROFILE}/descriptors/{{object}}/queries_{{split}}.log",
    params:
        names=lambda wc: list(target_thetas(wc.split)),
        rollouts=query_rollouts,
    resources:
        mem_mb=READ_MEM_MB,
    threads: READ_THREADS
    script:
        "../scripts/query_descriptors.py"
