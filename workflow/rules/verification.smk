# Verification of the MPM against an independent finite-element reference (knockgs_core.fem;
# docs/verification.md): a block held by its bottom layer and knocked by a uniform impulse,
# simulated by the MPM at several resolutions (dx and dt refined together) and by the FEM on
# a converged mesh. One job, no inputs. `snakemake verification` makes the table; `all`
# includes it when config verification.enabled is true.

VERIFICATION = config["verification"]
VERIFICATION_OUTPUTS = [f"{P}/tables/verification_fem.csv", f"{P}/tables/verification_fem.md"]
VERIFICATION_IN_ALL = register_study("verification", VERIFICATION_OUTPUTS,
                                     VERIFICATION_OUTPUTS if VERIFICATION["enabled"] else [])


rule verification_fem:
    """The MPM's gap to the finite-element reference per resolution level: RMS-displacement
    curve, first-mode period, peak displacement and trajectory errors, their observed orders,
    the reference's own mesh change, CPU seconds."""
    conda:
        "../envs/knockgs.yaml"
    output:
        csv=report(f"{P}/tables/verification_fem.csv", caption="../report/verification.rst", category="Tables", subcategory="verification"),
        md=f"{P}/tables/verification_fem.md",
    log:
        f"logs/{PROFILE}/tables/verification_fem.log",
    benchmark:
        f"{P}/benchmarks/verification/verification_fem.tsv"
    params:
        profile=PROFILE,
        settings={k: v for k, v in VERIFICATION.items() if k != "enabled"},
        device=DEVICE,
        deterministic=DETERMINISTIC,
    resources:
        mem_mb=8000 if PROFILE == "paper" else 2000,
        runtime=60 if PROFILE == "paper" else 10,
        gpu=1 if ON_GPU else 0,
    threads: 1
    script:
        "../scripts/verification_fem.py"


rule verification:
    """Named target: the MPM-vs-FEM verification table."""
    input:
        VERIFICATION_OUTPUTS,
