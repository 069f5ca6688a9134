# Discrepancy loop (SPEC §9): synthetic "measured" cases with a planted effect, one job per
# case and step, so runs parallelize and resume.
#
# Path grammar (P = results/{profile}, D = P/discrepancy):
#   D/cases/{case}/measured_{calib,heldout}.parquet   measured trajectories (positions only)
#   D/truth/{case}/truth.json, clean.npz              the truth: read by make-case and evaluate only
#   results/discrepancy/{case}/report.md              the loop's report (+ result.json,
#                                                     predictions.npz, residuals_*.png)
#   results/discrepancy/{case}/evaluation.md          the run against the truth (evaluate step)
#   D/eval/{case}.json                                one table row (run scored against the truth)
#   results/tables/discrepancy.csv|md                 the table of cases
#   results/figures/discrepancy.png                   RMSE before/after per case
#   results/audits/discrepancy_truth.json             verdict: no run read the truth

from knockgs_core.discrepancy import default_cases as _discrepancy_default_cases

DISCREPANCY_OBJECT = DISCREPANCY["object"]
DISCREPANCY_RES = DISCREPANCY["resolution"]  # contract resolution of the cases (config: discrepancy)
DISCREPANCY_CASES = [c.name for c in _discrepancy_default_cases()]
_D = f"{P}/discrepancy"
_DISCREPANCY_CONTRACT = load_contract(DISCREPANCY_OBJECT, DISCREPANCY_RES)


wildcard_constraints:
    case="[A-Za-z0-9_]+",
    res="ci|default|paper",


DISCREPANCY_OUTPUTS = [] if not DISCREPANCY["enabled"] else [
    "results/tables/discrepancy.csv",
    "results/tables/discrepancy.md",
    "results/figures/discrepancy.png",
    "results/audits/discrepancy_truth.json",
] + [f"results/discrepancy/{c}/report.md" for c in DISCREPANCY_CASES]


rule discrepancy_asset:
    """The case object built at the cases' resolution, when it differs from the profile's."""
    conda:
        "../envs/knockgs.yaml"
    output:
        ply=f"{_D}/{{res}}/assets/{{object}}.ply",
        particles=f"{_D}/{{res}}/assets/{{object}}.particles.npz",
        scene=f"{_D}/{{res}}/assets/{{object}}.scene.npz",
        summary=f"{_D}/{{res}}/assets/{{object}}.summary.json",
        figure=f"{_D}/{{res}}/assets/{{object}}.fill.png",
    log:
        f"logs/{PROFILE}/discrepancy/{{res}}/asset_{{object}}.log",
    params:
        profile=lambda wc: wc.res,
    resources:
        mem_mb=2000,
        runtime=30,
    threads: 1
    script:
        "../scripts/asset.py"


for _k, _chunk in enumerate(library_chunks()):

    rule:
        """Probe-A rollouts of a chunk of candidates at the cases' resolution (the loop's
        library base); chunked as the main library (simulate.smk)."""
        name:
            f"discrepancy_library_{_k}"
        conda:
            "../envs/knockgs.yaml"
        input:
            particles=f"{_D}/{{res}}/assets/{{object}}.particles.npz",
        output:
            rollouts=[f"{_D}/{{res}}/library/{{object}}/{theta_tag(candidate_theta(c))}.parquet" for c in _chunk],
        log:
            f"logs/{PROFILE}/discrepancy/{{res}}/library/{{object}}/chunk{_k}.log",
        benchmark:
            f"results/{PROFILE}/benchmarks/discrepancy/{{res}}/library/{{object}}/chunk{_k}.tsv"
        params:
            profile=lambda wc: wc.res,
            object=lambda wc: wc.object,
            runs=lambda wc, chunk=_chunk: _discrepancy_library_runs(wc, chunk),
            export_F=False,
            device=DEVICE,
        resources:
            mem_mb=2000,
            runtime=20 * LIBRARY_CHUNK,
            gpu=1 if ON_GPU else 0,
        threads: 1
        script:
            "../scripts/rollout.py"


rule discrepancy_case:
    """Truth side: plant the case's effect at its magnitude, write measured files and truth apart."""
    conda:
        "../envs/knockgs.yaml"
    input:
        particles=_discrepancy_particles(),
    output:
        calib=f"{_D}/cases/{{case}}/measured_calib.parquet",
        heldout=f"{_D}/cases/{{case}}/measured_heldout.parquet",
        truth=f"{_D}/truth/{{case}}/truth.json",
        clean=f"{_D}/truth/{{case}}/clean.npz",
    log:
        f"logs/{PROFILE}/discrepancy/case_{{case}}.log",
    params:
        object=DISCREPANCY_OBJECT,
        profile=DISCREPANCY_RES,
        device=DEVICE,
    threads: 1
    script:
        "../scripts/discrepancy_case.py"


rule discrepancy_run:
    """The loop on one case's measured files (never its truth); the held-out measurement only
    scores the predictions in the report."""
    conda:
        "../envs/knockgs.yaml"
    input:
        unpack(lambda wc: _discrepancy_run_inputs(wc.case)),
    output:
        report=report(f"results/discrepancy/{{case}}/report.md", category="Discrepancy", subcategory="{case}"),
        result=f"results/discrepancy/{{case}}/result.json",
        predictions=f"results/discrepancy/{{case}}/predictions.npz",
    log:
        f"logs/{PROFILE}/discrepancy/run_{{case}}.log",
    benchmark:
        f"results/{PROFILE}/benchmarks/discrepancy/run_{{case}}.tsv"
    params:
        object=DISCREPANCY_OBJECT,
        profile=DISCREPANCY_RES,
        device=DEVICE,
        probe=_DISCREPANCY_CONTRACT.roles["calibration"],
        heldout_probe=_DISCREPANCY_CONTRACT.roles["heldout"][0],
    threads: 1
    script:
        "../scripts/discrepancy_run.py"


rule discrepancy_evaluate:
    conda:
        "../envs/knockgs.yaml"
    input:
        result=f"results/discrepancy/{{case}}/result.json",
        predictions=f"results/discrepancy/{{case}}/predictions.npz",
        truth=f"{_D}/truth/{{case}}/truth.json",
        clean=f"{_D}/truth/{{case}}/clean.npz",
    output:
        row=f"{_D}/eval/{{case}}.json",
        page=report(f"results/discrepancy/{{case}}/evaluation.md", category="Discrepancy", subcategory="{case}"),
    log:
        f"logs/{PROFILE}/discrepancy/evaluate_{{case}}.log",
    script:
        "../scripts/discrepancy_evaluate.py"


rule discrepancy_table:
    conda:
        "../envs/knockgs.yaml"
    input:
        rows=[f"{_D}/eval/{c}.json" for c in DISCREPANCY_CASES],
    output:
        csv=report("results/tables/discrepancy.csv", category="Discrepancy"),
        md="results/tables/discrepancy.md",
        figure=report("results/figures/discrepancy.png", category="Discrepancy"),
    log:
        f"logs/{PROFILE}/discrepancy/table.log",
    script:
        "../scripts/discrepancy_table.py"


rule audit_discrepancy_truth:
    conda:
        "../envs/knockgs.yaml"
    input:
        results=[f"results/discrepancy/{c}/result.json" for c in DISCREPANCY_CASES],
        measured=[f"{_D}/cases/{c}/measured_{r}.parquet" for c in DISCREPANCY_CASES for r in ("calib", "heldout")],
    output:
        "results/audits/discrepancy_truth.json",
    log:
        f"logs/{PROFILE}/audits/discrepancy_truth.log",
    params:
        truth_dirs=[f"{_D}/truth"],
        declared={c: [v for vs in _discrepancy_run_inputs(c).values() for v in ([vs] if isinstance(vs, str) else vs)] for c in DISCREPANCY_CASES},
    script:
        "../scripts/discrepancy_audit.py"
