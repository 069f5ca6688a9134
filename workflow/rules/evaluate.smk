# Frozen write-back: every estimate re-simulated under Probe A and each Probe B, compared
# with the hidden target's rollouts (truth revealed only here).


def evaluation_inputs(wc):
    ests = estimated_thetas(wc)
    truths = target_thetas(wc.split)
    rollouts = set()
    for probe in eval_probes(wc.object):
        for th in list(ests.values()) + list(truths.values()):
            rollouts.add(eval_rollout(wc.object, probe, th))
    return {"estimate": estimate_json(wc), "targets": "config/targets.csv", "rollouts": sorted(rollouts)}


rule evaluate:
    input:
        unpack(evaluation_inputs),
    output:
        table=f"{P}/metrics/{{object}}/{{split}}/{{method}}.csv",
    log:
        f"logs/{PROFILE}/metrics/{{object}}/{{split}}/{{method}}.log",
    params:
        probes=lambda wc: eval_probes(wc.object),
        split=lambda wc: wc.split,
        rollout_dir=lambda wc: f"{P}/rollouts/{wc.object}/eval",
    script:
        "../scripts/evaluate.py"
