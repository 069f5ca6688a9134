"""Run one audit; write its verdict; fail the job (and so the run) if it did not pass."""
import json
import sys
from pathlib import Path

from knockgs_core import audits
from knockgs_core.io import check_job_inputs, write_text
from knockgs_core.contract import load_candidates, load_targets

sys.stderr = open(snakemake.log[0], "w")
check_job_inputs(snakemake)  # before any work: no file removed from an input folder since its job ended
name = snakemake.rule.removeprefix("audit_")
p = snakemake.params
if name == "leakage":
    verdict = audits.audit_leakage(snakemake.input.estimates, calibration_probes=p.calibration, candidates=load_candidates(),
                                   targets=load_targets(p.split), library_rollouts=p.library,
                                   sensitivity_grids=snakemake.input.sensitivity, frozen=p.frozen,
                                   passive_library_rollouts=p.passive_library)
elif name == "nonfinite":
    verdict = audits.audit_nonfinite(p.rollout_dirs, snakemake.input.tables, workers=snakemake.threads)
elif name == "missing_frames":
    verdict = audits.audit_missing_frames(p.rollout_dirs, workers=snakemake.threads)
elif name == "rollout_metadata":
    objects = audits.rollout_expectations(p.objects, p.profile, p.rollout_dirs, snakemake.input.particles)
    verdict = audits.audit_rollout_metadata(objects)
elif name == "duplicates":
    verdict = audits.audit_duplicates(load_candidates(), load_targets(p.split), snakemake.input.libraries)
elif name == "completion":
    verdict = audits.audit_completion(p.expected, p.mains, p.methods, results=p.results)
    for warning in verdict["warnings"]:  # in the job's log, and on the console of the run
        for out in (sys.stderr, sys.__stderr__):
            print(f"warning: audit completion: {warning}", file=out, flush=True)
else:
    raise SystemExit(f"unknown audit {name}")
verdict["audit"] = name
text = json.dumps(verdict, indent=1)
write_text(snakemake.output[0], text)
if not verdict["passed"]:
    failed = Path(snakemake.log[0]).with_suffix(".failed.json")
    write_text(failed, text)
    print(text, file=sys.stderr)
    raise SystemExit(f"audit {name} failed: {verdict['problems'][:5]} (verdict in {failed})")
