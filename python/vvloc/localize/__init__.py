"""Localization against a map: map database, localizer, loop closures and exports.

:mod:`vvloc.localize.mapdb` stores keyframes (poses, descriptors, BEVs) in one HDF5 file;
:mod:`vvloc.localize.export` writes loop closures (CSV, g2o) and trajectories (TUM);
:mod:`vvloc.localize.metric` runs metric localization (translation search + exact yaw);
:mod:`vvloc.localize.calibrate` measures on held-out sessions when a localization is accepted.
"""

from vvloc.localize.export import (
    G2OGraph,
    KeyframeTable,
    LoopClosures,
    information_from_sigmas,
    read_g2o,
    read_keyframe_csv,
    read_loop_csv,
    read_tum,
    write_g2o,
    write_loop_csv,
    write_tum,
)
from vvloc.localize.mapdb import (
    FORMAT_VERSION,
    MapDatabase,
    MapError,
    MapMetadata,
    MapWriter,
    model_config_hash,
)
from vvloc.localize.metric import MetricResult, SearchConfig, metric_localize

__all__ = [
    "FORMAT_VERSION",
    "G2OGraph",
    "KeyframeTable",
    "LoopClosures",
    "MapDatabase",
    "MapError",
    "MapMetadata",
    "MapWriter",
    "MetricResult",
    "SearchConfig",
    "information_from_sigmas",
    "metric_localize",
    "model_config_hash",
    "read_g2o",
    "read_keyframe_csv",
    "read_loop_csv",
    "read_tum",
    "write_g2o",
    "write_loop_csv",
    "write_tum",
]
