# Asset and interior fill: one job per object.


rule asset:
    conda:
        "../envs/knockgs.yaml"
    output:
        ply=f"{P}/assets/{{object}}.ply",
        particles=f"{P}/assets/{{object}}.particles.npz",
        scene=f"{P}/assets/{{object}}.scene.npz",
        summary=f"{P}/assets/{{object}}.summary.json",
        figure=report(f"{P}/figures/fill_{{object}}.png", caption="../report/fill.rst", category="Assets"),
    log:
        f"logs/{PROFILE}/assets/{{object}}.log",
    benchmark:
        f"{P}/benchmarks/assets/{{object}}.tsv"
    params:
        profile=PROFILE,
    resources:
        mem_mb=8000 if PROFILE == "paper" else 2000,
        runtime=30,
    threads: 1
    script:
        "../scripts/asset.py"
