"""The settings of C-SAM (:class:`CsamConfig`, the ``csam:`` section of a scenario or parameter
file) and the options of each step derived from them (docs/METHOD.md sections 5-6)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from csam_ros.core.joining.alignment import AlignmentOptions
from csam_ros.core.joining.consistency import ConsistencyOptions
from csam_ros.core.joining.rendezvous_filters import RendezvousThinning
from csam_ros.core.model.chi_square import CHI2_2DOF_99
from csam_ros.core.model.config_file import Section, load_document, setting
from csam_ros.core.sam.solver import SolverOptions
from csam_ros.core.smoothing.local_map_config import SMOOTHER

MERGER = "merger"  # the node that takes most CsamConfig fields as parameters
_POSITIVE = {"minimum": 0.0, "exclusive": True, "node": MERGER}


@dataclass
class CsamConfig(Section):
    """Parameters of C-SAM (the ``csam:`` section of a scenario or merger parameter file).

    The merger takes each field as a ROS parameter, but the rendezvous thinning, which decides
    where the local maps hold poses and so belongs to the smoothers (online) and
    :func:`~csam_ros.core.joining.pipeline.run_csam` (offline)."""

    section = "csam"

    chi2_gate: float = setting(
        CHI2_2DOF_99, "association gate on the Mahalanobis distance (2 dof)", **_POSITIVE
    )
    max_heading_sigma_deg: float = setting(
        5.0, "deg: a robot stays pending if the rendezvous fix its heading worse", **_POSITIVE
    )
    mutual_time_tolerance: float = setting(
        1e-3, "s: two measurements this close are mutual", **_POSITIVE
    )
    stamp_tolerance: float = setting(
        1e-6, "s: matching rendezvous stamps to local-map poses", **_POSITIVE
    )
    skip_missing_poses: bool = setting(
        False, "leave out rendezvous measurements without a local-map pose", node=MERGER
    )
    alignment_method: str = setting(
        "auto",
        "Algorithm 1's solver and with it Algorithm 2's conditioning: 'auto' (sparse), "
        "'dense-newton' (both dense: the tests' oracle, small teams only)",
        choices=("auto", "dense-newton"),
        node=MERGER,
    )
    max_iterations: int = setting(
        100, "iterations of Algorithm 1 and of the joint solve", **_POSITIVE
    )
    step_tolerance: float = setting(
        1e-9, "m, rad: stop when the largest step component is below", **_POSITIVE
    )
    # MR.CLAM's robust joint costs creep at 1e-11-1e-12 per iteration long after the map
    # settled: Dataset 2 took 103 iterations to 1e-12 (20 of them below 1e-10), so the cap of
    # 100 left it unconverged; features move < 1e-6 m over that creep
    relative_tolerance: float = setting(
        1e-10, "stop when the relative cost decrease is below", **_POSITIVE
    )
    # SolverOptions.max_step_scale; MR.CLAM: 100+ -> 68 iterations
    max_step_scale: float = setting(
        64.0,
        "joint solve: stretch a robust (reweighted) step by up to this factor while the cost "
        "falls (1: off)",
        minimum=1.0,
        node=MERGER,
    )
    associate: bool = setting(True, "false: join through rendezvous rows only", node=MERGER)
    # measured (python -m csam_ros.bench.merger_replay): no fewer iterations on simulated runs,
    # where a cold solve is the offline one; on MR.CLAM fewer, in other minima of the robust
    # cost within the poses' uncertainty (on in config/mrclam.yaml)
    warm_start: bool = setting(
        False, "start each live solve from the previous one (docs/METHOD.md 6.4)", node=MERGER
    )
    # rendezvous filters for real data (csam_ros.core.joining.rendezvous_filters; defaults keep
    # everything)
    rendezvous_min_interval: float = setting(
        0.0, "s between kept rendezvous of one ordered robot pair", minimum=0.0, node=SMOOTHER
    )
    rendezvous_max_per_pair: int = setting(
        0,
        "rendezvous kept per ordered robot pair, spread over time (0: no cap)",
        minimum=0,
        node=SMOOTHER,
    )
    rendezvous_consistency: bool = setting(
        False, "RANSAC check of rendezvous against the local maps", node=MERGER
    )
    consistency_drift: float = setting(
        0.3, "m allowed for local-map errors in that check", **_POSITIVE
    )
    # a local map's own residuals (csam_ros.core.joining.consistency; docs/METHOD.md 6.5)
    check_local_maps: bool = setting(
        True, "check each local map against its own measurements before joining", node=MERGER
    )
    max_trajectory_outliers: float = setting(
        0.02,
        "share of a map's factors between poses beyond the 99.9 % gate above which the robot "
        "stays pending",
        minimum=0.0,
        node=MERGER,
    )
    max_observation_outliers: float = setting(
        0.3,
        "share of a map's observations beyond the gate above which the robot stays pending",
        minimum=0.0,
        node=MERGER,
    )
    max_feature_outliers: float = setting(
        0.3,
        "share of one feature's observations beyond the gate above which it is not associated",
        minimum=0.0,
        node=MERGER,
    )

    @classmethod
    def from_file(cls, name_or_path: str | Path) -> CsamConfig:
        """The ``csam:`` section of a scenario or parameter file (defaults when absent)."""
        return cls.from_dict(load_document(name_or_path).get("csam"), f"{name_or_path}: csam")

    def thinning(self) -> RendezvousThinning:
        """The streaming rendezvous thinning these settings describe."""
        return RendezvousThinning(
            self.rendezvous_min_interval, self.rendezvous_max_per_pair or None
        )

    def alignment_options(self) -> AlignmentOptions:
        """The options of Algorithm 1 (docs/METHOD.md section 5)."""
        return AlignmentOptions(
            max_heading_sigma=float(np.deg2rad(self.max_heading_sigma_deg)),
            mutual_time_tolerance=self.mutual_time_tolerance,
            max_iterations=self.max_iterations,
            step_tolerance=self.step_tolerance,
            relative_tolerance=self.relative_tolerance,
            method=self.alignment_method,
        )

    def consistency_options(self) -> ConsistencyOptions:
        """The options of the local-map check (docs/METHOD.md section 6.5)."""
        return ConsistencyOptions(
            max_trajectory_outliers=self.max_trajectory_outliers,
            max_observation_outliers=self.max_observation_outliers,
            max_feature_outliers=self.max_feature_outliers,
        )

    def solver_options(self) -> SolverOptions:
        """The options of the joint solve (docs/METHOD.md section 6.2)."""
        return SolverOptions(
            max_iterations=self.max_iterations,
            relative_tolerance=self.relative_tolerance,
            step_tolerance=self.step_tolerance,
            max_step_scale=self.max_step_scale,
        )
