# Config helpers, wildcard constraints and path helpers shared by every rule file.
import os

from knockgs_core.contract import load_candidates, load_contract, load_targets
from knockgs_core.rollout import theta_tag

PROFILE = config["profile"]
P = f"results/{PROFILE}"
DEVICE = config.get("device", "cpu")
OBJECTS = list(config["objects"])
SPLIT = config.get("split", "main")
METHODS = list(config["methods"])
RENDER = {"enabled": True, "width": 160, "height": 120, "gif_target": "target_001", **config.get("render", {})}
ON_GPU = DEVICE.startswith("cuda")
DISCREPANCY = {"enabled": True, "object": "pillow", "resolution": PROFILE, **config.get("discrepancy", {})}

CANDIDATES = load_candidates()
CONTRACTS = {o: load_contract(o, PROFILE) for o in OBJECTS}


wildcard_constraints:
    object="[A-Za-z0-9_]+",
    probe="[A-Za-z0-9_]+",
    theta=r"sE[0-9.]+_sR[0-9.]+",
    split="[A-Za-z0-9_]+",
    method="[a-z_]+",


def targets(split=SPLIT):
    return load_targets(split)


def calibration_probe(obj):
    return CONTRACTS[obj].roles["calibration"]


def heldout_probes(obj):
    return list(CONTRACTS[obj].roles["heldout"])


def eval_probes(obj):
    """Probe A then every held-out Probe B of the object (the main-table columns)."""
    return [calibration_probe(obj)] + heldout_probes(obj)


def parse_theta(tag):
    se, sr = tag[2:].split("_sR")
    return float(se), float(sr)


def candidate_theta(case):
    """(s_E, s_rho) of a candidate, by case name."""
    row = CANDIDATES.set_index("case_name").loc[case]
    return float(row.E_scale), float(row.density_scale)


def lib_rollout(obj, case):
    return f"{P}/rollouts/{obj}/lib/{theta_tag(candidate_theta(case))}.parquet"


CANDIDATE_TAGS = frozenset(theta_tag((r.E_scale, r.density_scale)) for r in CANDIDATES.itertuples(index=False))


def _eval_base(obj, probe, theta):
    """A candidate's Probe-A evaluation rollout is its library rollout (the same simulation,
    which exports F too); every other (probe, theta) has its own evaluation rollout."""
    tag = theta_tag(theta)
    if probe == calibration_probe(obj) and tag in CANDIDATE_TAGS:
        return f"{P}/rollouts/{obj}/lib/{tag}"
    return f"{P}/rollouts/{obj}/eval/{probe}/{tag}"


def eval_rollout(obj, probe, theta):
    return _eval_base(obj, probe, theta) + ".parquet"


def eval_deformation(obj, probe, theta):
    return _eval_base(obj, probe, theta) + ".F.parquet"


def evaluation_rollout_map(wc):
    """{"probe/theta_tag": rollout path} of the evaluation inputs (for the evaluate script)."""
    ths = list(estimated_thetas(wc).values()) + list(target_thetas(wc.split).values())
    return {f"{pr}/{theta_tag(th)}": eval_rollout(wc.object, pr, th) for pr in eval_probes(wc.object) for th in ths}


def target_thetas(split=SPLIT):
    t = targets(split)
    return {r.case_name: (r.E_scale, r.density_scale) for r in t.itertuples(index=False)}


def config_hash():
    import hashlib, json

    return hashlib.sha256(json.dumps(config, sort_keys=True, default=str).encode()).hexdigest()[:16]


def estimate_json(wc):
    """The frozen-estimate file of (object, split, method): a checkpoint, so rules that
    depend on the estimated thetas are scheduled once it exists."""
    cp = checkpoints.oracle_estimate if wc.method == "parameter_nearest_oracle" else checkpoints.estimate
    return cp.get(object=wc.object, split=wc.split, method=wc.method).output.json


def estimated_thetas(wc):
    import json

    with open(estimate_json(wc)) as fh:
        doc = json.load(fh)
    return {p["case_name"]: (p["E_scale"], p["density_scale"]) for p in doc["predictions"]}


def all_outputs():
    out = []
    for o in OBJECTS:
        out += [f"results/tables/main_{o}.csv", f"results/tables/main_{o}.md", f"results/tables/targetwise_{o}.csv",
                f"results/tables/targetwise_{o}.md", f"results/figures/main_{o}.png", f"results/figures/fill_{o}.png"]
        if RENDER["enabled"]:
            out += [f"results/tables/render_{o}.csv", f"results/tables/render_{o}.md", f"results/figures/qualitative_{o}.png", f"results/figures/compare_{o}.gif"]
    out += ["results/tables/objects.csv", "results/tables/objects.md", "results/figures/objects.png"]
    out += [f"results/audits/{a}.json" for a in AUDITS]
    out += globals().get("DISCREPANCY_OUTPUTS", [])
    return out


# used by simulate.smk
def _rollout_resources(wildcards, attempt):
    return 16000 if PROFILE == "paper" else 2000


# used by evaluate.smk
def evaluation_inputs(wc):
    rollouts = sorted(set(evaluation_rollout_map(wc).values()))
    return {"estimate": estimate_json(wc), "targets": "config/targets.csv", "rollouts": rollouts}


# used by render.smk
def render_metric_inputs(wc):
    ests = estimated_thetas(wc)
    truths = target_thetas(wc.split)
    frames = set()
    for probe in eval_probes(wc.object):
        for th in list(ests.values()) + list(truths.values()):
            frames.add(f"{P}/renders/{wc.object}/{probe}/{theta_tag(th)}.npz")
    return {"estimate": estimate_json(wc), "targets": "config/targets.csv", "frames": sorted(frames)}


# used by render.smk
def qualitative_inputs(wc):
    target = RENDER["gif_target"]
    probe = heldout_probes(wc.object)[0]
    out = {"estimates": [], "frames": [f"{P}/renders/{wc.object}/{probe}/{theta_tag(target_thetas()[target])}.npz"]}
    for m in METHODS:
        w = type("W", (), {"object": wc.object, "split": SPLIT, "method": m})
        out["estimates"].append(estimate_json(w))
        out["frames"].append(f"{P}/renders/{wc.object}/{probe}/{theta_tag(estimated_thetas(w)[target])}.npz")
    return out


# used by audit.smk
AUDITS = ["leakage", "nonfinite", "missing_frames", "duplicates", "completion"]


# used by audit.smk
def _all_estimates():
    return [f"{P}/estimates/{o}/{SPLIT}/{m}.json" for o in OBJECTS for m in METHODS]


# used by audit.smk
def _reported_tables():
    t = [f"results/tables/main_{o}.csv" for o in OBJECTS] + [f"results/tables/targetwise_{o}.csv" for o in OBJECTS] + ["results/tables/objects.csv"]
    if RENDER["enabled"]:
        t += [f"results/tables/render_{o}.csv" for o in OBJECTS]
    return t


# used by discrepancy.smk (DISCREPANCY_OBJECT, DISCREPANCY_RES and _D are defined there)
def _discrepancy_particles():
    """The cases' particles: the main asset when the cases run at the profile's resolution,
    else the discrepancy study's own build at its resolution."""
    obj = DISCREPANCY_OBJECT
    if DISCREPANCY_RES == PROFILE:
        return f"{P}/assets/{obj}.particles.npz"
    return f"{_D}/{DISCREPANCY_RES}/assets/{obj}.particles.npz"


def _discrepancy_library(case_name):
    obj = DISCREPANCY_OBJECT
    if DISCREPANCY_RES == PROFILE:
        return lib_rollout(obj, case_name)
    return f"{_D}/{DISCREPANCY_RES}/library/{obj}/{theta_tag(candidate_theta(case_name))}.parquet"


def _discrepancy_library_runs(wc, chunk):
    """(theta, Probe A) of each candidate of a chunk, at the cases' resolution."""
    probe = load_contract(wc.object, wc.res).roles["calibration"]
    return [(candidate_theta(c), probe) for c in chunk]


def _discrepancy_run_inputs(case):
    """The run job's inputs: measured files, particles, the object's candidate library."""
    return {
        "measured": f"{_D}/cases/{case}/measured_calib.parquet",
        "heldout": f"{_D}/cases/{case}/measured_heldout.parquet",
        "particles": _discrepancy_particles(),
        "library": [_discrepancy_library(c) for c in CANDIDATES.case_name],
    }
