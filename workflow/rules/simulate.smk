# MPM rollouts, cached as Parquet, one job per (object, theta, probe).


rule rollout_library:
    """A candidate's Probe-A rollout (library member)."""
    conda:
        "../envs/knockgs.yaml"
    input:
        particles=f"{P}/assets/{{object}}.particles.npz",
    output:
        rollout=f"{P}/rollouts/{{object}}/lib/{{theta}}.parquet",
    log:
        f"logs/{PROFILE}/rollouts/{{object}}/lib/{{theta}}.log",
    benchmark:
        f"results/{PROFILE}/benchmarks/rollouts/{{object}}/lib/{{theta}}.tsv"
    params:
        profile=PROFILE,
        probe=lambda wc: calibration_probe(wc.object),
        theta=lambda wc: parse_theta(wc.theta),
        export_F=False,
        device=DEVICE,
    resources:
        mem_mb=_rollout_resources,
        runtime=60 if PROFILE == "paper" else 20,
        gpu=1 if ON_GPU else 0,
    threads: 1
    script:
        "../scripts/rollout.py"


rule rollout_eval:
    """Evaluation rollout at any theta (targets and frozen estimates) under any probe, with the
    deformation gradients of the Gaussian-associated particles for rendering."""
    conda:
        "../envs/knockgs.yaml"
    input:
        particles=f"{P}/assets/{{object}}.particles.npz",
    output:
        rollout=f"{P}/rollouts/{{object}}/eval/{{probe}}/{{theta}}.parquet",
        F=f"{P}/rollouts/{{object}}/eval/{{probe}}/{{theta}}.F.parquet",
    log:
        f"logs/{PROFILE}/rollouts/{{object}}/eval/{{probe}}/{{theta}}.log",
    benchmark:
        f"results/{PROFILE}/benchmarks/rollouts/{{object}}/eval/{{probe}}/{{theta}}.tsv"
    params:
        profile=PROFILE,
        probe=lambda wc: wc.probe,
        theta=lambda wc: parse_theta(wc.theta),
        export_F=True,
        device=DEVICE,
    resources:
        mem_mb=_rollout_resources,
        runtime=60 if PROFILE == "paper" else 20,
        gpu=1 if ON_GPU else 0,
    threads: 1
    script:
        "../scripts/rollout.py"
