# Rendering: every evaluation rollout rendered with the same renderer and camera; image
# metrics of each method's frozen estimates against the hidden target's frames.

RENDER_OUTPUTS = [
    path
    for o in (OBJECTS if RENDER["enabled"] else [])
    for path in (f"{P}/tables/render_{o}.csv", f"{P}/tables/render_{o}.md", f"{P}/figures/qualitative_{o}.png", f"{P}/figures/compare_{o}.gif")
]


rule render:
    """Every frame of one theta's evaluation rollouts, under every evaluation probe of the
    object (one process per theta: start-up is amortized over the probes)."""
    conda:
        "../envs/knockgs.yaml"
    input:
        ply=f"{P}/assets/{{object}}.ply",
        scene=f"{P}/assets/{{object}}.scene.npz",
        rollouts=lambda wc: folders(job["rollout"] for job in render_jobs(wc)),
        F=lambda wc: temp_F_folders(render_jobs(wc)),
    output:
        folder=directory(f"{P}/frames/{{object}}/{{theta}}"),
    log:
        f"logs/{PROFILE}/frames/{{object}}/{{theta}}.log",
    benchmark:
        f"{P}/benchmarks/frames/{{object}}/{{theta}}.tsv"
    params:
        jobs=render_jobs,
        camera=lambda wc: contract(wc.object).camera,
        width=RENDER["width"],
        height=RENDER["height"],
        device=DEVICE,
    resources:
        mem_mb=4000,
        runtime=30,
        gpu=1 if ON_GPU else 0,
    # with temporary F (render.keep_deformation_gradients false) a theta's render runs as soon as
    # its rollouts are done, so few thetas' F are on disk at once
    priority: 1 if EVAL_F_TEMP else 0
    script:
        "../scripts/render.py"


rule render_metrics:
    conda:
        "../envs/knockgs.yaml"
    input:
        unpack(render_metric_inputs),
    output:
        table=f"{P}/render_metrics/{{object}}/{{split}}/{{method}}.csv",
    log:
        f"logs/{PROFILE}/render_metrics/{{object}}/{{split}}/{{method}}.log",
    params:
        probes=lambda wc: eval_probes(wc.object),
        frames=render_frames,
    script:
        "../scripts/render_metrics.py"


rule render_table:
    conda:
        "../envs/knockgs.yaml"
    input:
        metrics=lambda wc: [f"{P}/render_metrics/{wc.object}/{SPLIT}/{m}.csv" for m in METHODS],
    output:
        csv=report(f"{P}/tables/render_{{object}}.csv", caption="../report/render_table.rst", category="Tables", subcategory="{object}"),
        md=f"{P}/tables/render_{{object}}.md",
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
        png=report(f"{P}/figures/qualitative_{{object}}.png", caption="../report/qualitative.rst", category="Figures", subcategory="{object}"),
        gif=report(f"{P}/figures/compare_{{object}}.gif", caption="../report/gif.rst", category="Figures", subcategory="{object}"),
    log:
        f"logs/{PROFILE}/figures/qualitative_{{object}}.log",
    params:
        frames=qualitative_frames,
        methods=METHODS,
        probe=lambda wc: heldout_probes(wc.object)[0],
        target=RENDER["gif_target"],
    script:
        "../scripts/qualitative.py"
