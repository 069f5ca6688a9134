# Shared by every stage: config validation, wildcard constraints, path helpers and the input
# functions of the stages' rules. The path grammar is at the top of the Snakefile.
#
# The config schema (workflow/schemas/config.schema.yaml) is the one source of the workflow's
# defaults: validate() fills them in, and nothing below restates one.

import json
import os
import re
from functools import cache

from snakemake.exceptions import WorkflowError
from snakemake.utils import validate

from knockgs_core.calibration import METHOD_NAMES, ORACLE_METHOD
from knockgs_core.contract import check_held_out, load_candidates, load_contract, load_targets, read_yaml
from knockgs_core.errors import InputError
from knockgs_core.rollout import theta_tag


def _yaml_scalars(config, schema_file):
    """``--config deterministic=true``: Snakemake reads a command-line value as a number,
    ``True`` or ``False``, else a string, and the values inside a mapping given on the command
    line (``--config 'calibration={candidate_stride: 6}'``) as strings. Where the schema asks
    for a boolean, YAML's ``true`` and ``false`` (as a config file writes them) are read as
    booleans; inside a mapping, where it asks for an integer or a number (or allows null), also
    as one alternative of several (``method_params={local_ridge: {alpha: 0.001}}``) and in a
    list, a string that reads as one is read as one (a config file's quoted "6" too). Other
    strings stay, for the schema to refuse."""
    import yaml

    def types(prop):
        t = prop.get("type", [])
        alternatives = prop.get("oneOf", []) + prop.get("anyOf", [])  # alpha: a number or "cv"
        return set([t] if isinstance(t, str) else t).union(*(types(alt) for alt in alternatives))

    def convert(value, prop, nested):
        t = types(prop)
        if isinstance(value, dict) and "properties" in prop:
            for key, v in value.items():
                if key in prop["properties"]:
                    value[key] = convert(v, prop["properties"][key], True)
            return value
        if isinstance(value, list) and isinstance(prop.get("items"), dict):
            return [convert(v, prop["items"], nested) for v in value]
        if not isinstance(value, str):
            return value
        if "boolean" in t and value.lower() in ("true", "false"):
            return value.lower() == "true"
        if not nested:
            return value
        if "null" in t and value in ("null", "~"):
            return None
        for kind, cast in (("integer", int), ("number", float)):
            if kind in t:
                try:
                    return cast(value)
                except ValueError:
                    pass
        return value

    with open(schema_file) as f:
        props = yaml.safe_load(f)["properties"]
    for key, value in config.items():
        if key in props:
            config[key] = convert(value, props[key], False)


def config_refusal(message):
    """Stop the run at config read with one line on stderr (which file, which key, what is
    allowed) and no stack: a refused config is bad input, not a failure of the workflow."""
    import sys

    sys.exit(f"knockgs workflow: config error: {' '.join(str(message).split())}")


def _config_file_of(key):
    """Where the top-level ``key`` is set: the command line's --config (which wins), else the
    last --configfile that sets it, else the Snakefile's configfile."""
    settings = workflow.config_settings
    if key in (settings.config or {}):
        return "--config"
    given = [str(p) for p in settings.configfiles]
    order = list(reversed(given)) + [p for p in reversed(workflow.configfiles) if str(os.path.abspath(p)) not in given]
    for path in order:
        try:
            data = read_yaml(path)
        except InputError:
            continue
        if isinstance(data, dict) and key in data:
            return path
    return "--config"


def _check_config_files():
    """Every config file read as strictly as a contract: a key given twice (the last would win
    silently), an alias or a non-YAML file is refused, naming the file and the line."""
    for path in workflow.configfiles:
        try:
            read_yaml(path)
        except InputError as exc:
            config_refusal(exc)


def _validate_config(schema_file):
    """validate() against the schema, its refusal as one line: the file that sets the key, the
    key's path, what is wrong and what is allowed (not the whole schema)."""
    import jsonschema

    try:
        validate(config, schema_file, set_default=True)
    except WorkflowError as exc:
        err = exc.__context__  # the schema's ValidationError, which validate() formats with the whole schema
        if not isinstance(err, jsonschema.exceptions.ValidationError):
            raise
        if err.context:  # a oneOf/anyOf: the alternative that came closest
            err = jsonschema.exceptions.best_match(err.context)
        keys = [str(k) for k in err.absolute_path]
        allowed = ""
        if err.validator == "additionalProperties":
            props = err.schema.get("properties", {})
            unexpected = sorted(set(err.instance) - set(props)) if isinstance(err.instance, dict) else []
            keys += unexpected[:1]
            allowed = f"; allowed keys here: {', '.join(props)}"
        elif err.validator == "enum":
            allowed = f"; allowed: {', '.join(map(str, err.validator_value))}"
        where = _config_file_of(keys[0]) if keys else "config"
        config_refusal(f"{where}: key '{'.'.join(keys) or '(top level)'}': {err.message[:300]}{allowed}")


_check_config_files()
_yaml_scalars(config, os.path.join(workflow.current_basedir, "../schemas/config.schema.yaml"))
_validate_config("../schemas/config.schema.yaml")

PROFILE = config["profile"]
P = f"results/{PROFILE}"
DEVICE = config["device"]
ON_GPU = DEVICE.startswith("cuda")
# every simulating job's bitwise-reproducible P2G, on a GPU: CPU rollouts are reproducible either way,
# and keep the scatter, 1.4x faster there than the fixed-point sums
# (benchmarks/results/2026-11-28-fixed-point-sums.md)
DETERMINISTIC = config["deterministic"] and ON_GPU
# the paper profile's rollouts are large (0.2-0.9 GB each): the jobs that read many of them
# (descriptors, evaluations, shift tables, audits) read them on threads; the same outputs for
# any count (knockgs_core.io.ordered_map)
READ_THREADS = 8 if PROFILE == "paper" else 1
# their memory: a 121-frame paper-scale rollout held with its prediction and scored takes ~3 GB a
# thread, a read alone ~1.2 GB (benchmarks/reading_memory_bench.py); the duration table's five
# targets on threads ~15 GB
READ_MEM_MB = 16000 if PROFILE == "paper" else 2000
OBJECTS = list(config["objects"])
SPLIT = config["split"]
METHODS = list(config["methods"])
# the config's deployable methods (every one but the oracle)
CONFIG_DEPLOYABLE = [m for m in METHODS if m != ORACLE_METHOD]
RENDER = config["render"]
# the evaluation jobs write deformation gradients only for renders (config render.enabled; at paper
# scale 0.5 GB a rollout), and the library only where render.library_deformation_gradients
EVAL_F = RENDER["enabled"]
LIBRARY_F = RENDER["library_deformation_gradients"]
# render.keep_deformation_gradients false: the evaluation jobs' F go to a temporary folder of
# their own (evalF), removed once its readers are done
EVAL_F_TEMP = EVAL_F and not RENDER["keep_deformation_gradients"]
DISCREPANCY = config["discrepancy"]
SHIFTS = config["probe_shifts"]

# the tables, every split's targets held out from the candidates (a target equal to a candidate,
# or two targets with one pair, refused here for every table, not only by the `all` audit), the
# config's split: refused at config read, as one line
try:
    CANDIDATES = load_candidates()
    check_held_out()
    load_targets(SPLIT)
except InputError as exc:
    config_refusal(exc)

# A library job simulates LIBRARY_CHUNK candidates in one process (simulate.smk; config
# library_chunk), in candidates.csv order: job {chunk} writes the folder .../lib/chunk{chunk}.
_CANDIDATE_NAMES = list(CANDIDATES.case_name)
_gpu = workflow.global_resources.get("gpu")  # --resources gpu=N (a Resource in Snakemake 9, a number before)
_CARDS = max(1, int(getattr(_gpu, "value", _gpu) or 1))
LIBRARY_CHUNK = config["library_chunk"]
if LIBRARY_CHUNK == "auto":  # a job a card (each job's runs on streams of one card), or 6 a job on the CPU
    LIBRARY_CHUNK = -(-len(_CANDIDATE_NAMES) // _CARDS) if ON_GPU else 6
LIBRARY_CHUNKS = [_CANDIDATE_NAMES[i : i + LIBRARY_CHUNK] for i in range(0, len(_CANDIDATE_NAMES), LIBRARY_CHUNK)]
_CHUNK_OF = {case: k for k, chunk in enumerate(LIBRARY_CHUNKS) for case in chunk}
# A rollout job's time limit [min] (`runtime`, what a Slurm profile asks for) for `runs`
# rollouts: an hour a paper-scale rollout on a CPU, 20 minutes at the smaller profiles; on a
# GPU a paper-scale rollout takes 2-12 s (the Ficus's 75,000 substeps the longest;
# benchmarks/results/2026-11-26-paper-tables-one-gpu.md), so a minute a rollout and ten for the job's start leave 5x there:
# 54 candidates on one card ask for 64 minutes, not 54 hours.
_ROLLOUT_MINUTES = (1 if ON_GPU else 60) if PROFILE == "paper" else 20
_JOB_MINUTES = 10 if PROFILE == "paper" and ON_GPU else 0


def rollout_minutes(runs):
    """The time limit [min] of a job of ``runs`` rollouts."""
    return _JOB_MINUTES + _ROLLOUT_MINUTES * runs


_CANDIDATE_THETA = {r.case_name: (float(r.E_scale), float(r.density_scale)) for r in CANDIDATES.itertuples(index=False)}
_CANDIDATE_OF_TAG = {theta_tag(theta): case for case, theta in _CANDIDATE_THETA.items()}


wildcard_constraints:
    object="[A-Za-z0-9_]+",
    probe="[A-Za-z0-9_]+",
    theta=r"sE[0-9.]+_sR[0-9.]+",
    split="[A-Za-z0-9_]+",
    method="|".join(METHOD_NAMES),
    chunk="[0-9]+",
    case="[A-Za-z0-9_]+",
    res="ci|default|paper",


# ---------------------------------------------------------------- contracts, targets, thetas


@cache
def contract(obj, profile=PROFILE, n_grid=None):
    """The object contract at a resolution profile (loaded once), on ``n_grid`` cells per axis
    where given (``at_resolution``)."""
    return load_contract(obj, profile, n_grid=n_grid)


for _obj in OBJECTS:  # a broken or unknown contract fails at parse time, naming its file and field
    try:
        contract(_obj)
    except InputError as exc:
        config_refusal(exc)


def calibration_probe(obj):
    return contract(obj).roles["calibration"]


def heldout_probes(obj):
    return list(contract(obj).roles["heldout"])


def eval_probes(obj):
    """Probe A then every held-out Probe B of the object (the main-table columns)."""
    return [calibration_probe(obj)] + heldout_probes(obj)


def target_thetas(split=SPLIT):
    """target name -> (s_E, s_rho) of a split, in targets.csv order."""
    return {r.case_name: (r.E_scale, r.density_scale) for r in load_targets(split).itertuples(index=False)}


def candidate_theta(case):
    """(s_E, s_rho) of a candidate, by case name."""
    return _CANDIDATE_THETA[case]


def parse_theta(tag):
    """(s_E, s_rho) of a theta tag (the 6-decimal values the evaluation rollouts run at)."""
    se, sr = tag[2:].split("_sR")
    return float(se), float(sr)


def config_hash():
    import hashlib

    return hashlib.sha256(json.dumps(config, sort_keys=True, default=str).encode()).hexdigest()[:16]


# ---------------------------------------------------------------- rollout and frame paths


def folders(paths):
    """The folders holding ``paths``: the outputs of the jobs that write them."""
    return sorted({os.path.dirname(p) for p in paths})


def library_root(obj):
    return f"{P}/rollouts/{obj}/lib"


def library_rollout(root, case, suffix=".parquet"):
    """A candidate's library rollout in the library folder ``root`` (suffix ".F.parquet": its
    deformation gradients)."""
    return f"{root}/chunk{_CHUNK_OF[case]}/{theta_tag(candidate_theta(case))}{suffix}"


def library_rollouts(obj):
    """candidate name -> library rollout of the object, in candidates.csv order."""
    return {case: library_rollout(library_root(obj), case) for case in _CANDIDATE_NAMES}


def library_runs(chunk, probe, root, *, export_F):
    """The rollouts of library job ``chunk``: each candidate of the chunk under ``probe``."""
    return [
        {
            "theta": candidate_theta(case),
            "probe": probe,
            "rollout": library_rollout(root, case),
            "F": library_rollout(root, case, ".F.parquet") if export_F else None,
        }
        for case in LIBRARY_CHUNKS[int(chunk)]
    ]


def simulated_probes(obj, tag):
    """The probes the evaluation job of theta ``tag`` simulates: a candidate's Probe-A
    evaluation rollout is its library rollout, so a candidate needs only the held-out probes
    (and Probe A too, for its deformation gradients, where the library has none: LIBRARY_F)."""
    return heldout_probes(obj) if tag in _CANDIDATE_OF_TAG and (LIBRARY_F or not EVAL_F) else eval_probes(obj)


def eval_rollout(obj, probe, theta, suffix=".parquet", *, with_F=False):
    """The evaluation rollout of (probe, theta): a candidate's library rollout under Probe A,
    else the evaluation job's file (suffix ".F.parquet": the deformation gradients).
    ``with_F``: the rollout of a run that has deformation gradients (a consumer of the
    gradients reads positions and gradients of one run): the evaluation job's where the
    library has none (LIBRARY_F false)."""
    tag = theta_tag(theta)
    with_F = with_F or suffix == ".F.parquet"
    if probe == calibration_probe(obj) and tag in _CANDIDATE_OF_TAG and (LIBRARY_F or not with_F):
        return library_rollout(library_root(obj), _CANDIDATE_OF_TAG[tag], suffix)
    if suffix == ".F.parquet" and EVAL_F_TEMP:
        return f"{P}/rollouts/{obj}/evalF/{tag}/{probe}{suffix}"
    return f"{P}/rollouts/{obj}/eval/{tag}/{probe}{suffix}"


def temp_F_folders(runs):
    """The temporary deformation-gradient folders (EVAL_F_TEMP) that the runs' "F" paths lie
    in: a reader's input, so they are removed only once it is done (none where F stays with
    the positions)."""
    return folders(r["F"] for r in runs) if EVAL_F_TEMP else []


def need_eval_F(consumer):
    """Stop with the setting named where ``consumer`` renders evaluation rollouts that have no
    deformation gradients (render.enabled false)."""
    if not EVAL_F:
        raise WorkflowError(f"config render.enabled is false (profile {PROFILE}), so the evaluation rollouts have "
                            f"no deformation gradients, but {consumer} renders them: set it to true")


def evaluation_runs(wc):
    """The rollouts of the evaluation job of (object, theta), with deformation gradients."""
    theta = parse_theta(wc.theta)
    return [
        {"theta": theta, "probe": probe, "rollout": eval_rollout(wc.object, probe, theta, with_F=True),
         "F": eval_rollout(wc.object, probe, theta, ".F.parquet") if EVAL_F else None}
        for probe in simulated_probes(wc.object, wc.theta)
    ]


def diag_set_folder(obj, name):
    """The folder of a diagnostics' set of rollouts (one job: simulate.smk, rollout_diag_set)."""
    return f"{P}/rollouts/{obj}/diag/{SPLIT}/{name}"


def diag_set_paths(obj, name):
    """{(probe, theta): rollout} of a diagnostics' set: every (probe, theta) that the study
    ``name`` simulates beyond the evaluation rollouts, known once its estimates exist
    (:func:`diag_set_cases`, through their checkpoints)."""
    folder = diag_set_folder(obj, name)
    probes, thetas = diag_set_cases(obj, name)
    return {(pr, th): f"{folder}/{theta_tag(th)}__{pr}.parquet" for pr in probes for th in thetas}


def diag_set_rollouts(obj, name):
    """{"probe/theta tag": rollout} of a diagnostics' set (:func:`diag_set_paths`)."""
    return {f"{pr}/{theta_tag(th)}": path for (pr, th), path in diag_set_paths(obj, name).items()}


def frames_file(obj, probe, theta):
    return f"{P}/frames/{obj}/{theta_tag(theta)}/{probe}.npz"


def render_jobs(wc):
    """Rollout, deformation gradients and frames file of each evaluation probe of the render
    job of (object, theta)."""
    need_eval_F("the render rule")
    theta = parse_theta(wc.theta)
    return [
        {"rollout": eval_rollout(wc.object, probe, theta, with_F=True), "F": eval_rollout(wc.object, probe, theta, ".F.parquet"),
         "frames": frames_file(wc.object, probe, theta)}
        for probe in eval_probes(wc.object)
    ]


# ---------------------------------------------------------------- frozen estimates (checkpoints)


def estimate_json(obj, split, method):
    """The frozen-estimate file of (object, split, method): a checkpoint, so rules that
    depend on the estimated thetas are scheduled once it exists."""
    if method == ORACLE_METHOD:
        return checkpoints.oracle_estimate.get(object=obj, split=split).output.json
    return checkpoints.estimate.get(object=obj, split=split).output.json[CONFIG_DEPLOYABLE.index(method)]


def thetas_of(path):
    """target name -> frozen (s_E, s_rho) of an estimate file."""
    with open(path) as fh:
        doc = json.load(fh)
    return {p["case_name"]: (p["E_scale"], p["density_scale"]) for p in doc["predictions"]}


def _estimate_thetas(path):
    """The frozen thetas of an estimate file, in its targets' order (:func:`thetas_of`)."""
    return list(thetas_of(path).values())


def estimated_thetas(obj, split, method):
    """target name -> frozen (s_E, s_rho) of a method."""
    return thetas_of(estimate_json(obj, split, method))


def writeback_thetas(wc):
    """The method's frozen estimates, then the split's hidden targets."""
    return list(estimated_thetas(wc.object, wc.split, wc.method).values()) + list(target_thetas(wc.split).values())


# ---------------------------------------------------------------- input functions


def query_rollouts(wc):
    """The targets' Probe-A rollouts, in targets.csv order."""
    return [eval_rollout(wc.object, calibration_probe(wc.object), th) for th in target_thetas(wc.split).values()]


def evaluation_rollouts(wc):
    """{"probe/theta": rollout} of the write-back evaluation of (object, split, method)."""
    ths = writeback_thetas(wc)
    return {f"{pr}/{theta_tag(th)}": eval_rollout(wc.object, pr, th) for pr in eval_probes(wc.object) for th in ths}


def evaluation_inputs(wc):
    return {"estimate": estimate_json(wc.object, wc.split, wc.method), "targets": "config/targets.csv",
            "rollouts": folders(evaluation_rollouts(wc).values())}


def render_frames(wc):
    """{"probe/theta": frames file} of the image metrics of (object, split, method)."""
    ths = writeback_thetas(wc)
    return {f"{pr}/{theta_tag(th)}": frames_file(wc.object, pr, th) for pr in eval_probes(wc.object) for th in ths}


def render_metric_inputs(wc):
    return {"estimate": estimate_json(wc.object, wc.split, wc.method), "targets": "config/targets.csv",
            "frames": folders(render_frames(wc).values())}


def qualitative_frames(wc):
    """Frames of the animated target, then of each method's estimate of it, under the object's
    first held-out probe."""
    target = RENDER["gif_target"]
    probe = heldout_probes(wc.object)[0]
    thetas = [target_thetas()[target]] + [estimated_thetas(wc.object, SPLIT, m)[target] for m in METHODS]
    return [frames_file(wc.object, probe, th) for th in thetas]


def qualitative_inputs(wc):
    return {"estimates": [estimate_json(wc.object, SPLIT, m) for m in METHODS], "frames": folders(qualitative_frames(wc))}


# ---------------------------------------------------------------- registries the studies fill in

#: study -> {"outputs", "in_all"}: what the study's named target (a rule named as the study)
#: makes, and the part of it that `all` makes, by the study's config switches. Each study's
#: .smk registers itself (register_study); the Snakefile's `all` takes every study's in_all
#: (studies_in_all).
STUDIES = {}


def register_study(name, outputs, in_all):
    """Register the study ``name``: its ``outputs`` and the part of them ``all`` makes, which
    is returned."""
    STUDIES[name] = {"outputs": list(outputs), "in_all": list(in_all)}
    return STUDIES[name]["in_all"]


def studies_in_all():
    """Every registered study's outputs that `all` makes."""
    return [path for study in STUDIES.values() for path in study["in_all"]]


#: diagnostics' set -> (cases(obj) -> (probes, thetas), estimates(obj) -> the estimate files
#: the thetas come from): the rollouts a study simulates beyond the evaluation rollouts, each
#: set in one job (simulate.smk: rollout_diag_set). The studies register their sets.
DIAG_SETS = {}


def diag_set_cases(obj, name):
    """(probes, thetas) of the diagnostics' set ``name`` (known once its estimates exist)."""
    return DIAG_SETS[name][0](obj)


def diag_set_estimates(wc):
    """The estimate files that a diagnostics' set's thetas come from."""
    return DIAG_SETS[wc.set][1](wc.object)


def diag_set_runs(wc):
    """The rollouts of a diagnostics' set's job, without deformation gradients."""
    return [{"theta": parse_theta(theta_tag(th)), "probe": pr, "rollout": path, "F": None}
            for (pr, th), path in diag_set_paths(wc.object, wc.set).items()]
