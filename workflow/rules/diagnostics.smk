# The paper's generalization diagnostics per object (docs/diagnostics.md):
#   P/tables/splits_{object}.csv|md            one row per target split (main, alt_1..alt_3): local ridge
#                                              against the strongest other deployable method, strict gate,
#                                              Probe-B gates; P/figures/splits_{object}.png
#   P/tables/sensitivity_size_{object}.csv|md  local ridge (frozen k, alpha) on nested random library subsets
#   P/tables/sensitivity_k_alpha_{object}.csv|md  candidate leave-one-out and held-out error over k x alpha;
#                                              P/figures/sensitivity_{object}.png (three panels)
#   P/tables/identifiability_{object}.csv|md   descriptor vs parameter vs trajectory distances of every
#                                              candidate pair, local-ridge condition numbers;
#   P/tables/identifiability_pairs_{object}.csv  the pairs; P/figures/identifiability_{object}.png
# The sensitivity and identifiability studies read only the frozen descriptor tables (and the
# library's Probe-A rollouts): no new rollout. The splits run the main protocol on every split
# (rules estimate / rollout_eval / evaluate with the split wildcard). `snakemake diagnostics`
# makes them all; `all` includes them when config diagnostics.enabled is true, the splits only
# with diagnostics.splits_in_all too (`snakemake splits` makes them alone).

DIAGNOSTICS = config["diagnostics"]
DIAGNOSTIC_SPLITS = [SPLIT] + [s for s in DIAGNOSTICS["splits"] if s != SPLIT]
DIAGNOSTICS_OUTPUTS = [
    path
    for o in OBJECTS
    for path in (
        f"{P}/tables/splits_{o}.csv", f"{P}/tables/splits_{o}.md", f"{P}/figures/splits_{o}.png",
        f"{P}/tables/sensitivity_size_{o}.csv", f"{P}/tables/sensitivity_size_{o}.md",
        f"{P}/tables/sensitivity_k_alpha_{o}.csv", f"{P}/tables/sensitivity_k_alpha_{o}.md", f"{P}/figures/sensitivity_{o}.png",
        f"{P}/tables/identifiability_{o}.csv", f"{P}/tables/identifiability_{o}.md", f"{P}/tables/identifiability_pairs_{o}.csv",
        f"{P}/figures/identifiability_{o}.png",
    )
]
SPLITS_OUTPUTS = [path for path in DIAGNOSTICS_OUTPUTS if os.path.basename(path).startswith("splits_")]
# the splits re-run the main protocol three times (the default profile: about 60 more
# evaluation rollouts per object), hence their own switch
DIAGNOSTICS_IN_ALL = register_study("diagnostics", DIAGNOSTICS_OUTPUTS, [
    path for path in DIAGNOSTICS_OUTPUTS if DIAGNOSTICS["splits_in_all"] or path not in SPLITS_OUTPUTS
] if DIAGNOSTICS["enabled"] else [])


rule splits_table:
    """Local ridge against the strongest other deployable method on every target split."""
    conda:
        "../envs/knockgs.yaml"
    input:
        metrics=lambda wc: [f"{P}/metrics/{wc.object}/{s}/{m}.csv" for s in DIAGNOSTIC_SPLITS for m in METHODS],
    output:
        csv=report(f"{P}/tables/splits_{{object}}.csv", caption="../report/diagnostics.rst", category="Tables", subcategory="{object}"),
        md=f"{P}/tables/splits_{{object}}.md",
        png=report(f"{P}/figures/splits_{{object}}.png", caption="../report/diagnostics.rst", category="Figures", subcategory="{object}"),
    log:
        f"logs/{PROFILE}/tables/splits_{{object}}.log",
    params:
        splits=DIAGNOSTIC_SPLITS,
        methods=METHODS,
        heldout=lambda wc: heldout_probes(wc.object),
        profile=PROFILE,
    script:
        "../scripts/splits_table.py"


rule sensitivity_tables:
    """Library-size and (k, alpha) sensitivity of local ridge from the frozen descriptor tables."""
    conda:
        "../envs/knockgs.yaml"
    input:
        library=f"{P}/descriptors/{{object}}/library.csv",
        queries=f"{P}/descriptors/{{object}}/queries_{SPLIT}.csv",
        targets="config/targets.csv",
    output:
        size=report(f"{P}/tables/sensitivity_size_{{object}}.csv", caption="../report/diagnostics.rst", category="Tables",
                    subcategory="{object}"),
        size_md=f"{P}/tables/sensitivity_size_{{object}}.md",
        grid=f"{P}/tables/sensitivity_k_alpha_{{object}}.csv",
        grid_md=f"{P}/tables/sensitivity_k_alpha_{{object}}.md",
        png=report(f"{P}/figures/sensitivity_{{object}}.png", caption="../report/diagnostics.rst", category="Figures",
                   subcategory="{object}"),
    log:
        f"logs/{PROFILE}/tables/sensitivity_{{object}}.log",
    params:
        split=SPLIT,
        local=config["method_params"].get("local_ridge", {}),
        knn=config["method_params"].get("response_knn", {}),
        settings={k: v for k, v in DIAGNOSTICS.items() if k in ("sizes", "draws", "seed", "ks", "alphas")},
        profile=PROFILE,
    script:
        "../scripts/sensitivity.py"


rule identifiability_table:
    """Which candidates the descriptor cannot tell apart; local-ridge condition numbers."""
    conda:
        "../envs/knockgs.yaml"
    input:
        library=f"{P}/descriptors/{{object}}/library.csv",
        queries=f"{P}/descriptors/{{object}}/queries_{SPLIT}.csv",
        rollouts=lambda wc: folders(library_rollouts(wc.object).values()),
    output:
        csv=report(f"{P}/tables/identifiability_{{object}}.csv", caption="../report/diagnostics.rst", category="Tables",
                   subcategory="{object}"),
        md=f"{P}/tables/identifiability_{{object}}.md",
        pairs=f"{P}/tables/identifiability_pairs_{{object}}.csv",
        png=report(f"{P}/figures/identifiability_{{object}}.png", caption="../report/diagnostics.rst", category="Figures",
                   subcategory="{object}"),
    log:
        f"logs/{PROFILE}/tables/identifiability_{{object}}.log",
    params:
        rollouts=lambda wc: library_rollouts(wc.object),
        local=config["method_params"].get("local_ridge", {}),
        profile=PROFILE,
    resources:
        mem_mb=16000 if PROFILE == "paper" else 2000,
    script:
        "../scripts/identifiability.py"


rule diagnostics:
    """Named target: every object's splits, sensitivity and identifiability tables and figures."""
    input:
        DIAGNOSTICS_OUTPUTS,


rule splits:
    """Named target: every object's splits table and figure."""
    input:
        SPLITS_OUTPUTS,
