# Where the model-error floor lives (docs/floor.md): each object's MPM at several resolutions
# against the finite-element reference of the same object, supports and impulse, on a mesh of
# its own (knockgs_core.experiments._floor). One job per object, no inputs:
#   P/tables/floor_{object}.csv|md     trajectory RMSE, first-mode periods, the fitted theta per level
#   P/figures/floor_{object}.png       RMSE and period error against dx, log-log
# Objects: config floor.objects (one material region each: the FEM reference has no second
# region, so not the Ficus). `snakemake floor` makes them; `all` includes them when
# floor.enabled is true.

FLOOR = config["floor"]
for _obj in FLOOR["objects"]:  # an unknown object, or one the FEM reference cannot hold: refused at config read
    try:
        _regions = contract(_obj).region_names
    except InputError as exc:
        config_refusal(f"config floor.objects: {exc}")
    if _regions != ("base",):
        config_refusal(f"config floor.objects: '{_obj}' has material regions {list(_regions)}; "
                       "the floor study's FEM reference supports one (base)")
FLOOR_OUTPUTS = [f"{P}/{kind}/floor_{o}.{ext}" for o in FLOOR["objects"]
                 for kind, ext in (("tables", "csv"), ("tables", "md"), ("figures", "png"))]
FLOOR_IN_ALL = register_study("floor", FLOOR_OUTPUTS, FLOOR_OUTPUTS if FLOOR["enabled"] else [])


rule floor_table:
    """One object's MPM levels against the finite-element reference: trajectory RMSE, periods,
    observed orders, the theta the MPM needs to match the reference, cost."""
    conda:
        "../envs/knockgs.yaml"
    output:
        csv=report(f"{P}/tables/floor_{{object}}.csv", caption="../report/floor.rst", category="Tables",
                   subcategory="{object}"),
        md=f"{P}/tables/floor_{{object}}.md",
        png=report(f"{P}/figures/floor_{{object}}.png", caption="../report/floor.rst", category="Figures",
                   subcategory="{object}"),
    log:
        f"logs/{PROFILE}/tables/floor_{{object}}.log",
    benchmark:
        f"{P}/benchmarks/floor/floor_{{object}}.tsv"
    params:
        profile=PROFILE,
        settings={k: v for k, v in FLOOR.items() if k not in ("enabled", "objects")},
        device=DEVICE,
        deterministic=DETERMINISTIC,
    resources:
        mem_mb=16000 if PROFILE == "paper" else 4000,
        runtime=120 if PROFILE == "paper" else 20,
        gpu=1 if ON_GPU else 0,
    threads: 1
    script:
        "../scripts/floor_table.py"


rule floor:
    """Named target: the floor tables and figures of floor.objects."""
    input:
        FLOOR_OUTPUTS,
