# Discrepancy loop (SPEC §9): synthetic "measured" cases with a planted effect, one job per
# case and step, so runs parallelize and resume.
#
# Path grammar (P = results/{profile}, D = P/discrepancy):
#   D/cases/{case}/measured_{calib,heldout}.parquet        measured trajectories (positions only)
#   D/truth/{case}/truth.json, clean.npz                   the truth: read by make-case and evaluate only
#   D/reports/{case}/report.md                             the loop's report (+ result.json,
#                                                          predictions.npz, residuals_*.png)
#   D/reports/{case}/evaluation.md                         the run against the truth (evaluate step)
#   D/eval/{case}.json                                     one table row (run scored against the truth)
#   D/{res}/assets/{object}.*                              the case object at the cases' resolution
#   D/{res}/library/{object}/chunk{chunk}/{theta}.parquet  its candidate library (Probe A), chunked as
#                                                          the main library (simulate.smk)
#   P/tables/discrepancy.csv|md, P/figures/discrepancy.png the table of cases, RMSE before/after per case
#   P/audits/discrepancy_truth.json                        verdict: no run read the truth
#   P/tables/discrepancy_worlds.csv|md, P/figures/discrepancy_worlds.png,
#   P/audits/discrepancy_worlds_truth.json                 the world cases (finer grid, FEM): target
#                                                          `discrepancy_worlds`, not in `all`
#   D/{res}/floor_{object}.csv|md|png                      the loop's grid against the finite-element
#                                                          reference of the profile's `floor` block: the
#                                                          world cases' runs judge their grid by it
#
# The world cases stand for measured data: with discrepancy.floor (default) their runs read the
# floor table of the loop's own body, as `knockgs discrepancy run --floor-table` does, and where
# that grid's floor is above half discrepancy.smallest_effect they say that effects below about
# twice it cannot be named there; their theta intervals carry the grid's calibration bias. The
# standard cases are data the loop's own model made, and run without it.
#
# The cases run at config discrepancy.resolution, on discrepancy.n_grid cells per axis where it
# is set (the fill refined with it: knockgs_core.contract.at_resolution). At the profile's own
# resolution they share its asset (P/assets) and candidate library (P/rollouts/{object}/lib); at
# another, the D/{res}/ asset and library are built for them ({res}: the resolution, or
# {resolution}_n{n_grid}).

from knockgs_core.discrepancy import default_cases, world_cases

D = f"{P}/discrepancy"
DISCREPANCY_OBJECT = DISCREPANCY["object"]
DISCREPANCY_PROFILE = DISCREPANCY["resolution"]
DISCREPANCY_N_GRID = DISCREPANCY.get("n_grid")
DISCREPANCY_RES = DISCREPANCY_PROFILE if DISCREPANCY_N_GRID is None else f"{DISCREPANCY_PROFILE}_n{DISCREPANCY_N_GRID}"
DISCREPANCY_CASES = [c.name for c in default_cases()]
_WORLD_CASES = [c.name for c in world_cases()]
_unknown_worlds = sorted(set(DISCREPANCY.get("worlds") or []) - set(_WORLD_CASES))
if _unknown_worlds:
    raise ValueError(f"config discrepancy.worlds: unknown world cases {_unknown_worlds}; known: {_WORLD_CASES}")
# the world cases (data the loop's model cannot match exactly), in world_cases() order
DISCREPANCY_WORLD_CASES = [c for c in _WORLD_CASES if c in (DISCREPANCY.get("worlds") or _WORLD_CASES)]
try:
    _DISCREPANCY_CONTRACT = contract(DISCREPANCY_OBJECT, DISCREPANCY_PROFILE, n_grid=DISCREPANCY_N_GRID)
except InputError as exc:  # an object the grid cannot hold: one line at config read
    config_refusal(f"{_config_file_of('discrepancy')}: discrepancy: {exc}")
_DISCREPANCY_SHARED = DISCREPANCY_RES == PROFILE
DISCREPANCY_PARTICLES = (f"{P}/assets/{DISCREPANCY_OBJECT}.particles.npz" if _DISCREPANCY_SHARED
                         else f"{D}/{DISCREPANCY_RES}/assets/{DISCREPANCY_OBJECT}.particles.npz")
DISCREPANCY_LIBRARY_ROOT = (library_root(DISCREPANCY_OBJECT) if _DISCREPANCY_SHARED
                            else f"{D}/{DISCREPANCY_RES}/library/{DISCREPANCY_OBJECT}")
# the loop's library base, in candidates.csv order
DISCREPANCY_LIBRARY = [library_rollout(DISCREPANCY_LIBRARY_ROOT, case) for case in CANDIDATES.case_name]
# the floor table the world cases' runs read (none with discrepancy.floor false)
DISCREPANCY_FLOOR = [f"{D}/{DISCREPANCY_RES}/floor_{DISCREPANCY_OBJECT}.csv"] if DISCREPANCY.get("floor", True) else []
# the files each run job reads (and the truth audit checks)
DISCREPANCY_RUN_READS = {
    case: [f"{D}/cases/{case}/measured_calib.parquet", f"{D}/cases/{case}/measured_heldout.parquet", DISCREPANCY_PARTICLES,
           *DISCREPANCY_LIBRARY, *(DISCREPANCY_FLOOR if case in DISCREPANCY_WORLD_CASES else [])]
    for case in DISCREPANCY_CASES + DISCREPANCY_WORLD_CASES
}

DISCREPANCY_STUDY_OUTPUTS = (
    [f"{P}/tables/discrepancy.csv", f"{P}/tables/discrepancy.md", f"{P}/figures/discrepancy.png", f"{P}/audits/discrepancy_truth.json"]
    + [f"{D}/reports/{case}/report.md" for case in DISCREPANCY_CASES]
)
DISCREPANCY_OUTPUTS = register_study("discrepancy", DISCREPANCY_STUDY_OUTPUTS,
                                     DISCREPANCY_STUDY_OUTPUTS if DISCREPANCY["enabled"] else [])
DISCREPANCY_WORLDS_OUTPUTS = [f"{P}/tables/discrepancy_worlds.csv", f"{P}/tables/discrepancy_worlds.md",
                              f"{P}/figures/discrepancy_worlds.png", f"{P}/audits/discrepancy_worlds_truth.json"]
register_study("discrepancy_worlds", DISCREPANCY_WORLDS_OUTPUTS, [])


rule discrepancy_asset:
    """The case object built at the cases' resolution, when it differs from the profile's."""
    conda:
        "../envs/knockgs.yaml"
    output:
        ply=f"{D}/{{res}}/assets/{{object}}.ply",
        particles=f"{D}/{{res}}/assets/{{object}}.particles.npz",
        scene=f"{D}/{{res}}/assets/{{object}}.scene.npz",
        summary=f"{D}/{{res}}/assets/{{object}}.summary.json",
        figure=f"{D}/{{res}}/assets/{{object}}.fill.png",
    log:
        f"logs/{PROFILE}/discrepancy/{{res}}/asset_{{object}}.log",
    wildcard_constraints:
        res=re.escape(DISCREPANCY_RES),  # the one resolution its params build
    params:
        profile=DISCREPANCY_PROFILE,
        n_grid=DISCREPANCY_N_GRID,
    resources:
        mem_mb=2000,
        runtime=30,
    threads: 1
    script:
        "../scripts/asset.py"


rule discrepancy_library:
    """Probe-A rollouts of one chunk of candidates at the cases' resolution (the loop's
    library base); chunked as the main library (simulate.smk)."""
    conda:
        "../envs/knockgs.yaml"
    input:
        particles=f"{D}/{{res}}/assets/{{object}}.particles.npz",
    output:
        folder=directory(f"{D}/{{res}}/library/{{object}}/chunk{{chunk}}"),
    log:
        f"logs/{PROFILE}/discrepancy/{{res}}/library/{{object}}/chunk{{chunk}}.log",
    benchmark:
        f"{P}/benchmarks/discrepancy/{{res}}/library/{{object}}/chunk{{chunk}}.tsv"
    wildcard_constraints:
        res=re.escape(DISCREPANCY_RES),
    params:
        profile=DISCREPANCY_PROFILE,
        n_grid=DISCREPANCY_N_GRID,
        object=lambda wc: wc.object,
        runs=lambda wc: library_runs(wc.chunk, _DISCREPANCY_CONTRACT.roles["calibration"], f"{D}/{wc.res}/library/{wc.object}",
                                     export_F=False),
        device=DEVICE,
        deterministic=DETERMINISTIC,
    resources:
        mem_mb=2000,
        runtime=20 * LIBRARY_CHUNK,
        gpu=1 if ON_GPU else 0,
    threads: 1
    script:
        "../scripts/rollout.py"


rule discrepancy_floor:
    """The loop's own body at its grid against the finite-element reference of the profile's
    `floor` block (the floor study, knockgs_core.experiments.floor_study, with one MPM level):
    the table the world cases' runs judge their grid by."""
    conda:
        "../envs/knockgs.yaml"
    output:
        csv=f"{D}/{{res}}/floor_{{object}}.csv",
        md=f"{D}/{{res}}/floor_{{object}}.md",
        png=f"{D}/{{res}}/floor_{{object}}.png",
    log:
        f"logs/{PROFILE}/discrepancy/{{res}}/floor_{{object}}.log",
    benchmark:
        f"{P}/benchmarks/discrepancy/{{res}}/floor_{{object}}.tsv"
    wildcard_constraints:
        res=re.escape(DISCREPANCY_RES),
        object=re.escape(DISCREPANCY_OBJECT),
    params:
        profile=DISCREPANCY_PROFILE,
        n_grid=DISCREPANCY_N_GRID,
        settings={**{k: v for k, v in config["floor"].items() if k not in ("enabled", "objects")},
                  "n_grid": [_DISCREPANCY_CONTRACT.sim.n_grid]},
        device=DEVICE,
        deterministic=DETERMINISTIC,
    resources:
        mem_mb=16000 if PROFILE == "paper" else 4000,
        runtime=120 if PROFILE == "paper" else 20,
        gpu=1 if ON_GPU else 0,
    threads: 1
    script:
        "../scripts/floor_table.py"


rule discrepancy_case:
    """Truth side: plant the case's effect at its magnitude, write measured files and truth apart."""
    conda:
        "../envs/knockgs.yaml"
    input:
        particles=DISCREPANCY_PARTICLES,
        targets="config/targets.csv",
    output:
        calib=f"{D}/cases/{{case}}/measured_calib.parquet",
        heldout=f"{D}/cases/{{case}}/measured_heldout.parquet",
        truth=f"{D}/truth/{{case}}/truth.json",
        clean=f"{D}/truth/{{case}}/clean.npz",
    log:
        f"logs/{PROFILE}/discrepancy/case_{{case}}.log",
    params:
        object=DISCREPANCY_OBJECT,
        profile=DISCREPANCY_PROFILE,
        n_grid=DISCREPANCY_N_GRID,
        device=DEVICE,
        deterministic=DETERMINISTIC,
    resources:
        gpu=1 if ON_GPU else 0,
    threads: 1
    script:
        "../scripts/discrepancy_case.py"


rule discrepancy_run:
    """The loop on one case's measured files (never its truth); the held-out measurement only
    scores the predictions in the report."""
    conda:
        "../envs/knockgs.yaml"
    input:
        measured=f"{D}/cases/{{case}}/measured_calib.parquet",
        heldout=f"{D}/cases/{{case}}/measured_heldout.parquet",
        particles=DISCREPANCY_PARTICLES,
        library=folders(DISCREPANCY_LIBRARY),
        floor=lambda wc: DISCREPANCY_FLOOR if wc.case in DISCREPANCY_WORLD_CASES else [],
    output:
        report=report(f"{D}/reports/{{case}}/report.md", category="Discrepancy", subcategory="{case}"),
        result=f"{D}/reports/{{case}}/result.json",
        predictions=f"{D}/reports/{{case}}/predictions.npz",
    log:
        f"logs/{PROFILE}/discrepancy/run_{{case}}.log",
    benchmark:
        f"{P}/benchmarks/discrepancy/run_{{case}}.tsv"
    params:
        object=DISCREPANCY_OBJECT,
        profile=DISCREPANCY_PROFILE,
        n_grid=DISCREPANCY_N_GRID,
        device=DEVICE,
        deterministic=DETERMINISTIC,
        probe=_DISCREPANCY_CONTRACT.roles["calibration"],
        heldout_probe=_DISCREPANCY_CONTRACT.roles["heldout"][0],
        library=DISCREPANCY_LIBRARY,
        loop_n_grid=_DISCREPANCY_CONTRACT.sim.n_grid,  # the grid the floor table judges
        smallest_effect=float(DISCREPANCY.get("smallest_effect", 0.2)),
    resources:
        gpu=1 if ON_GPU else 0,
    threads: 1
    script:
        "../scripts/discrepancy_run.py"


rule discrepancy_evaluate:
    conda:
        "../envs/knockgs.yaml"
    input:
        result=f"{D}/reports/{{case}}/result.json",
        predictions=f"{D}/reports/{{case}}/predictions.npz",
        truth=f"{D}/truth/{{case}}/truth.json",
        clean=f"{D}/truth/{{case}}/clean.npz",
    output:
        row=f"{D}/eval/{{case}}.json",
        page=report(f"{D}/reports/{{case}}/evaluation.md", category="Discrepancy", subcategory="{case}"),
    log:
        f"logs/{PROFILE}/discrepancy/evaluate_{{case}}.log",
    script:
        "../scripts/discrepancy_evaluate.py"


rule discrepancy_table:
    conda:
        "../envs/knockgs.yaml"
    input:
        rows=[f"{D}/eval/{case}.json" for case in DISCREPANCY_CASES],
    output:
        csv=report(f"{P}/tables/discrepancy.csv", category="Discrepancy"),
        md=f"{P}/tables/discrepancy.md",
        figure=report(f"{P}/figures/discrepancy.png", category="Discrepancy"),
    log:
        f"logs/{PROFILE}/discrepancy/table.log",
    script:
        "../scripts/discrepancy_table.py"


rule audit_discrepancy_truth:
    conda:
        "../envs/knockgs.yaml"
    input:
        results=[f"{D}/reports/{case}/result.json" for case in DISCREPANCY_CASES],
        measured=[f"{D}/cases/{case}/measured_{role}.parquet" for case in DISCREPANCY_CASES for role in ("calib", "heldout")],
    output:
        f"{P}/audits/discrepancy_truth.json",
    log:
        f"logs/{PROFILE}/audits/discrepancy_truth.log",
    params:
        truth_dirs=[f"{D}/truth"],
        declared=DISCREPANCY_RUN_READS,
    script:
        "../scripts/discrepancy_audit.py"


rule discrepancy_worlds_table:
    """The world cases (data from a finer MPM grid and from the FEM reference), scored by the
    world rule (knockgs_core.discrepancy.world_acceptance)."""
    conda:
        "../envs/knockgs.yaml"
    input:
        rows=[f"{D}/eval/{case}.json" for case in DISCREPANCY_WORLD_CASES],
    output:
        csv=report(f"{P}/tables/discrepancy_worlds.csv", category="Discrepancy"),
        md=f"{P}/tables/discrepancy_worlds.md",
        figure=report(f"{P}/figures/discrepancy_worlds.png", category="Discrepancy"),
    log:
        f"logs/{PROFILE}/discrepancy/table_worlds.log",
    params:
        title="Discrepancy loop in worlds its model cannot match (finer grid, FEM reference)",
    script:
        "../scripts/discrepancy_table.py"


rule audit_discrepancy_worlds_truth:
    conda:
        "../envs/knockgs.yaml"
    input:
        results=[f"{D}/reports/{case}/result.json" for case in DISCREPANCY_WORLD_CASES],
        measured=[f"{D}/cases/{case}/measured_{role}.parquet" for case in DISCREPANCY_WORLD_CASES for role in ("calib", "heldout")],
    output:
        f"{P}/audits/discrepancy_worlds_truth.json",
    log:
        f"logs/{PROFILE}/audits/discrepancy_worlds_truth.log",
    params:
        truth_dirs=[f"{D}/truth"],
        declared=DISCREPANCY_RUN_READS,
    script:
        "../scripts/discrepancy_audit.py"


rule discrepancy_worlds:
    """Named target: the discrepancy loop on the world cases, their table and truth audit."""
    input:
        DISCREPANCY_WORLDS_OUTPUTS,


rule discrepancy:
    """Named target: the discrepancy loop's cases, their reports, table and truth audit."""
    input:
        DISCREPANCY_STUDY_OUTPUTS,
