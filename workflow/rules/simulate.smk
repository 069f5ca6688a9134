# MPM rollouts, cached as Parquet: one file per (object, theta, probe).
#
# A job simulates several rollouts in one process: a chunk of LIBRARY_CHUNK candidates
# (library), one theta under the evaluation probes of its object (evaluation), or every
# rollout one diagnostics' study adds (a diagnostics' set). Process
# start-up (Python, Warp, the contract) costs ~2 s a job on a laptop CPU, as much as a whole
# Pillow rollout; amortizing it keeps the default `all` within its time budget. Every
# rollout still has its own Parquet file, in the job's output folder, and a finished job is
# never re-run. A candidate's library rollout doubles as its Probe-A evaluation rollout
# (common.smk: eval_rollout), so the evaluation job of a candidate theta simulates only
# the held-out probes (common.smk: simulated_probes).


rule rollout_library:
    """Probe-A rollouts of one chunk of candidates (library members), with the deformation
    gradients unless LIBRARY_F is false: a candidate's library rollout is also its Probe-A
    evaluation rollout."""
    conda:
        "../envs/knockgs.yaml"
    input:
        particles=f"{P}/assets/{{object}}.particles.npz",
    output:
        folder=directory(f"{P}/rollouts/{{object}}/lib/chunk{{chunk}}"),
    log:
        f"logs/{PROFILE}/rollouts/{{object}}/lib/chunk{{chunk}}.log",
    benchmark:
        f"{P}/benchmarks/rollouts/{{object}}/lib/chunk{{chunk}}.tsv"
    params:
        profile=PROFILE,
        object=lambda wc: wc.object,
        runs=lambda wc: library_runs(wc.chunk, calibration_probe(wc.object), library_root(wc.object), export_F=LIBRARY_F),
        device=DEVICE,
        deterministic=DETERMINISTIC,
    resources:
        mem_mb=16000 if PROFILE == "paper" else 2000,
        runtime=rollout_minutes(LIBRARY_CHUNK),
        gpu=1 if ON_GPU else 0,
    threads: 1
    script:
        "../scripts/rollout.py"


rule rollout_eval:
    """Evaluation rollouts of one theta (a target or a frozen estimate) under the object's
    evaluation probes (a candidate theta: its held-out probes), with the deformation
    gradients of the Gaussian-associated particles for rendering."""
    conda:
        "../envs/knockgs.yaml"
    input:
        particles=f"{P}/assets/{{object}}.particles.npz",
    output:
        folder=directory(f"{P}/rollouts/{{object}}/eval/{{theta}}"),
        # render.keep_deformation_gradients false: F in a temporary folder of its own
        **({"F_folder": temp(directory(f"{P}/rollouts/{{object}}/evalF/{{theta}}"))} if EVAL_F_TEMP else {}),
    log:
        f"logs/{PROFILE}/rollouts/{{object}}/eval/{{theta}}.log",
    benchmark:
        f"{P}/benchmarks/rollouts/{{object}}/eval/{{theta}}.tsv"
    params:
        profile=PROFILE,
        object=lambda wc: wc.object,
        runs=evaluation_runs,
        device=DEVICE,
        deterministic=DETERMINISTIC,
    resources:
        mem_mb=16000 if PROFILE == "paper" else 2000,
        runtime=lambda wc: rollout_minutes(len(simulated_probes(wc.object, wc.theta))),
        gpu=1 if ON_GPU else 0,
    threads: 1
    script:
        "../scripts/rollout.py"


rule rollout_diag_set:
    """A diagnostics' set: every (theta, probe) a study simulates beyond the evaluation rollouts
    (the probe shifts' ``duration`` and ``contact``, each rung's Probe B of the observation
    ladder, ``ladder-{rung}``), without deformation gradients, in one job. Which thetas is known
    only once the study's estimates exist (their checkpoints)."""
    conda:
        "../envs/knockgs.yaml"
    input:
        particles=f"{P}/assets/{{object}}.particles.npz",
        estimates=diag_set_estimates,
    output:
        folder=directory(f"{P}/rollouts/{{object}}/diag/{SPLIT}/{{set}}"),
    log:
        f"logs/{PROFILE}/rollouts/{{object}}/diag/{SPLIT}/{{set}}.log",
    benchmark:
        f"{P}/benchmarks/rollouts/{{object}}/diag/{SPLIT}/{{set}}.tsv"
    wildcard_constraints:
        set="[^/]+",  # a registered diagnostics' set (DIAG_SETS)
    params:
        profile=PROFILE,
        object=lambda wc: wc.object,
        runs=diag_set_runs,
        device=DEVICE,
        deterministic=DETERMINISTIC,
    resources:
        mem_mb=16000 if PROFILE == "paper" else 2000,
        runtime=lambda wc: rollout_minutes(len(diag_set_runs(wc))),
        gpu=1 if ON_GPU else 0,
    threads: 1
    script:
        "../scripts/rollout.py"
