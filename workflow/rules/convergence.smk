# The discretization study of the Probe-A response (knockgs_core.experiments convergence_study):
# per object, dt -> dt/2 -> dt/4 at the profile's grid; n_grid -> 1.5x -> 2x with the same
# particles (the "grid resolution changed" condition: particles per cell thin out); and, for
# objects with an interior fill, n_grid+fill: grid and fill resolution refined together, the
# Gaussian-associated particles fixed and the fill rebuilt per grid (the spatial discretization
# error). One job per object runs its rollouts (six, eight with a fill: the space rows share
# level 1). `snakemake convergence` makes every object's table and figure; `all` includes them
# when config convergence.enabled is true.

CONVERGENCE = config["convergence"]
CONVERGENCE_OUTPUTS = [
    path
    for o in OBJECTS
    for path in (f"{P}/tables/convergence_{o}.csv", f"{P}/tables/convergence_{o}.md", f"{P}/figures/convergence_{o}.png")
]
CONVERGENCE_IN_ALL = register_study("convergence", CONVERGENCE_OUTPUTS,
                                    CONVERGENCE_OUTPUTS if CONVERGENCE["enabled"] else [])


rule convergence_study:
    """Time and space convergence of one object's Probe-A response at one fixed theta (rows dt,
    n_grid with the particles fixed, n_grid+fill with the fill rebuilt per grid): the change
    between successive levels, the observed order and the Richardson-extrapolated error of the
    profile's setting."""
    conda:
        "../envs/knockgs.yaml"
    input:
        particles=f"{P}/assets/{{object}}.particles.npz",
    output:
        csv=report(f"{P}/tables/convergence_{{object}}.csv", caption="../report/convergence.rst", category="Tables", subcategory="{object}"),
        md=f"{P}/tables/convergence_{{object}}.md",
        png=report(f"{P}/figures/convergence_{{object}}.png", caption="../report/convergence.rst", category="Figures", subcategory="{object}"),
    log:
        f"logs/{PROFILE}/tables/convergence_{{object}}.log",
    benchmark:
        f"{P}/benchmarks/convergence/{{object}}.tsv"
    params:
        profile=PROFILE,
        object=lambda wc: wc.object,
        theta=CONVERGENCE["theta"],
        n_frames=None if CONVERGENCE["n_frames"] == "all" else CONVERGENCE["n_frames"],
        device=DEVICE,
        deterministic=DETERMINISTIC,
    resources:
        mem_mb=16000 if PROFILE == "paper" else 2000,
        runtime=120 if PROFILE == "paper" else 30,
        gpu=1 if ON_GPU else 0,
    threads: 1
    script:
        "../scripts/convergence.py"


rule convergence:
    """Named target: every object's convergence table and figure."""
    input:
        CONVERGENCE_OUTPUTS,
