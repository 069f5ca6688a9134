"""The measured Probe-A observation: its descriptor (the query, no label) and how it was
observed (tracks, the tracked curve, the camera the library is to be seen by)."""
import sys
from dataclasses import asdict

import pandas as pd

from knockgs_core.contract import load_contract
from knockgs_core.descriptors import FEATURE_NAMES
from knockgs_core.experiments import ObservationSettings, camera_from_dict, camera_to_dict, measured_observation
from knockgs_core.io import write_json, write_text

sys.stderr = open(snakemake.log[0], "w")
p = snakemake.params
contract = load_contract(p.contract, p.profile)
settings = ObservationSettings(**p.observation)
probe = contract.probes[contract.roles["calibration"]]
phi, curve, info, camera = measured_observation(snakemake.input.measurement, settings, probe)
# tracked points bring no camera: the library is seen by the contract's (params.camera, as is an RGB-D file's)
camera = camera_from_dict(p.camera) if camera is None else camera
write_json(snakemake.output.info, {"measurement": snakemake.input.measurement, "probe": probe.name, **info,
                                   "curve": curve.tolist(), "tracker": asdict(settings.tracker()),
                                   "camera": camera_to_dict(camera)}, indent=1)
row = pd.DataFrame([{"case_name": "measurement", **dict(zip(FEATURE_NAMES, phi))}])
write_text(snakemake.output.query, row.to_csv(index=False, float_format="%.10g", lineterminator="\n"))
print(f"{snakemake.input.measurement}: {info}", file=sys.stderr)
