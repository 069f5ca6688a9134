# Frozen write-back: every estimate re-simulated under Probe A and each Probe B, compared
# with the hidden target's rollouts (truth revealed only here).


rule evaluate:
    conda:
        "../envs/knockgs.yaml"
    input:
        unpack(evaluation_inputs),
    output:
        table=f"{P}/metrics/{{object}}/{{split}}/{{method}}.csv",
    log:
        f"logs/{PROFILE}/metrics/{{object}}/{{split}}/{{method}}.log",
    params:
        probes=lambda wc: eval_probes(wc.object),
        split=lambda wc: wc.split,
        rollouts=evaluation_rollouts,
        labels=lambda wc: {"object": wc.object, "method": wc.method},
    resources:
        mem_mb=READ_MEM_MB,
    threads: READ_THREADS
    script:
        "../scripts/evaluate.py"
