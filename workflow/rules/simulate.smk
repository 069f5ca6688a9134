# MPM rollouts, cached as Parquet: one file per (object, theta, probe).
#
# A job simulates several rollouts in one process: a chunk of LIBRARY_CHUNK candidates
# (library), or one theta under the evaluation probes of its object (evaluation). Process
# start-up (Python, Warp, the contract) costs ~2 s a job on a laptop CPU, as much as a whole
# Pillow rollout; amortizing it keeps the default `all` within its time budget. Every
# rollout still has its own Parquet file, and a finished job is never re-run. A candidate's
# library rollout doubles as its Probe-A evaluation rollout (common.smk: eval_rollout).

import re

LIBRARY_CHUNK = 6


def library_chunks():
    """Candidate names in groups of LIBRARY_CHUNK, in candidates.csv order."""
    names = list(CANDIDATES.case_name)
    return [names[i : i + LIBRARY_CHUNK] for i in range(0, len(names), LIBRARY_CHUNK)]


for _k, _chunk in enumerate(library_chunks()):

    rule:
        """Probe-A rollouts of a chunk of candidates (library members), with the deformation
        gradients: a candidate's library rollout is also its Probe-A evaluation rollout."""
        name:
            f"rollout_library_{_k}"
        conda:
            "../envs/knockgs.yaml"
        input:
            particles=f"{P}/assets/{{object}}.particles.npz",
        output:
            rollouts=[f"{P}/rollouts/{{object}}/lib/{theta_tag(candidate_theta(c))}.parquet" for c in _chunk],
            F=[f"{P}/rollouts/{{object}}/lib/{theta_tag(candidate_theta(c))}.F.parquet" for c in _chunk],
        log:
            f"logs/{PROFILE}/rollouts/{{object}}/lib/chunk{_k}.log",
        benchmark:
            f"results/{PROFILE}/benchmarks/rollouts/{{object}}/lib/chunk{_k}.tsv"
        params:
            profile=PROFILE,
            object=lambda wc: wc.object,
            runs=lambda wc, chunk=_chunk: [(candidate_theta(c), calibration_probe(wc.object)) for c in chunk],
            export_F=True,
            device=DEVICE,
        resources:
            mem_mb=_rollout_resources,
            runtime=60 * LIBRARY_CHUNK if PROFILE == "paper" else 20 * LIBRARY_CHUNK,
            gpu=1 if ON_GPU else 0,
        threads: 1
        script:
            "../scripts/rollout.py"


def _theta_regex(candidates: bool) -> str:
    """Theta tags of the candidates, or every other theta tag."""
    alt = "|".join(re.escape(t) for t in sorted(CANDIDATE_TAGS))
    # the wildcard is matched inside the whole path: "(?![0-9])" ends a tag, not "$"
    return f"(?:{alt})(?![0-9])" if candidates else f"(?!(?:{alt})(?![0-9]))sE[0-9.]+_sR[0-9.]+"


for _obj in OBJECTS:
    for _cand in (False, True):
        # a candidate theta needs only the held-out probes: its Probe-A rollout is the library's
        _probes = heldout_probes(_obj) if _cand else eval_probes(_obj)

        rule:
            """Evaluation rollouts of one theta (a target or a frozen estimate) under the
            object's evaluation probes, with the deformation gradients of the
            Gaussian-associated particles for rendering."""
            name:
                f"rollout_eval_{_obj}" + ("_candidate" if _cand else "")
            conda:
                "../envs/knockgs.yaml"
            wildcard_constraints:
                theta=_theta_regex(_cand),
            input:
                particles=f"{P}/assets/{_obj}.particles.npz",
            output:
                rollouts=[f"{P}/rollouts/{_obj}/eval/{pr}/{{theta}}.parquet" for pr in _probes],
                F=[f"{P}/rollouts/{_obj}/eval/{pr}/{{theta}}.F.parquet" for pr in _probes],
            log:
                f"logs/{PROFILE}/rollouts/{_obj}/eval/{{theta}}.log",
            benchmark:
                f"results/{PROFILE}/benchmarks/rollouts/{_obj}/eval/{{theta}}.tsv"
            params:
                profile=PROFILE,
                object=_obj,
                runs=lambda wc, probes=_probes: [(parse_theta(wc.theta), pr) for pr in probes],
                export_F=True,
                device=DEVICE,
            resources:
                mem_mb=_rollout_resources,
                runtime=60 * len(_probes) if PROFILE == "paper" else 20 * len(_probes),
                gpu=1 if ON_GPU else 0,
            threads: 1
            script:
                "../scripts/rollout.py"
