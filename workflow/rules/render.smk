# Rendering: every evaluation rollout rendered with the same renderer and camera; image
# metrics of each method's frozen estimates against the hidden target's frames.


rule render:
    conda:
        "../envs/knockgs.yaml"
    input:
        ply=f"{P}/assets/{{object}}.ply",
        scene=f"{P}/assets/{{object}}.scene.npz",
        rollout=f"{P}/rollouts/{{object}}/eval/{{probe}}/{{theta}}.parquet",
        F=f"{P}/rollouts/{{object}}/eval/{{probe}}/{{theta}}.F.parquet",
    output:
        frames=f"{P}/renders/{{object}}/{{probe}}/{{theta}}.npz",
    log:
        f"logs/{PROFILE}/renders/{{object}}/{{probe}}/{{theta}}.log",
    benchmark:
        f"results/{PROFILE}/benchmarks/renders/{{object}}/{{probe}}/{{theta}}.tsv"
    params:
        camera=lambda wc: CONTRACTS[wc.object].camera,
        width=RENDER["width"],
        height=RENDER["height"],
        device=DEVICE,
    resources:
        mem_mb=4000,
        runtime=30,
        gpu=1 if ON_GPU else 0,
    script:
        "../scripts/render.py"


rule render_metrics:
    conda:
        "../envs/knockgs.yaml"
    input:
        unpack(render_metric_inputs),
    output:
        table=f"{P}/render/{{object}}/{{split}}/{{method}}.csv",
    log:
        f"logs/{PROFILE}/render/{{object}}/{{split}}/{{method}}.log",
    params:
        probes=lambda wc: eval_probes(wc.object),
        render_dir=lambda wc: f"{P}/renders/{wc.object}",
    script:
        "../scripts/render_metrics.py"


rule render_table:
    conda:
        "../envs/knockgs.yaml"
    input:
        metrics=lambda wc: [f"{P}/render/{wc.object}/{SPLIT}/{m}.csv" for m in METHODS],
    output:
        csv=report("results/tables/render_{object}.csv", caption="../report/render_table.rst", category="Tables", subcategory="{object}"),
        md="results/tables/render_{object}.md",
    log:
        f"logs/{PROFILE}/tables/render_{{object}}.log",
    params:
        methods=METHODS,
        probes=lambda wc: eval_probes(wc.object),
        profile=PROFILE,
    script:
        "../scripts/render_table.py"


rule qualitative:
    conda:
        "../envs/knockgs.yaml"
    input:
        unpack(qualitative_inputs),
    output:
        png=report("results/figures/qualitative_{object}.png", caption="../report/qualitative.rst", category="Figures", subcategory="{object}"),
        gif=report("results/figures/compare_{object}.gif", caption="../report/gif.rst", category="Figures", subcategory="{object}"),
    log:
        f"logs/{PROFILE}/figures/qualitative_{{object}}.log",
    params:
        methods=METHODS,
        probe=lambda wc: heldout_probes(wc.object)[0],
        target=RENDER["gif_target"],
    script:
        "../scripts/qualitative.py"
