"""The workflow end to end on the ci profile (one object), audits, and a planted leak."""

from __future__ import annotations

import ast
import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from _workflow import CI, CI_RUN_CONFIG, CI_TESTS_METHODS, scratch_copy, snakemake

from knockgs_core.audits import audit_completion, audit_duplicates, audit_leakage
from knockgs_core.calibration import METHOD_NAMES, METHOD_OPTIONS
from knockgs_core.contract import load_candidates, load_contract, load_targets
from knockgs_core.rollout import read_rollout

ROOT = Path(__file__).resolve().parents[1]
METHODS = CI_TESTS_METHODS  # the shared run's estimators, in table order


def _snakemake(workdir: Path, *targets: str, extra=()):
    # targets first: --config takes a list of values and would swallow them
    return snakemake(workdir, *targets, "--cores", "2", "--configfile=config/ci.yaml", *extra, "--config", "objects=[pillow]")


# ``ci_run`` (tests/conftest.py): the shared ci-profile run of the Pillow main table, render table,
# audits, diagnostics (the main and one alternative split), probe shifts, the passive route and
# the observation ladder (one flow-noise rung), made once per test run


@pytest.mark.slow
def test_ci_run_writes_only_its_profile(ci_run):
    # the ci command leaves the default profile's tables, figures and audits alone
    assert sorted(p.name for p in (ci_run / "results").iterdir()) == ["ci"]
    assert sorted(p.name for p in (ci_run / "logs").iterdir()) == ["ci"]


@pytest.mark.slow
def test_ci_main_table_end_to_end(ci_run):
    t = pd.read_csv(ci_run / f"{CI}/tables/main_pillow.csv")
    assert list(t["method"]) == METHODS
    for col in ["joint_error_pct", "joint_error_sd", "traj_rmse_standard_x", "traj_rmse_standard_y", "traj_rmse_strong_x",
                "curve_rmse_standard_y"]:
        assert col in t.columns and t[col].notna().all()
    e = t.set_index("method")["joint_error_pct"]
    # the fixed default ignores the evidence: its error is a property of the targets alone
    assert e["fixed_default"] == pytest.approx(27.3126, abs=1e-3)
    assert e["local_ridge"] < e["response_nearest"] < e["fixed_default"]
    assert (ci_run / f"{CI}/tables/main_pillow.md").read_text().startswith("# Main table: pillow")
    tw = pd.read_csv(ci_run / f"{CI}/tables/targetwise_pillow.csv")
    assert len(tw) == 5 * len(METHODS)


@pytest.mark.slow
def test_ci_render_outputs(ci_run):
    r = pd.read_csv(ci_run / f"{CI}/tables/render_pillow.csv")
    assert list(r["method"]) == METHODS
    assert {"psnr_fg_standard_y", "ssim_crop_standard_y", "psnr_fg_strong_x"} <= set(r.columns)
    p = r.set_index("method")
    for probe in ["standard_x", "standard_y", "strong_x"]:
        assert p.loc["local_ridge", f"psnr_fg_{probe}"] > p.loc["fixed_default", f"psnr_fg_{probe}"]
    assert (ci_run / f"{CI}/figures/compare_pillow.gif").stat().st_size > 1000


@pytest.mark.slow
def test_ci_candidate_probe_a_evaluation_is_the_library_rollout(ci_run):
    # response nearest lands on candidates: their Probe-A write-back is the library rollout
    # (simulated once, with F), their Probe-B rollouts are evaluation rollouts
    P = ci_run / CI
    est = json.loads((P / "estimates/pillow/main/response_nearest.json").read_text())
    tags = {f"sE{r['E_scale']:.6f}_sR{r['density_scale']:.6f}" for r in est["predictions"]}
    assert tags
    library = {p.name.removesuffix(".F.parquet") for p in (P / "rollouts/pillow/lib").glob("chunk*/*.F.parquet")}
    assert len(library) == 54
    for tag in tags:
        assert tag in library
        assert not (P / f"rollouts/pillow/eval/{tag}/standard_x.parquet").exists()
        assert (P / f"rollouts/pillow/eval/{tag}/standard_y.parquet").exists()
        assert (P / f"frames/pillow/{tag}/standard_x.npz").exists()
    # a target (never a candidate) has its own Probe-A evaluation rollout
    assert (P / "rollouts/pillow/eval/sE0.950000_sR1.350000/standard_x.parquet").exists()


@pytest.mark.slow
def test_ci_audits_pass_and_rerun_is_a_no_op(ci_run):
    for name in ["leakage", "duplicates", "nonfinite", "missing_frames", "rollout_metadata"]:
        verdict = json.loads((ci_run / f"{CI}/audits/{name}.json").read_text())
        assert verdict["passed"], verdict
    leak = json.loads((ci_run / f"{CI}/audits/leakage.json").read_text())
    # the main split's estimates and the passive route's; the Probe-A and the passive libraries;
    # the k x alpha grid's selection
    deployable = [m for m in METHODS if m != "parameter_nearest_oracle"]   # the main and the passive route's
    assert leak["deployable_estimates_checked"] == 2 * len(deployable) and leak["library_rollouts_checked"] == 2 * 54
    assert leak["sensitivity_grids_checked"] == 1
    dry = snakemake(ci_run, "-n", f"{CI}/tables/main_pillow.csv", *CI_RUN_CONFIG)
    assert dry.returncode == 0 and "Nothing to be done" in dry.stdout + dry.stderr


@pytest.mark.slow
def test_ci_diagnostics_tables(ci_run):
    P = ci_run / CI
    main = pd.read_csv(P / "tables/main_pillow.csv").set_index("method")["joint_error_pct"]
    sp = pd.read_csv(P / "tables/splits_pillow.csv")
    assert list(sp["split"]) == ["main"] and (sp["n_targets"] == 5).all()
    # the main split's row is the main table's
    row = sp.iloc[0]
    assert row["local_ridge_pct"] == pytest.approx(main["local_ridge"], rel=1e-9)
    assert row["strongest_pct"] == pytest.approx(main.drop(["local_ridge", "parameter_nearest_oracle"]).min(), rel=1e-9)
    assert {"probe_b_gate_standard_y", "probe_b_gate_strong_x"} <= set(sp.columns)
    assert "paper: 3/3, 2/3, 6/6" in (P / "tables/splits_pillow.md").read_text()
    # the frozen configuration on the full library reproduces the main table's local ridge
    size = pd.read_csv(P / "tables/sensitivity_size_pillow.csv")
    assert list(size["size"]) == [18, 27, 36, 45, 54] and (size["n_nonfinite"] == 0).all()
    assert size["mean_joint_error_pct"].iloc[-1] == pytest.approx(main["local_ridge"], rel=1e-9)
    grid = pd.read_csv(P / "tables/sensitivity_k_alpha_pillow.csv")
    frozen = grid.loc[grid["frozen"], "heldout_joint_error_pct"]
    assert len(grid) == 30 and frozen.iloc[0] == pytest.approx(main["local_ridge"], rel=1e-9)
    assert "2375 offline predictions" in (P / "tables/sensitivity_k_alpha_pillow.md").read_text()
    ident = pd.read_csv(P / "tables/identifiability_pillow.csv").set_index("quantity")["value"]
    assert ident["candidate pairs"] == 1431
    assert len(pd.read_csv(P / "tables/identifiability_pairs_pillow.csv")) == 1431
    for fig in ("splits_pillow", "sensitivity_pillow", "identifiability_pillow"):
        assert (P / f"figures/{fig}.png").stat().st_size > 1000


@pytest.mark.slow
def test_ci_probe_shift_and_passive_tables(ci_run):
    P = ci_run / CI
    deployable = [m for m in METHODS if m != "parameter_nearest_oracle"]
    main = pd.read_csv(P / "tables/main_pillow.csv").set_index("method")["joint_error_pct"]
    d = pd.read_csv(P / "tables/duration_pillow.csv").set_index("method")
    assert list(d.index) == deployable and (d["n_targets"] == 5).all()
    # the frozen estimates are the main table's; evidence beats the fixed default under the new probe
    assert d["joint_error_pct"].to_dict() == pytest.approx(main.drop("parameter_nearest_oracle").to_dict(), rel=1e-9)
    rmse = d["traj_rmse_mean"]
    assert rmse["local_ridge"] < rmse["response_nearest"] < rmse["fixed_default"]
    # the two protocols differ measurably on the targets themselves
    assert (d["protocol_distance_mean"] > 1e-5).all()
    c = pd.read_csv(P / "tables/contact_pillow.csv")
    assert len(c) == 2 * len(deployable) and set(c["target"]) == {"target_001"}
    assert list(c["contact"].unique()) == ["local_center_x", "shifted_contact_x"]
    assert "Single-target demonstration" in (P / "tables/contact_pillow.md").read_text()
    # passive: the protocol is blind to a common scale, bit for bit, and Probe A is not
    prot = json.loads((P / "passive/protocols/pillow.json").read_text())
    assert prot["gravity"][2] < 0 and all(c["passive_bitwise_equal"] and c["active_max_abs_diff"] > 1e-3
                                          for c in prot["invariance"])
    pa = pd.read_csv(P / "tables/passive_active_pillow.csv").set_index(["protocol", "method"])
    lr_a, lr_p = pa.loc[("active", "local_ridge")], pa.loc[("passive", "local_ridge")]
    assert lr_a["joint_error_pct"] == pytest.approx(main["local_ridge"], rel=1e-9)
    # passive recovers the ratio, not the scale: the scale-direction error dominates and exceeds the active one
    assert lr_p["scale_error"] > 5 * lr_p["ratio_error"] and lr_p["scale_error"] > 5 * lr_a["scale_error"]
    assert lr_p["joint_error_pct"] > 5 * lr_a["joint_error_pct"]
    assert lr_p["ratio_span_true_pct"] == pytest.approx(162.5, abs=0.05)
    assert len(pd.read_csv(P / "tables/passive_active_targets_pillow.csv")) == 2 * 5 * len(deployable)
    assert (P / "figures/passive_active_pillow.png").stat().st_size > 1000


@pytest.mark.slow
def test_ci_observation_ladder(ci_run):
    P = ci_run / CI
    deployable = [m for m in METHODS if m != "parameter_nearest_oracle"]
    main = pd.read_csv(P / "tables/main_pillow.csv").set_index("method")
    lad = pd.read_csv(P / "tables/ladder_pillow.csv")
    rungs = ["particles", "gaussians", "visible", "depth", "flow", "flow_noise_0.01"]
    assert list(dict.fromkeys(lad["rung"])) == rungs and len(lad) == len(rungs) * len(deployable)
    # rung 1 is the main route: the same descriptor tables, the same estimates, the same errors
    lib = pd.read_csv(P / "descriptors/pillow/library.csv")
    assert lib.equals(pd.read_csv(P / "ladder/descriptors/pillow/particles/library.csv"))
    q = pd.read_csv(P / "descriptors/pillow/queries_main.csv")
    assert q.equals(pd.read_csv(P / "ladder/descriptors/pillow/particles/queries_main.csv"))
    first = lad[lad["rung"] == "particles"].set_index("method")
    for m in deployable:
        assert first.loc[m, "joint_error_pct"] == pytest.approx(main.loc[m, "joint_error_pct"], rel=1e-12)
        assert first.loc[m, "traj_rmse_probe_b"] == pytest.approx(main.loc[m, "traj_rmse_standard_y"], rel=1e-6)
    # evidence degrades up the ladder: ID-free noisy tracks lose local ridge's accuracy
    lr = lad[lad["method"] == "local_ridge"].set_index("rung")["joint_error_pct"]
    assert lr["particles"] < 2.0 and lr["flow_noise_0.01"] > 3 * lr["particles"]
    assert (P / "figures/ladder_pillow.png").stat().st_size > 1000


@pytest.mark.slow
def test_planted_leak_fails_the_audit(ci_run, tmp_path):
    est_dir = ci_run / f"{CI}/estimates/pillow/main"
    good = json.loads((est_dir / "local_ridge.json").read_text())
    leaked = dict(good, rule_inputs=good["rule_inputs"] + [f"{CI}/rollouts/pillow/eval/sE0.950000_sR1.350000/standard_y.parquet"])
    f = tmp_path / "estimates/pillow/main/local_ridge.json"
    f.parent.mkdir(parents=True)
    f.write_text(json.dumps(leaked))
    v = audit_leakage([f], calibration_probes={"pillow": "standard_x"}, candidates=load_candidates(), targets=load_targets())
    assert not v["passed"] and any("standard_y" in p for p in v["problems"])
    # and the untouched estimate passes
    g = tmp_path / "ok/pillow/main/local_ridge.json"
    g.parent.mkdir(parents=True)
    g.write_text(json.dumps(dict(good, rule_inputs=[str(ci_run / x) for x in good["rule_inputs"]])))
    ok = audit_leakage([g], calibration_probes={"pillow": "standard_x"}, candidates=load_candidates(), targets=load_targets())
    assert ok["passed"]


def test_leakage_audit_flags_labels_in_queries(tmp_path):
    q = tmp_path / "queries_main.csv"
    pd.DataFrame({"case_name": ["t1"], "E_scale": [1.0], **{c: [0.1] for c in ["norm_auc_rms_disp"]}}).to_csv(q, index=False)
    est = tmp_path / "estimates/pillow/main/knn.json"
    est.parent.mkdir(parents=True)
    est.write_text(json.dumps({"deployable": True, "rule_inputs": [str(tmp_path / "library.csv"), str(q)]}))
    v = audit_leakage([est], calibration_probes={"pillow": "standard_x"}, candidates=load_candidates(), targets=load_targets())
    assert not v["passed"] and any("label" in p for p in v["problems"])


def test_leakage_audit_flags_a_target_in_the_library():
    cands = load_candidates()
    targets = load_targets()
    bad = pd.concat([cands, targets.iloc[:1]], ignore_index=True)
    assert audit_leakage([], calibration_probes={}, candidates=bad, targets=targets)["passed"] is False
    assert audit_leakage([], calibration_probes={}, candidates=cands, targets=targets)["passed"] is True


def test_duplicates_and_completion_audits(tmp_path):
    cands = load_candidates()
    assert audit_duplicates(cands, load_targets())["passed"]
    dup = pd.concat([cands, cands.iloc[:1]], ignore_index=True)
    assert not audit_duplicates(dup, load_targets())["passed"]
    assert not audit_completion([tmp_path / "nope.csv"])["passed"]


def test_the_completion_audit_lists_staging_folders_left_by_stopped_jobs(tmp_path):
    # a job killed by SIGKILL leaves its hidden staging folder; if the job never runs again
    # nothing removes it, so the completion audit (run when every job has ended) lists it, warns
    # with the command that removes it, and still passes: no output is read from such a folder
    from knockgs_core.io import staging_folder

    results = tmp_path / "results" / "ci"
    table = results / "tables" / "main_pillow.csv"
    table.parent.mkdir(parents=True)
    table.write_text("method,x\nlocal_ridge,1\n")
    clean = audit_completion([table], [table], ["local_ridge"], results=results)
    assert clean["passed"] and clean["stale_staging"] == [] and clean["warnings"] == []
    stale = [staging_folder(results / "rollouts" / "pillow" / "lib" / "chunk3"),
             staging_folder(results / "frames" / "ficus" / "sE1.050000_sR1.200000")]
    for folder in stale:
        (folder / "inner" / ".nested.partial").mkdir(parents=True)   # a staging folder's contents are not searched
        (folder / "standard_x.parquet").write_bytes(b"half")
    (results / "rollouts" / "pillow" / "lib" / "chunk0").mkdir()     # a finished folder is not listed
    verdict = audit_completion([table], [table], ["local_ridge"], results=results)
    assert verdict["passed"] and verdict["problems"] == []
    assert verdict["stale_staging"] == sorted(str(f) for f in stale)
    assert len(verdict["warnings"]) == 1 and verdict["warnings"][0].startswith("2 staging folder(s)")
    assert all(str(f) in verdict["warnings"][0] for f in stale) and "rm -r" in verdict["warnings"][0]
    assert "stale_staging" not in audit_completion([table])   # without the results folder, as before
    rules = (ROOT / "workflow/rules/audit.smk").read_text()
    assert "results=lambda wc, output: os.path.dirname(os.path.dirname(output[0]))" in rules.split("rule audit_completion:")[1]


def _planned_paths(dry_run_stdout: str) -> list[str]:
    """Every output, log and benchmark file of the jobs a dry run plans."""
    paths = []
    for line in dry_run_stdout.splitlines():
        key, _, rest = line.strip().partition(": ")
        if key in ("output", "log", "benchmark"):
            paths += [p.strip() for p in rest.split(",")]
    return paths


def _planned_jobs(dry_run_stdout: str) -> list[dict]:
    """The jobs a dry run plans: ``rule`` and the lines under it (``input``, ``output``, ...,
    ``resources``) as they read."""
    jobs = []
    for line in dry_run_stdout.splitlines():
        words = line.split()
        if len(words) == 2 and words[0] in ("rule", "localrule", "checkpoint") and words[1].endswith(":"):
            jobs.append({"rule": words[1][:-1]})
        elif jobs and line.startswith("    ") and ": " in line:
            key, _, rest = line.strip().partition(": ")
            jobs[-1].setdefault(key, rest)
    return jobs


@pytest.fixture(scope="module")
def dry_run(tmp_path_factory):
    """``snakemake -n ARGS`` (its CompletedProcess) in one scratch copy of the workflow, each plan
    made once for the module's tests that read it: the profiles' ``all`` and the paper profile's
    plan of the Pillow on one card are read by several tests, and each Snakemake start costs a
    few CPU seconds, a plan read again none. ``dry_run.work``: the scratch copy."""
    work = scratch_copy(tmp_path_factory.mktemp("plans"))
    plans = {}

    def plan(*args: str):
        if args not in plans:
            plans[args] = snakemake(work, "-n", *args)
        return plans[args]

    plan.work = work
    return plan


#: the profiles' ``all`` plans (read by several tests): profile -> dry-run arguments
ALL = {profile: ("all", f"--configfile={cfg}")
       for cfg, profile in [("config/config.yaml", "default"), ("config/ci.yaml", "ci"), ("config/paper.yaml", "paper")]}
#: the paper profile's plan of the Pillow's main table on one card (read by several tests)
PAPER_ONE_CARD = ("--configfile=config/paper.yaml", "--resources", "gpu=1", "--", "results/paper/tables/main_pillow.csv")


@pytest.mark.slow
def test_workflow_lints_and_dry_runs_for_all_profiles(dry_run):
    work = dry_run.work
    lint = snakemake(work, "--lint", "--configfile=config/ci.yaml")
    assert lint.returncode == 0 and "good condition" in lint.stdout + lint.stderr, lint.stdout[-3000:]
    planned = {}
    for profile, args in ALL.items():
        out = dry_run(*args)
        assert out.returncode == 0, out.stderr[-3000:]
        # each profile writes only under its own results/ and logs/ folders: the ci command
        # never overwrites the default run's tables, figures or audits
        paths = planned[profile] = _planned_paths(out.stdout)
        assert len(paths) > 100 and f"results/{profile}/tables/main_pillow.csv" in paths
        assert all(p.startswith((f"results/{profile}/", f"logs/{profile}/")) for p in paths), \
            [p for p in paths if not p.startswith((f"results/{profile}/", f"logs/{profile}/"))][:5]
    # the ci profile's `all` plans every configured target split through the whole protocol: its
    # queries and each deployable method's estimate (the shared test run keeps the main split alone)
    diagnostics = yaml.safe_load((work / "config/ci.yaml").read_text())["diagnostics"]
    assert diagnostics["splits_in_all"] and len(diagnostics["splits"]) == 3
    for split in ["main", *diagnostics["splits"]]:
        assert f"results/ci/descriptors/pillow/queries_{split}.csv" in planned["ci"], split
        assert f"results/ci/estimates/pillow/{split}/local_ridge.json" in planned["ci"], split


@pytest.mark.slow
def test_every_rule_is_a_statement(tmp_path):
    # no rule is generated in a loop: --list-rules names exactly the rule/checkpoint statements
    work = scratch_copy(tmp_path)
    files = [work / "Snakefile", *sorted((work / "workflow/rules").glob("*.smk"))]
    statements = [m for f in files for m in re.findall(r"^(?:rule|checkpoint) (\w+):", f.read_text(), flags=re.M)]
    out = snakemake(work, "--list-rules")
    assert out.returncode == 0, out.stderr[-3000:]
    listed = [line.split()[0] for line in out.stdout.splitlines() if line and not line[0].isspace()]
    assert sorted(listed) == sorted(statements) and len(set(statements)) == len(statements)
    assert {"rollout_library", "rollout_eval", "render", "discrepancy_library"} <= set(listed)


def test_every_registered_study_has_a_named_target_and_reaches_all_through_the_registry():
    # a study registers its outputs (register_study, common.smk) beside a named target rule of
    # the same name that makes exactly them; `all` takes the registry's in-all part, naming no
    # study's list itself; and nothing in the main stages' files reads a study's names
    rules = ROOT / "workflow" / "rules"
    texts = {f.name: f.read_text() for f in sorted(rules.glob("*.smk"))}
    registered = [(f, name, outputs) for f, text in texts.items()
                  for name, outputs in re.findall(r'register_study\(\s*"(\w+)",\s*(\w+),', text)]
    assert {name for _, name, _ in registered} >= {"diagnostics", "probe_shifts", "passive_active", "ladder", "cmaes",
                                                   "convergence", "boundaries", "verification", "discrepancy",
                                                   "calibration"}
    for f, name, outputs in registered:
        block = re.search(rf"^rule {name}:\n((?:[ \t]+.*\n|\n)*)", texts[f], flags=re.M)
        assert block is not None, f"{f} registers the study {name} but has no rule {name}"
        assert re.search(rf"^    input:\n        {outputs},\n", block.group(1), flags=re.M), \
            f"rule {name} ({f}) does not make the registered outputs {outputs}"
    snakefile = (ROOT / "Snakefile").read_text()
    all_inputs = re.search(r"^rule all:\n((?:[ \t]+.*\n)*)", snakefile, flags=re.M).group(1)
    assert "studies_in_all()" in all_inputs
    assert not re.search(r"\b[A-Z_]+_IN_ALL\b", all_inputs), all_inputs
    includes = re.findall(r'^include: "workflow/rules/(\w+)\.smk"', snakefile, flags=re.M)
    assert includes[-1] == "audit", "the audits read every study's outputs: their file comes last"
    study_files = {f.removesuffix(".smk") for f, _, _ in registered}
    main = includes[: min(includes.index(f) for f in study_files)]
    assert main == ["common", "assets", "simulate", "describe", "calibrate", "evaluate", "render", "report"]
    own = {f: texts[f + ".smk"] + ((rules / "inputs" / f"{f}.smk").read_text() if (rules / "inputs" / f"{f}.smk").exists()
                                   else "") for f in study_files}
    study_names = {n for f in study_files for n in re.findall(r"^(?:([A-Z][A-Z_]+) = |def (\w+)\()", own[f], flags=re.M)
                   for n in n if n}
    for f in main:
        used = study_names & set(re.findall(r"\b\w+\b", texts[f + ".smk"]))
        assert not used, f"{f}.smk reads {sorted(used)}, defined by a study's file included after it"


def test_config_schema_method_vocabulary_is_the_registry():
    schema = yaml.safe_load((ROOT / "workflow/schemas/config.schema.yaml").read_text())["properties"]
    assert tuple(schema["methods"]["items"]["enum"]) == METHOD_NAMES
    params = schema["method_params"]["properties"]
    assert list(params) == list(METHOD_NAMES)
    for method in METHOD_NAMES:
        assert tuple(params[method].get("properties", {})) == METHOD_OPTIONS[method], method
        assert params[method]["additionalProperties"] is False
    assert list(yaml.safe_load((ROOT / "config/config.yaml").read_text())["methods"]) == list(METHOD_NAMES)


def _minimum(option_schema: dict) -> float:
    numeric = [s for s in option_schema.get("oneOf", [option_schema]) if s.get("type") in ("integer", "number")][0]
    numeric = numeric.get("items", numeric)
    return numeric.get("minimum", numeric.get("exclusiveMinimum"))


@pytest.mark.parametrize(("method", "option", "cls"), [("response_knn", "k", "ResponseKNN"), ("local_ridge", "k", "LocalRidge"),
                                                       ("global_ridge", "alpha", "GlobalRidge"),
                                                       ("local_ridge", "alpha", "LocalRidge")])
def test_config_schema_minimums_are_the_estimators(method, option, cls):
    import knockgs_core.calibration as calibration

    schema = yaml.safe_load((ROOT / "workflow/schemas/config.schema.yaml").read_text())
    low = _minimum(schema["properties"]["method_params"]["properties"][method]["properties"][option])
    estimator = getattr(calibration, cls)
    estimator(**{option: low})  # the schema's minimum is accepted by the code
    with pytest.raises(ValueError):
        estimator(**{option: low - 1 if option == "k" else -1e-9})


@pytest.mark.slow
def test_bad_config_is_a_clear_error(tmp_path):
    (tmp_path / "w").mkdir()
    bad = tmp_path / "bad.yaml"
    bad.write_text((ROOT / "config/ci.yaml").read_text() + "\nunknown_key: 1\n")
    out = snakemake(scratch_copy(tmp_path / "w"), "-n", f"--configfile={bad}", "all")
    assert out.returncode != 0 and "unknown_key" in out.stdout + out.stderr


@pytest.mark.slow
def test_boolean_config_values_are_read_as_yaml_writes_them(tmp_path):
    # --config deterministic=true: Snakemake reads "true" as a string, which the schema's
    # boolean refused; YAML's true and false are now read as booleans, other words still refused
    work = scratch_copy(tmp_path)
    table = "results/ci/tables/main_pillow.csv"
    # a number where the schema allows a number or a word (alpha: a number or cv) is read as one;
    # it rides along with the first boolean (one Snakemake start for both)
    nested = "method_params={local_ridge: {k: 9, alpha: 0.001}}"
    for value, also in (("true", [nested]), ("false", []), ("True", [])):
        out = snakemake(work, "-n", "--configfile=config/ci.yaml", "--config", f"deterministic={value}", *also, "--", table)
        assert out.returncode == 0, (value, also, out.stderr[-2000:])
    bad = snakemake(work, "-n", "--configfile=config/ci.yaml", "--config", "deterministic=maybe", "--", table)
    assert bad.returncode != 0 and "deterministic" in bad.stdout + bad.stderr and "'maybe'" in bad.stdout + bad.stderr
    bad = snakemake(work, "-n", "--configfile=config/ci.yaml", "--config", nested.replace("0.001", "much"), "--", table)
    assert bad.returncode != 0 and "method_params.local_ridge.alpha" in bad.stdout + bad.stderr


def _calls_with(code: str, keyword: str) -> list[tuple[str, list[str]]]:
    """(called name, its keywords as written) of each call in ``code`` (Python) that passes
    ``keyword`` (``name=value`` as written)."""
    out = []
    for node in ast.walk(ast.parse(code)):
        keywords = [ast.unparse(k) for k in node.keywords] if isinstance(node, ast.Call) else []
        if keyword in keywords:
            f = node.func
            out.append((f.attr if isinstance(f, ast.Attribute) else ast.unparse(f), keywords))
    return out


def test_every_simulating_rule_takes_the_reproducible_setting():
    # deterministic (on a GPU: every simulation of the job by fixed-point P2G sums) reaches every
    # rule that simulates: its params carry DETERMINISTIC and its script passes it, as a keyword
    # beside the device, to every call that simulates (no process-wide setting); rules with a
    # device that only render are listed
    render_only = {"render.py", "ladder_observe.py", "calibration_observe.py"}
    renders_stored = {"rollout_video"}  # calls with the device in simulating scripts that only render
    seen = set()
    for f in sorted((ROOT / "workflow/rules").glob("*.smk")):
        text = f.read_text()
        for m in re.finditer(r"^(?:rule|checkpoint) (\w+):\n(.*?)(?=^(?:rule|checkpoint) |\Z)", text, re.S | re.M):
            name, body = m.groups()
            if "device=DEVICE" not in body:
                continue
            script = Path(re.search(r'script:\s*\n\s*"([^"]+)"', body).group(1)).name
            seen.add(script)
            if script in render_only:
                assert "deterministic=" not in body, name
                continue
            assert "deterministic=DETERMINISTIC" in body, f"{f.name}: rule {name} simulates without the setting"
            code = (ROOT / "workflow/scripts" / script).read_text()
            # every call given the job's device simulates, and is given the job's setting beside
            # it, but for those that only render a stored rollout
            calls = [(fn, kw) for fn, kw in _calls_with(code, "device=p.device") if fn not in renders_stored]
            assert calls, f"{script} simulates nothing with the job's device"
            for fn, kw in calls:
                assert "deterministic=p.deterministic" in kw, f"{script}: {fn} drops the setting"
            # and nowhere else: no job-wide setting beside the calls
            assert code.count("deterministic=") == len(calls), f"{script} passes the setting outside its simulations"
    assert {"rollout.py", "convergence.py", "discrepancy_run.py", "verification_fem.py"} <= seen and render_only <= seen


def test_every_folder_output_is_built_in_a_staging_folder():
    # a rule whose output is a folder appears whole or not at all: its script builds the folder
    # under a hidden name and moves it into place at the end (knockgs_core.io.staged_folders), so a job
    # killed at any point (after which Snakemake may have recorded it as finished) leaves no
    # partial folder for a resumed run to trust (test_workflow_faults: SIGKILL-jobs-recorded)
    seen = {}
    for f in sorted((ROOT / "workflow/rules").glob("*.smk")):
        text = f.read_text()
        for m in re.finditer(r"^(?:rule|checkpoint) (\w+):\n(.*?)(?=^(?:rule|checkpoint) |\Z)", text, re.S | re.M):
            name, body = m.groups()
            output = re.search(r"^    output:\n(.*?)(?=^    \w+:|\Z)", body, re.S | re.M)
            if output is None or "directory(" not in output.group(1):
                continue
            script = Path(re.search(r'script:\s*\n\s*"([^"]+)"', body).group(1)).name
            seen[name] = script
            code = (ROOT / "workflow/scripts" / script).read_text()
            assert "staged_folders(" in code, f"{f.name}: rule {name}'s script {script} writes its folder in place"
    assert set(seen.values()) == {"rollout.py", "render.py", "boundaries_rollout.py"}, seen
    # the library, evaluation, diagnostics' set, passive (library, targets), boundary (library,
    # evaluation), discrepancy-library rollouts and the render; the calibration's library,
    # predictions and their render
    assert len(seen) == 12, seen


def _planned(work: Path, *args) -> dict:
    out = snakemake(work, "-n", *args)
    assert out.returncode == 0, out.stderr[-3000:]
    counts = {}
    for line in out.stdout.splitlines():
        parts = line.split()
        if len(parts) == 2 and parts[1].isdigit():
            counts[parts[0]] = int(parts[1])
    return counts


@pytest.mark.slow
def test_library_jobs_split_over_the_cards_the_run_may_hold(dry_run):
    # library_chunk auto: six candidates a job on the CPU; on a GPU the 54 candidates split
    # evenly over --resources gpu (one job an object on one card); a number is taken as given
    table = "results/{}/tables/main_pillow.csv"

    def library_jobs(*args):
        """The Pillow's library jobs in the plan of ``snakemake -n ARGS``."""
        out = dry_run(*args)
        assert out.returncode == 0, out.stderr[-3000:]
        return sum(1 for job in _planned_jobs(out.stdout)
                   if job["rule"] == "rollout_library" and "/rollouts/pillow/lib/chunk" in job["output"])

    def main_table(config, *args):
        profile = {"config": "default"}.get(config, config)
        return library_jobs(f"--configfile=config/{config}.yaml", *args, "--", table.format(profile))

    assert library_jobs(*ALL["default"]) == 9
    assert library_jobs(*PAPER_ONE_CARD) == library_jobs(*ALL["paper"]) == 1
    assert main_table("paper", "--resources", "gpu=4") == 4  # 14, 14, 14, 12
    assert main_table("paper", "--resources", "gpu=1", "--config", "library_chunk=6") == 9
    assert main_table("config", "--config", "library_chunk=54") == 1
    bad = dry_run("--config", "library_chunk=0", "--", table.format("default"))
    assert bad.returncode != 0 and "library_chunk" in bad.stdout + bad.stderr


def _planned_runtimes(out) -> dict:
    """The time limit [min] (``runtime``) of each rule's planned jobs in a dry run (its
    CompletedProcess): rule -> set."""
    assert out.returncode == 0, out.stderr[-3000:]
    runtimes = {}
    for job in _planned_jobs(out.stdout):
        fields = dict(f.strip().split("=", 1) for f in job.get("resources", "").split(",") if "=" in f)
        if "runtime" in fields:
            runtimes.setdefault(job["rule"], set()).add(int(fields["runtime"]))
    return runtimes


@pytest.mark.slow
def test_rollout_jobs_ask_for_the_time_their_device_needs(dry_run):
    # a Slurm job's time limit: an hour a paper-scale rollout on the CPU, 20 minutes at the
    # smaller profiles, a minute a rollout plus ten a job on a GPU (one job of 54 candidates a card)
    gpu = _planned_runtimes(dry_run(*PAPER_ONE_CARD))
    assert gpu["rollout_library"] == {10 + 54}
    assert gpu["rollout_eval"] <= {10 + 2, 10 + 3} and gpu["rollout_eval"]
    cpu = _planned_runtimes(dry_run("--configfile=config/paper.yaml", "--resources", "gpu=1", "--config", "device=cpu",
                                    "--", "results/paper/tables/main_pillow.csv"))
    assert cpu["rollout_library"] == {60 * 6} and cpu["rollout_eval"] <= {60 * 2, 60 * 3}
    default = _planned_runtimes(dry_run(*ALL["default"]))  # every object's library jobs
    assert default["rollout_library"] == {20 * 6}


@pytest.mark.slow
def test_discrepancy_cases_run_at_their_configured_resolution(dry_run):
    # default profile, cases at the ci resolution: their own asset and library, not the profile's
    out = dry_run(*ALL["default"])  # `all` holds the discrepancy table
    assert out.returncode == 0, out.stderr[-3000:]
    jobs = [job for job in _planned_jobs(out.stdout) if job["rule"].startswith("discrepancy_")]
    own = {rule: sum(1 for job in jobs if job["rule"] == rule) for rule in {job["rule"] for job in jobs}}
    assert own.get("discrepancy_asset") == 1 and own.get("discrepancy_library") == 9
    assert own.get("discrepancy_run") == own.get("discrepancy_case") > 0
    # no case, run or library job reads the profile's asset or library rollouts
    read = [p.strip() for job in jobs for p in job.get("input", "").split(",")]
    assert not [p for p in read if p.startswith(("results/default/assets/", "results/default/rollouts/"))], read
    assert "results/default/discrepancy/ci/assets/pillow.particles.npz" in read
    table = "results/default/tables/discrepancy.csv"
    shared = _planned(dry_run.work, "--config", "discrepancy={resolution: default}", "--", table)
    assert "discrepancy_library" not in shared and shared.get("rollout_library") == 9 and shared.get("asset") == 1
    bad = dry_run("--config", "discrepancy={resolution: huge}", "--", table)
    assert bad.returncode != 0 and "huge" in bad.stdout + bad.stderr


@pytest.mark.slow
def test_the_loop_runs_on_the_grid_its_config_names(tmp_path):
    """discrepancy.n_grid: the cases, their asset and library at that grid (the fill refined with
    it), in a folder of their own; the asset job builds the contract at that grid (its hash is
    at_resolution's, which the loop's run checks its particles and library against); a grid the
    contract refuses is one line at config read."""
    work = scratch_copy(tmp_path)
    cfg = ("--configfile=config/ci.yaml", "--config", "objects=[pillow]", "discrepancy={resolution: ci, n_grid: 24}")
    table = f"{CI}/tables/discrepancy.csv"
    plan = _planned(work, *cfg, "--", table)
    assert plan.get("discrepancy_asset") == 1 and plan.get("discrepancy_library") == 9 and "rollout_library" not in plan
    summary = f"{CI}/discrepancy/ci_n24/assets/pillow.summary.json"
    run = snakemake(work, *cfg, "--cores", "1", "--", summary)
    assert run.returncode == 0, run.stderr[-3000:]
    built = json.loads((work / summary).read_text())
    assert built["contract_hash"] == load_contract("pillow", "ci", n_grid=24).hash
    assert built["contract_hash"] != load_contract("pillow", "ci").hash
    bad = snakemake(work, "-n", "--configfile=config/ci.yaml", "--config", "discrepancy={resolution: ci, n_grid: 4}", "--", table)
    lines = [line for line in bad.stderr.splitlines() if line.strip()]
    assert bad.returncode != 0 and "Traceback" not in bad.stderr, bad.stderr[-2000:]
    assert "discrepancy" in lines[-1] and "n_grid" in lines[-1], lines[-1]


@pytest.mark.slow
def test_a_library_without_deformation_gradients_moves_them_to_the_evaluation_job(tmp_path):
    # render.library_deformation_gradients: false (the paper profile's setting): the library
    # writes positions only, and the evaluation job of a theta on a candidate simulates Probe A
    # too, with F, so the renders read positions and F of one run; the ladder, which renders the
    # library, stops with the setting named. Run with deterministic: true, which on the CPU (its
    # rollouts reproducible either way) keeps the scatter: the rollouts say they are not the
    # fixed-point ones
    work = scratch_copy(tmp_path)
    first = load_candidates().iloc[0]
    tag = f"sE{first.E_scale:.6f}_sR{first.density_scale:.6f}"
    cfg = yaml.safe_load((ROOT / "config/ci.yaml").read_text())
    cfg["render"]["library_deformation_gradients"] = False
    (work / "config/ci_no_library_F.yaml").write_text(yaml.safe_dump(cfg))
    flag = ["--configfile=config/ci_no_library_F.yaml", "--config", "objects=[pillow]", "deterministic=true"]
    run = snakemake(work, f"{CI}/rollouts/pillow/lib/chunk0", f"{CI}/rollouts/pillow/eval/{tag}", "--cores", "2", *flag)
    assert run.returncode == 0, run.stderr[-3000:]
    lib = sorted(p.name for p in (work / f"{CI}/rollouts/pillow/lib/chunk0").glob("*.parquet"))
    assert len(lib) == 6 and not any(n.endswith(".F.parquet") for n in lib) and f"{tag}.parquet" in lib
    ev = sorted(p.name for p in (work / f"{CI}/rollouts/pillow/eval/{tag}").glob("*.parquet"))
    probes = ["standard_x", "standard_y", "strong_x"]
    assert ev == sorted([f"{p}.parquet" for p in probes] + [f"{p}.F.parquet" for p in probes]), ev
    # the evaluation job's Probe-A run is the library's, bit for bit (CPU rollouts are deterministic)
    a = pd.read_parquet(work / f"{CI}/rollouts/pillow/lib/chunk0/{tag}.parquet")
    b = pd.read_parquet(work / f"{CI}/rollouts/pillow/eval/{tag}/standard_x.parquet")
    pd.testing.assert_frame_equal(a, b)
    meta = read_rollout(work / f"{CI}/rollouts/pillow/lib/chunk0/{tag}.parquet").meta
    assert meta["device"] == "cpu" and "deterministic" not in meta and "reproducible_sums" not in meta
    ladder = snakemake(work, "-n", f"{CI}/ladder/observations/pillow/lib/chunk0.csv", *flag)
    assert ladder.returncode != 0 and "library_deformation_gradients" in ladder.stdout + ladder.stderr


@pytest.mark.slow
def test_temporary_deformation_gradients_are_removed_once_rendered(tmp_path):
    # render.keep_deformation_gradients: false (the paper profile's setting): the evaluation job
    # writes its F to a folder of its own, which the render reads and the workflow then removes;
    # the positions stay, and the frames equal those rendered from F kept on disk
    work = scratch_copy(tmp_path)
    cfg = yaml.safe_load((ROOT / "config/ci.yaml").read_text())
    cfg["render"]["keep_deformation_gradients"] = False
    (work / "config/ci_temp_F.yaml").write_text(yaml.safe_dump(cfg))
    tag = "sE0.910000_sR1.230000"  # not a candidate: every evaluation probe is simulated here
    probes = ["standard_x", "standard_y", "strong_x"]
    frames = {}
    for name, flag in (("kept", ["--configfile=config/ci.yaml"]), ("temporary", ["--configfile=config/ci_temp_F.yaml"])):
        run = snakemake(work, f"{CI}/frames/pillow/{tag}", "--cores", "2", *flag, "--config", "objects=[pillow]")
        assert run.returncode == 0, run.stderr[-3000:]
        ev = sorted(p.name for p in (work / f"{CI}/rollouts/pillow/eval/{tag}").glob("*.parquet"))
        if name == "kept":
            assert ev == sorted([f"{p}.parquet" for p in probes] + [f"{p}.F.parquet" for p in probes]), ev
            assert not (work / f"{CI}/rollouts/pillow/evalF").exists()
        else:
            assert ev == [f"{p}.parquet" for p in probes], ev
            assert not (work / f"{CI}/rollouts/pillow/evalF/{tag}").exists()  # removed once rendered
            assert "evalF" in run.stderr and "Removing temporary output" in run.stderr
        frames[name] = {p: dict(np.load(work / f"{CI}/frames/pillow/{tag}/{p}.npz")) for p in probes}
        if name == "kept":  # a render failing on its last probe removes the frames it had written
            last_F = work / f"{CI}/rollouts/pillow/eval/{tag}/{probes[-1]}.F.parquet"
            last_F.write_bytes(last_F.read_bytes()[:1000])
            bad = snakemake(work, f"{CI}/frames/pillow/{tag}", "--forcerun", "render", "--cores", "2", *flag,
                            "--config", "objects=[pillow]")
            assert bad.returncode != 0
            assert not (work / f"{CI}/frames/pillow/{tag}").exists()
            job_log = (work / f"logs/ci/frames/pillow/{tag}.log").read_text()
            assert f"{probes[0]}.npz: 31 frames" in job_log and "removed the partial output" in job_log, job_log
        shutil.rmtree(work / f"{CI}/rollouts/pillow/eval/{tag}")
        shutil.rmtree(work / f"{CI}/frames/pillow/{tag}", ignore_errors=True)
    for p in probes:
        assert frames["kept"][p].keys() == frames["temporary"][p].keys()
        for k in frames["kept"][p]:
            np.testing.assert_array_equal(frames["kept"][p][k], frames["temporary"][p][k])


@pytest.mark.slow
def test_evaluation_jobs_write_deformation_gradients_only_for_renders(tmp_path):
    # render.enabled: false: the evaluation job writes positions only (no consumer reads F), and
    # a render or a video route asked for anyway stops with the setting named
    work = scratch_copy(tmp_path)
    cfg = yaml.safe_load((ROOT / "config/ci.yaml").read_text())
    cfg["render"]["enabled"] = False
    (work / "config/ci_no_render.yaml").write_text(yaml.safe_dump(cfg))
    flag = ["--configfile=config/ci_no_render.yaml", "--config", "objects=[pillow]"]
    tag = "sE0.910000_sR1.230000"  # not a candidate: every evaluation probe is simulated here
    run = snakemake(work, f"{CI}/rollouts/pillow/eval/{tag}", "--cores", "2", *flag)
    assert run.returncode == 0, run.stderr[-3000:]
    ev = sorted(p.name for p in (work / f"{CI}/rollouts/pillow/eval/{tag}").glob("*.parquet"))
    assert ev == ["standard_x.parquet", "standard_y.parquet", "strong_x.parquet"], ev
    for target in (f"{CI}/frames/pillow/{tag}", f"{CI}/ladder/observations/pillow/targets_main.csv"):
        out = snakemake(work, "-n", target, *flag)
        assert out.returncode != 0 and "render.enabled is false" in out.stdout + out.stderr, target


@pytest.mark.slow
def test_the_tests_that_read_the_shared_ci_run_are_the_tables_tier_and_only_by_name():
    """``pytest`` leaves out every test that reads the shared ci run (the project's ``-m "not
    tables"``); ``pytest -m tables`` collects them and nothing else. Collection only, no test runs."""
    def collected(*args):
        out = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-n", "0", "-p", "no:cacheprovider",
                              *args, "tests/test_workflow.py", "tests/test_convergence_study.py"],
                             cwd=ROOT, capture_output=True, text=True)
        assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-2000:]
        return {line for line in out.stdout.splitlines() if "::" in line}

    default, tables = collected(), collected("-m", "tables")
    assert "tests/test_workflow.py::test_ci_main_table_end_to_end" in tables
    assert any(t.startswith("tests/test_convergence_study.py::") for t in tables)
    assert not default & tables
    assert default | tables == collected("-m", "tables or not tables")
