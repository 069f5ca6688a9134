# Tables and figures: the paper's main table per object, target-wise table, three-object table.

REPORT_OUTPUTS = [
    path
    for o in OBJECTS
    for path in (f"{P}/tables/main_{o}.csv", f"{P}/tables/main_{o}.md", f"{P}/tables/targetwise_{o}.csv", f"{P}/tables/targetwise_{o}.md",
                 f"{P}/figures/main_{o}.png", f"{P}/figures/fill_{o}.png")
] + [f"{P}/tables/objects.csv", f"{P}/tables/objects.md", f"{P}/figures/objects.png"]


rule main_table:
    conda:
        "../envs/knockgs.yaml"
    input:
        metrics=lambda wc: [f"{P}/metrics/{wc.object}/{SPLIT}/{m}.csv" for m in METHODS],
    output:
        csv=report(f"{P}/tables/main_{{object}}.csv", caption="../report/main_table.rst", category="Tables", subcategory="{object}"),
        md=f"{P}/tables/main_{{object}}.md",
        targetwise=report(f"{P}/tables/targetwise_{{object}}.csv", caption="../report/targetwise.rst", category="Tables", subcategory="{object}"),
        targetwise_md=f"{P}/tables/targetwise_{{object}}.md",
    log:
        f"logs/{PROFILE}/tables/main_{{object}}.log",
    params:
        methods=METHODS,
        probes=lambda wc: eval_probes(wc.object),
        profile=PROFILE,
    script:
        "../scripts/main_table.py"


rule main_figure:
    conda:
        "../envs/knockgs.yaml"
    input:
        csv=f"{P}/tables/main_{{object}}.csv",
    output:
        report(f"{P}/figures/main_{{object}}.png", caption="../report/main_figure.rst", category="Figures", subcategory="{object}"),
    log:
        f"logs/{PROFILE}/figures/main_{{object}}.log",
    params:
        probes=lambda wc: eval_probes(wc.object),
        profile=PROFILE,
    script:
        "../scripts/main_figure.py"


rule objects_table:
    conda:
        "../envs/knockgs.yaml"
    input:
        mains=expand(f"{P}/tables/main_{{object}}.csv", object=OBJECTS),
    output:
        csv=report(f"{P}/tables/objects.csv", caption="../report/objects.rst", category="Tables"),
        md=f"{P}/tables/objects.md",
        png=report(f"{P}/figures/objects.png", caption="../report/objects.rst", category="Figures"),
    log:
        f"logs/{PROFILE}/tables/objects.log",
    params:
        objects=OBJECTS,
        heldout={o: heldout_probes(o) for o in OBJECTS},
        calibration={o: calibration_probe(o) for o in OBJECTS},
        profile=PROFILE,
    script:
        "../scripts/objects_table.py"
