"""Probe-A response descriptors: five numbers from an exported particle rollout (SPEC §5)."""

from ._descriptor import (
    FEATURE_NAMES,
    curve_descriptor,
    descriptor,
    descriptor_from_rollout,
    descriptor_table,
    read_positions,
    rms_curves,
)

__all__ = [
    "FEATURE_NAMES",
    "rms_curves",
    "descriptor",
    "curve_descriptor",
    "read_positions",
    "descriptor_from_rollout",
    "descriptor_table",
]
