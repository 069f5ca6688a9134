# Rendering: every evaluation rollout rendered with the same renderer and camera; image
# metrics of each method's frozen estimates against the hidden target's frames.


for _obj in OBJECTS:

    rule:
        """Every frame of one theta's evaluation rollouts, under every evaluation probe of the
        object (one process per theta: start-up is amortized over the probes)."""
        name:
            f"render_{_obj}"
        conda:
            "../envs/knockgs.yaml"
        input:
            ply=f"{P}/assets/{_obj}.ply",
            scene=f"{P}/assets/{_obj}.scene.npz",
            rollouts=lambda wc, o=_obj: [eval_rollout(o, pr, parse_theta(wc.theta)) for pr in eval_probes(o)],
            F=lambda wc, o=_obj: [eval_deformation(o, pr, parse_theta(wc.theta)) for pr in eval_probes(o)],
        output:
            frames=[f"{P}/renders/{_obj}/{pr}/{{theta}}.npz" for pr in eval_probes(_obj)],
        log:
            f"logs/{PROFILE}/renders/{_obj}/{{theta}}.log",
        benchmark:
            f"results/{PROFILE}/benchmarks/renders/{_obj}/{{theta}}.tsv"
        params:
            camera=CONTRACTS[_obj].camera,
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
