# CMA-ES direct video optimization, the alternative inverse route (docs/cmaes.md):
#   P/cmaes/estimates/{object}/{split}/seed{seed}.json   CMA-ES on (log s_E, log s_rho) against each target's
#                                                        rendered RGB-D Probe-A video, `cmaes.budget` simulator
#                                                        calls per target, then frozen (checkpoint; one job per seed)
#   P/tables/cmaes_{object}.csv|md                       their write-back evaluation under Probe A and every
#                                                        Probe B (joint error, trajectory RMSE, foreground PSNR,
#                                                        crop SSIM), mean +- sd over seeds, simulator calls beside
#                                                        the library's offline rollouts
# The frozen thetas' evaluation rollouts and frames are made by rollout_eval (simulate.smk) and
# render (render.smk), as every estimate's. Only the targets' Probe-A rollouts (their rendered
# video) enter the search: no descriptor, no library, no label. Helpers: common.smk (cmaes_*).

include: "inputs/cmaes.smk"


CMAES = config["cmaes"]
CMAES_OUTPUTS = [f"{P}/tables/cmaes_{o}.{ext}" for o in OBJECTS for ext in ("csv", "md")]
CMAES_IN_ALL = register_study("cmaes", CMAES_OUTPUTS, CMAES_OUTPUTS if CMAES["enabled"] else [])


checkpoint cmaes_estimate:
    """CMA-ES of one seed for every target of the split: each target's Probe-A rollout is
    rendered as an RGB-D video once, then `budget` candidates are simulated under Probe A,
    rendered and scored against it; the lowest-loss theta is frozen."""
    conda:
        "../envs/knockgs.yaml"
    input:
        ply=f"{P}/assets/{{object}}.ply",
        scene=f"{P}/assets/{{object}}.scene.npz",
        particles=f"{P}/assets/{{object}}.particles.npz",
        candidates="config/candidates.csv",
        rollouts=lambda wc: folders(r["rollout"] for r in cmaes_target_rollouts(wc.object, wc.split).values()),
        F=lambda wc: temp_F_folders(cmaes_target_rollouts(wc.object, wc.split).values()),
    output:
        json=f"{P}/cmaes/estimates/{{object}}/{{split}}/seed{{seed}}.json",
    log:
        f"logs/{PROFILE}/cmaes/estimates/{{object}}/{{split}}/seed{{seed}}.log",
    benchmark:
        f"{P}/benchmarks/cmaes/estimates/{{object}}/{{split}}/seed{{seed}}.tsv"
    wildcard_constraints:
        seed="[0-9]+",
    params:
        profile=PROFILE,
        object=lambda wc: wc.object,
        seed=lambda wc: int(wc.seed),
        targets=lambda wc: cmaes_target_rollouts(wc.object, wc.split),
        probe=lambda wc: calibration_probe(wc.object),
        budget=CMAES["budget"],
        width=CMAES["width"],
        height=CMAES["height"],
        depth_weight=CMAES["depth_weight"],
        device=DEVICE,
        deterministic=DETERMINISTIC,
        config_hash=config_hash(),
    resources:
        mem_mb=16000 if PROFILE == "paper" else 2000,
        runtime=lambda wc: (2 if PROFILE == "paper" else 1) * CMAES["budget"] * len(target_thetas(wc.split)),
        gpu=1 if ON_GPU else 0,
    threads: 1
    script:
        "../scripts/cmaes_estimate.py"


rule cmaes_table:
    """Every seed's frozen CMA-ES estimates written back: joint error, trajectory RMSE and image
    metrics under every evaluation probe, mean +- sd over seeds, per target and over targets."""
    conda:
        "../envs/knockgs.yaml"
    input:
        # the seed files as plain paths (every seed's job scheduled at once), their thetas'
        # rollouts and frames through the checkpoint
        estimates=lambda wc: [cmaes_estimate_file(wc.object, SPLIT, s) for s in CMAES["seeds"]],
        targets="config/targets.csv",
        rollouts=lambda wc: folders(cmaes_eval_paths(wc.object, SPLIT, CMAES["seeds"], eval_rollout).values()),
        frames=lambda wc: folders(cmaes_eval_paths(wc.object, SPLIT, CMAES["seeds"], frames_file).values()),
    output:
        csv=report(f"{P}/tables/cmaes_{{object}}.csv", caption="../report/cmaes.rst", category="Tables",
                   subcategory="{object}"),
        md=f"{P}/tables/cmaes_{{object}}.md",
    log:
        f"logs/{PROFILE}/tables/cmaes_{{object}}.log",
    params:
        profile=PROFILE,
        split=SPLIT,
        seeds=CMAES["seeds"],
        budget=CMAES["budget"],
        width=CMAES["width"],
        height=CMAES["height"],
        probes=lambda wc: eval_probes(wc.object),
        rollouts=lambda wc: cmaes_eval_paths(wc.object, SPLIT, CMAES["seeds"], eval_rollout),
        frames=lambda wc: cmaes_eval_paths(wc.object, SPLIT, CMAES["seeds"], frames_file),
        library_rollouts=len(CANDIDATES),
    script:
        "../scripts/cmaes_table.py"


rule cmaes:
    """Named target: the CMA-ES video route's table for every object."""
    input:
        CMAES_OUTPUTS,
