# The input functions and helpers of calibration.smk (included at its top).


def calibration_config(cal):
    """The configured calibration's (contract source, contract) after checking the config block:
    (None, None) when ``calibration.object`` is not set. A problem stops the run with one line
    naming the config key."""
    from knockgs_core.errors import InputError

    if not cal["object"]:
        for key in ("contract", "measurement"):
            if cal[key]:
                raise WorkflowError(f"config calibration.{key}: given, but calibration.object is not set")
        return None, None
    source = cal["contract"] or cal["object"]
    if cal["contract"] and not os.path.isfile(cal["contract"]):
        raise WorkflowError(f"config calibration.contract: {cal['contract']} is not a file")
    try:
        c = load_contract(source, PROFILE)
    except InputError as exc:
        raise WorkflowError(f"config calibration.contract: {exc}") from None
    if c.name != cal["object"]:
        raise WorkflowError(f"config calibration.object: {cal['object']!r}, but the contract {c.source.name} is of "
                            f"{c.name!r}")
    m = cal["measurement"]
    if not m:
        raise WorkflowError("config calibration.measurement: not set (the measured Probe-A observation: tracked "
                            "points or an RGB-D .npz, docs/own_splat.md)")
    if not os.path.isfile(m):
        raise WorkflowError(f"config calibration.measurement: {m} is not a file")
    suffix = os.path.splitext(m)[1].lower()
    if cal["kind"] == "rgbd" and suffix != ".npz":
        raise WorkflowError(f"config calibration.kind: rgbd, but the measurement {m} is not an RGB-D .npz")
    if cal["kind"] == "tracks" and suffix not in (".parquet", ".csv", ".npz"):
        raise WorkflowError(f"config calibration.measurement: tracked points are .parquet, .csv or .npz, got {m}")
    return source, c


def calibration_camera(cal, c):
    """The camera the library is seen by, as JSON (experiments.camera_to_dict): an RGB-D
    measurement's own, else the contract camera at calibration.width x height. Known when the
    workflow starts, so a new measurement by the same camera leaves the library's observation
    as it is."""
    from knockgs_core.experiments import camera_from_contract, camera_from_dict, camera_to_dict

    if cal["kind"] != "rgbd":
        return camera_to_dict(camera_from_contract(c.camera, width=cal["width"], height=cal["height"]))
    import numpy as np

    try:
        with np.load(cal["measurement"], allow_pickle=False) as f:
            k, pose = np.asarray(f["intrinsics"], dtype=np.float64), np.asarray(f["world_to_camera"], dtype=np.float64)
        d = dict(zip(("width", "height", "fx", "fy", "cx", "cy"), k.tolist()), world_to_camera=pose.tolist())
        return camera_to_dict(camera_from_dict(d))
    except Exception as exc:  # not an .npz, a field missing, a camera that is none
        raise WorkflowError(f"config calibration.measurement: {cal['measurement']}: no RGB-D camera (intrinsics, "
                            f"world_to_camera) in it ({type(exc).__name__}: {exc})") from None


def calibration_not_configured(wc):
    """The target `calibration` without a configured object: stop, naming the config key."""
    raise WorkflowError("config calibration.object: not set; the target `calibration` needs calibration.object, "
                        ".contract and .measurement (docs/own_splat.md)")


def cal_rollout(case, suffix=".parquet"):
    """A candidate's library rollout (suffix ".F.parquet": its deformation gradients)."""
    return f"{C}/library/chunk{CAL_CHUNK_OF[case]}/{theta_tag(candidate_theta(case))}{suffix}"


def cal_library_runs(wc):
    """The Probe-A rollouts of library job ``wc.chunk``, with deformation gradients (the
    library is rendered to be observed)."""
    return [{"case_name": case, "theta": candidate_theta(case), "probe": CAL_PROBE, "rollout": cal_rollout(case),
             "F": cal_rollout(case, ".F.parquet")} for case in CAL_CHUNKS[int(wc.chunk)]]


def cal_theta(prediction):
    """(s_E, s_rho) of a prediction: the base material before, the frozen estimate after
    (known once the estimate's checkpoint has run)."""
    if prediction == "before":
        return tuple(BASE_THETA)
    (path,) = checkpoints.calibration_estimate.get().output.json
    return tuple(next(iter(thetas_of(path).values())))


def cal_prediction(prediction, probe, suffix=".parquet"):
    return f"{C}/predictions/{prediction}/{probe}{suffix}"


def cal_prediction_runs(wc):
    """The rollouts of a prediction under Probe A and every held-out probe, with deformation
    gradients (rendered)."""
    theta = cal_theta(wc.prediction)
    return [{"theta": theta, "probe": probe, "rollout": cal_prediction(wc.prediction, probe),
             "F": cal_prediction(wc.prediction, probe, ".F.parquet")} for probe in CAL_PROBES]


def cal_prediction_estimate(wc):
    """The frozen estimate a prediction's theta comes from (none for the base material)."""
    return [] if wc.prediction == "before" else checkpoints.calibration_estimate.get().output.json


def cal_render_jobs(wc):
    return [{"rollout": cal_prediction(wc.prediction, probe), "F": cal_prediction(wc.prediction, probe, ".F.parquet"),
             "frames": f"{C}/frames/{wc.prediction}/{probe}.npz"} for probe in CAL_PROBES]


def cal_observed_prediction_runs(wc):
    """Each prediction's Probe-A rollout, observed as the measurement."""
    return [{"case_name": which, "theta": cal_theta(which), "rollout": cal_prediction(which, CAL_PROBE),
             "F": cal_prediction(which, CAL_PROBE, ".F.parquet")} for which in CAL_PREDICTIONS]
