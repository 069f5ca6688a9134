"""MPM rollouts of one job: (theta, probe) runs of one object -> one Parquet file each in the
job's output folder (+ deformation gradients). The contract, particles and Warp kernels are
loaded once. With an input ``protocol`` (a passive protocol's JSON), every run is under that
protocol instead of a contract probe."""
import contextlib
import json
import sys
from pathlib import Path

from knockgs_core.io import StagedFolders, check_files_in, staged_folders
from knockgs_core.assets import load_particles
from knockgs_core.contract import load_contract
from knockgs_core.rollout import BackgroundWriter, batches, run_rollouts

log = open(snakemake.log[0], "w")
sys.stderr = log
p = snakemake.params
# a job writes a folder of rollouts, or a single rollout (output "rollout")
folder = Path(snakemake.output.folder) if "folder" in snakemake.output.keys() else Path(snakemake.output.rollout).parent
# the deformation gradients: in the same folder, or in a folder of their own (output "F_folder")
F_folder = Path(snakemake.output.F_folder) if "F_folder" in snakemake.output.keys() else folder
check_files_in([run["rollout"] for run in p.runs], [folder], source="rollout job")
check_files_in([run["F"] for run in p.runs], [F_folder], source="rollout job")
contract = load_contract(p.object, p.profile, n_grid=getattr(p, "n_grid", None))
particles = load_particles(snakemake.input.particles)
passive = None
if "protocol" in snakemake.input.keys():
    from knockgs_core.experiments import PassiveProtocol  # the studies' package: only a passive job pays its import

    with open(snakemake.input.protocol) as fh:
        passive = PassiveProtocol.from_dict(json.load(fh), snakemake.input.protocol)


def schedule(run):
    """Runs simulated together must share the export schedule and whether F is exported."""
    export = passive.probe().export if passive is not None else contract.probes[run["probe"]].export
    return (export.frame_dt, export.n_frames, run["F"] is not None)


# On a GPU the runs of one schedule are simulated together, each on its own CUDA stream
# (P2G's atomics on separate grids overlap); on the CPU one after the other (the results are
# the same bit for bit either way). Each rollout's files are written while it is simulated,
# frame by frame on threads of their own (a stream per rollout), so that once a batch ends
# only its last frames and the files' footers are left to write.
groups = batches(p.runs, schedule, together=p.device.startswith("cuda"))
extra = {} if passive is None else passive.run_kwargs()


# A job's output folders are built under hidden names and moved into place once every file
# is written (staged_folders): a job stopped at any point, by an exception, Ctrl-C, a batch
# system's SIGTERM or a SIGKILL, leaves no folder, so a resumed run simulates it again
# instead of taking a partial folder. The writer removes the staging folders of a failed
# block once its writes have stopped. A single rollout file is written atomically.
single = "folder" not in snakemake.output.keys()
if single:
    folder.mkdir(parents=True, exist_ok=True)
staging = (contextlib.nullcontext(StagedFolders([folder, F_folder], [folder, F_folder])) if single else
           staged_folders(folder, F_folder, log=log))
with staging as stages, BackgroundWriter(output=[Path(snakemake.output.rollout)] if single else
                                         sorted(set(stages))) as writer:
    for group in groups:
        tags = [f"[{i + 1}/{len(p.runs)}] theta ({run['theta'][0]:.6f}, {run['theta'][1]:.6f}) probe {run['probe']}"
                for i, run in group]

        def progress(k, frame, n_frames, stats, tags=tags):
            if frame % 5 == 0 or frame == n_frames - 1:
                print(f"{tags[k]}: frame {frame}/{n_frames - 1} cfl {stats['cfl']:.3g}", file=log, flush=True)

        streams = [writer.stream(stages.path(run["rollout"]), stages.path(run["F"])) for _, run in group]
        rollouts = run_rollouts(contract, [(run["theta"], run["probe"]) for _, run in group], particles=particles,
                                device=p.device, deterministic=p.deterministic, export_F=group[0][1]["F"] is not None,
                                progress=progress, streams=streams, **extra)
        for tag, (_, run), ro in zip(tags, group, rollouts):
            print(f"{tag}: done on {ro.meta['device']}, {ro.meta['stats']['steps']} substeps, {ro.meta['wall_seconds']:.2f} s"
                  f"{' (the batch of %d)' % len(group) if len(group) > 1 else ''}", file=log, flush=True)
