# The discretization study of the Probe-A response: per object, dt -> dt/2 -> dt/4 at the
# profile's grid and n_grid -> 1.5x -> 2x with the same particles (knockgs_core.experiments
# convergence_study). One job per object runs its six rollouts (levels shared between the two
# refinements are simulated once). `snakemake convergence` makes every object's table and figure;
# `all` includes them when config convergence.enabled is true.

CONVERGENCE = config["convergence"]
CONVERGENCE_OUTPUTS = [
    path
    for o in OBJECTS
    for path in (f"{P}/tables/convergence_{o}.csv", f"{P}/tables/convergence_{o}.md", f"{P}/figures/convergence_{o}.png")
]
CONVERGENCE_IN_ALL = CONVERGENCE_OUTPUTS if CONVERGENCE["enabled"] else []


rule convergence_study:
    """Time and space convergence of one object's Probe-A response at one fixed theta: the
    change between successive levels, the observed order and the Richardson-extrapolated error
    of the profile's setting."""
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
