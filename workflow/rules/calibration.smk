# One's own object calibrated from a measured Probe-A observation (config `calibration`;
# docs/own_splat.md). The object need not be one of `objects:` and its contract need not lie in
# config/objects/: everything it makes lies under C = P/calibration/{object}:
#   C/asset.ply, .particles.npz, .scene.npz, .summary.json, .fill.png   the object's asset
#   C/library/chunk{chunk}/{theta}.parquet (+ .F.parquet)   the candidates' Probe-A rollouts (one folder a job)
#   C/library/observed/chunk{chunk}.csv          each rendered with the measurement's camera, tracked with its
#                                                tracker, described (+ the tracked RMS-displacement curve)
#   C/library.csv                                the library: labels + the observed descriptors
#   C/measurement.csv, C/measurement.json        the measurement's descriptor (the query; no label) and its
#                                                observation (tracks, curve, camera)
#   C/estimate.json                              the local ridge's frozen estimate (checkpoint): theta, the
#                                                jackknife standard errors, condition number, neighbours
#   C/predictions/{prediction}/{probe}.parquet (+ .F.parquet)   before (base material, theta (1, 1)) and
#                                                after (the frozen estimate), under Probe A and every held-out probe
#   C/predictions/observed.csv                   the Probe-A predictions observed as the measurement
#   C/frames/{prediction}/{probe}.npz            their rendered frames (contract camera)
#   C/calibration.csv|md, C/report.md, C/report.png   the table and the one-page report
# Not in `all` (it is the user's): `snakemake --cores 2 calibration --config 'calibration={...}'`.

from knockgs_core.experiments import BASE_THETA

include: "inputs/calibration.smk"


CAL = config["calibration"]
CAL_SOURCE, CAL_CONTRACT = calibration_config(CAL)
CAL_OBJECT = CAL["object"]
C = f"{P}/calibration/{CAL_OBJECT}"
CAL_PREDICTIONS = ["before", "after"]
if CAL_CONTRACT is not None:
    CAL_PROBE = CAL_CONTRACT.roles["calibration"]
    CAL_PROBES = [CAL_PROBE] + list(CAL_CONTRACT.roles["heldout"])
    # the library: every candidate_stride-th candidate, LIBRARY_CHUNK a job
    CAL_CANDIDATES = list(CANDIDATES.case_name)[:: CAL["candidate_stride"]]
    CAL_K = config["method_params"].get("local_ridge", {}).get("k")
    if isinstance(CAL_K, int) and CAL_K > len(CAL_CANDIDATES):
        config_refusal(f"config calibration.candidate_stride: {CAL['candidate_stride']} keeps "
                       f"{len(CAL_CANDIDATES)} candidates, fewer than method_params.local_ridge.k = {CAL_K} "
                       "neighbours (a smaller stride, or a smaller k)")
    CAL_CHUNKS = [CAL_CANDIDATES[i : i + LIBRARY_CHUNK] for i in range(0, len(CAL_CANDIDATES), LIBRARY_CHUNK)]
    CAL_CHUNK_OF = {case: k for k, chunk in enumerate(CAL_CHUNKS) for case in chunk}
    # the camera the library is seen by (the measurement's: an RGB-D file's own, else the contract's)
    CAL_CAMERA = calibration_camera(CAL, CAL_CONTRACT)
    CALIBRATION_OUTPUTS = [f"{C}/{name}" for name in ("report.md", "report.png", "calibration.csv", "calibration.md",
                                                       "library.csv", "measurement.csv", "estimate.json")] + [
        f"{C}/frames/{which}" for which in CAL_PREDICTIONS]
else:
    CAL_PROBE, CAL_PROBES, CAL_CANDIDATES, CAL_CHUNKS, CAL_CHUNK_OF, CAL_CAMERA = None, [], [], [], {}, None
    CALIBRATION_OUTPUTS = [calibration_not_configured]
register_study("calibration", CALIBRATION_OUTPUTS, [])
# how the measurement and the library are observed (experiments.ObservationSettings)
CAL_OBSERVATION = {"kind": CAL["kind"], "track": dict(CAL["track"]), "width": CAL["width"], "height": CAL["height"]}


wildcard_constraints:
    prediction="before|after",


rule calibration_asset:
    """The object's asset, from its contract wherever that lies."""
    conda:
        "../envs/knockgs.yaml"
    output:
        ply=f"{C}/asset.ply",
        particles=f"{C}/asset.particles.npz",
        scene=f"{C}/asset.scene.npz",
        summary=f"{C}/asset.summary.json",
        figure=f"{C}/asset.fill.png",
    log:
        f"logs/{PROFILE}/calibration/{CAL_OBJECT}/asset.log",
    params:
        profile=PROFILE,
        contract=CAL_SOURCE,
    resources:
        mem_mb=8000 if PROFILE == "paper" else 2000,
        runtime=30,
    threads: 1
    script:
        "../scripts/asset.py"


rule calibration_library:
    """Probe-A rollouts of one chunk of the calibration's candidates, with deformation gradients."""
    conda:
        "../envs/knockgs.yaml"
    input:
        particles=f"{C}/asset.particles.npz",
    output:
        folder=directory(f"{C}/library/chunk{{chunk}}"),
    log:
        f"logs/{PROFILE}/calibration/{CAL_OBJECT}/library/chunk{{chunk}}.log",
    benchmark:
        f"{P}/benchmarks/calibration/{CAL_OBJECT}/library/chunk{{chunk}}.tsv"
    params:
        profile=PROFILE,
        object=CAL_SOURCE,
        runs=cal_library_runs,
        device=DEVICE,
        deterministic=DETERMINISTIC,
    resources:
        mem_mb=16000 if PROFILE == "paper" else 2000,
        runtime=rollout_minutes(LIBRARY_CHUNK),
        gpu=1 if ON_GPU else 0,
    threads: 1
    script:
        "../scripts/rollout.py"


rule calibration_measurement:
    """The measured Probe-A observation's descriptor (tracked here if it is RGB-D) and the
    camera the library is to be seen by."""
    conda:
        "../envs/knockgs.yaml"
    input:
        measurement=CAL["measurement"] or [],
    output:
        query=f"{C}/measurement.csv",
        info=f"{C}/measurement.json",
    log:
        f"logs/{PROFILE}/calibration/{CAL_OBJECT}/measurement.log",
    params:
        contract=CAL_SOURCE,
        profile=PROFILE,
        observation=CAL_OBSERVATION,
        camera=CAL_CAMERA,
    script:
        "../scripts/calibration_measurement.py"


rule calibration_observe_library:
    """One chunk of library rollouts, each rendered as RGB-D by the measurement's camera,
    tracked with its tracker and described (a new measurement by the same camera and tracker
    leaves it as it is)."""
    conda:
        "../envs/knockgs.yaml"
    input:
        ply=f"{C}/asset.ply",
        scene=f"{C}/asset.scene.npz",
        rollouts=f"{C}/library/chunk{{chunk}}",
    output:
        table=f"{C}/library/observed/chunk{{chunk}}.csv",
    log:
        f"logs/{PROFILE}/calibration/{CAL_OBJECT}/library/observed/chunk{{chunk}}.log",
    benchmark:
        f"{P}/benchmarks/calibration/{CAL_OBJECT}/library/observed/chunk{{chunk}}.tsv"
    params:
        runs=cal_library_runs,
        observation=CAL_OBSERVATION,
        camera=CAL_CAMERA,
        device=DEVICE,
    resources:
        gpu=1 if ON_GPU else 0,
    script:
        "../scripts/calibration_observe.py"


rule calibration_library_table:
    """The library: labels + the observed descriptors, in candidates.csv order."""
    conda:
        "../envs/knockgs.yaml"
    input:
        observations=[f"{C}/library/observed/chunk{k}.csv" for k in range(len(CAL_CHUNKS))],
    output:
        table=f"{C}/library.csv",
    log:
        f"logs/{PROFILE}/calibration/{CAL_OBJECT}/library.log",
    params:
        cases=CAL_CANDIDATES,
    script:
        "../scripts/calibration_library.py"


checkpoint calibration_estimate:
    """The local ridge on the observed library and the measurement's descriptor alone."""
    conda:
        "../envs/knockgs.yaml"
    input:
        library=f"{C}/library.csv",
        queries=f"{C}/measurement.csv",
    output:
        json=[f"{C}/estimate.json"],
    log:
        f"logs/{PROFILE}/calibration/{CAL_OBJECT}/estimate.log",
    params:
        methods=["local_ridge"],
        options={"local_ridge": config["method_params"].get("local_ridge", {})},
        config_hash=config_hash(),
    script:
        "../scripts/estimate.py"


rule calibration_predict:
    """A prediction's rollouts (before: the base material; after: the frozen estimate) under
    Probe A and every held-out probe, with deformation gradients."""
    conda:
        "../envs/knockgs.yaml"
    input:
        particles=f"{C}/asset.particles.npz",
        estimate=cal_prediction_estimate,
    output:
        folder=directory(f"{C}/predictions/{{prediction}}"),
    log:
        f"logs/{PROFILE}/calibration/{CAL_OBJECT}/predictions/{{prediction}}.log",
    params:
        profile=PROFILE,
        object=CAL_SOURCE,
        runs=cal_prediction_runs,
        device=DEVICE,
        deterministic=DETERMINISTIC,
    resources:
        mem_mb=16000 if PROFILE == "paper" else 2000,
        runtime=rollout_minutes(len(CAL_PROBES)),
        gpu=1 if ON_GPU else 0,
    threads: 1
    script:
        "../scripts/rollout.py"


rule calibration_render:
    """Every frame of a prediction's rollouts, by the contract camera."""
    conda:
        "../envs/knockgs.yaml"
    input:
        ply=f"{C}/asset.ply",
        scene=f"{C}/asset.scene.npz",
        rollouts=f"{C}/predictions/{{prediction}}",
    output:
        folder=directory(f"{C}/frames/{{prediction}}"),
    log:
        f"logs/{PROFILE}/calibration/{CAL_OBJECT}/frames/{{prediction}}.log",
    params:
        jobs=cal_render_jobs,
        camera=CAL_CONTRACT.camera if CAL_CONTRACT is not None else None,
        width=None,
        height=None,
        device=DEVICE,
    resources:
        mem_mb=4000,
        runtime=30,
        gpu=1 if ON_GPU else 0,
    script:
        "../scripts/render.py"


rule calibration_observe_predictions:
    """Each prediction's Probe-A rollout observed as the measurement (the report's Probe-A panel)."""
    conda:
        "../envs/knockgs.yaml"
    input:
        ply=f"{C}/asset.ply",
        scene=f"{C}/asset.scene.npz",
        estimate=f"{C}/estimate.json",
        rollouts=[f"{C}/predictions/{which}" for which in CAL_PREDICTIONS],
    output:
        table=f"{C}/predictions/observed.csv",
    log:
        f"logs/{PROFILE}/calibration/{CAL_OBJECT}/predictions/observed.log",
    params:
        runs=cal_observed_prediction_runs,
        observation=CAL_OBSERVATION,
        camera=CAL_CAMERA,
        device=DEVICE,
    resources:
        gpu=1 if ON_GPU else 0,
    script:
        "../scripts/calibration_observe.py"


rule calibration_report:
    """The table and the one-page report: the estimate with its interval and condition number,
    the measurement against the Probe-A predictions, the held-out probes' predictions."""
    conda:
        "../envs/knockgs.yaml"
    input:
        estimate=f"{C}/estimate.json",
        library=f"{C}/library.csv",
        measurement=f"{C}/measurement.json",
        observed=f"{C}/predictions/observed.csv",
        predictions=[f"{C}/predictions/{which}" for which in CAL_PREDICTIONS],
        frames=[f"{C}/frames/{which}" for which in CAL_PREDICTIONS],
    output:
        csv=f"{C}/calibration.csv",
        md=f"{C}/calibration.md",
        report=f"{C}/report.md",
        png=report(f"{C}/report.png", caption="../report/calibration.rst", category="Calibration"),
    log:
        f"logs/{PROFILE}/calibration/{CAL_OBJECT}/report.log",
    params:
        object=CAL_OBJECT,
        probe=CAL_PROBE,
        probes=CAL_PROBES,
        predictions=CAL_PREDICTIONS,
        n_candidates=len(CAL_CANDIDATES),
        measurement=CAL["measurement"],
    script:
        "../scripts/calibration_report.py"


rule calibration:
    """Named target: the calibration of config `calibration`'s object from its measurement."""
    input:
        CALIBRATION_OUTPUTS,
