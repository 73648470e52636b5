"""A local map's settings: :class:`LocalMapOptions` of the smoothing engine
(:class:`~csam_ros.core.smoothing.local_map.LocalMap`) and :class:`LocalMapConfig`, the
``local_map:`` section of a parameter file that gives them."""

from __future__ import annotations

from dataclasses import dataclass, field

from csam_ros.core.model.config_file import Section, setting
from csam_ros.core.sam.factors import ROBUST_KERNELS, RobustKernel, robust_kernel
from csam_ros.core.sam.solver import GAUGE_SIGMA, SolverOptions


@dataclass
class LocalMapOptions:
    """Settings of a local map."""

    key_interval: float | None = 1.0  # regular key poses every this many seconds; None: off
    stamp_tolerance: float = 1e-6  # stamps closer than this share a key pose
    gauge_sigma: float = GAUGE_SIGMA
    robust: RobustKernel | None = None  # kernel on feature observations (real data)
    update_period: float = 1.0  # maybe_update(): seconds of new odometry between solves
    solver: SolverOptions = field(default_factory=SolverOptions)  # converged solves
    online_solver: SolverOptions = field(  # every other update: warm-started, capped
        default_factory=lambda: SolverOptions(relative_tolerance=1e-6, max_iterations=10)
    )
    odometry_calibration: bool = False  # unknowns (s, k_d, k_s) scaling the odometry
    driving_speed: float = 0.02  # m/s: |v| above it turns with k_d, else k_s
    calibration_sigmas: tuple[float, float, float] = (0.1, 0.5, 0.1)  # prior at (1, 1, 1)
    calibration_relinearise: float = 1e-4  # recompose the odometry when c moved this much
    fold_recovery: bool = False  # a map failing its check distrusts the odometry it refutes


SMOOTHER = "smoother"  # the node that takes LocalMapConfig fields as parameters
_NON_NEGATIVE = {"minimum": 0.0, "node": SMOOTHER}


@dataclass
class LocalMapConfig(Section):
    """The ``local_map:`` section of a parameter file; the smoother node's parameters of the
    same names (``batch_window`` is for offline builds only, ``publish_period`` for nodes)."""

    section = "local_map"

    key_interval: float = setting(1.0, "s between regular key poses (0: off)", **_NON_NEGATIVE)
    robust_kernel: str = setting(
        "",
        "kernel on feature observations ('': none)",
        choices=("", *ROBUST_KERNELS),
        node=SMOOTHER,
    )
    robust_threshold: float = setting(
        0.0,
        "the kernel's threshold or scale, whitened (0: its default)",
        **_NON_NEGATIVE,
    )
    batch_window: float = setting(
        60.0, "offline: s of odometry per warm-started solve (0: one batch)", minimum=0.0
    )
    publish_period: float = setting(
        1.0,
        "s (node clock) between a smoother's updates when data arrived",
        minimum=0.0,
        exclusive=True,
        node=SMOOTHER,
    )

    # SolverOptions.max_step_scale of the converged solves (a smoother's ~/flush, the end of
    # an offline build), not of the online updates (MR.CLAM: another minimum of the robust cost)
    converged_step_scale: float = setting(
        1.0,
        "converged solves: stretch a robust (reweighted) step by up to this factor while the "
        "cost falls (1: off)",
        minimum=1.0,
        node=SMOOTHER,
    )

    # SolverOptions.cost_tolerance of the same converged solves: along the flat directions of a
    # redescending kernel the cost creeps a fraction of a unit per step for tens of steps
    converged_cost_tolerance: float = setting(
        0.0,
        "converged solves: stop at a step that lowers the cost by less than this (a step under "
        "one standard deviation: 0.5; 0: off)",
        **_NON_NEGATIVE,
    )

    update_tolerance_m: float = setting(
        0.02,
        "m a pose moves before a smoother sends it again (0: every change)",
        **_NON_NEGATIVE,
    )
    update_tolerance_rad: float = setting(
        0.02,
        "rad a pose turns before a smoother sends it again (0: every change)",
        **_NON_NEGATIVE,
    )
    update_key_tolerance: float = setting(
        1e-3,
        "m (and rad) a feature or rendezvous pose moves before a smoother sends it again",
        **_NON_NEGATIVE,
    )

    odometry_calibration: bool = setting(
        False,
        "estimate per robot the odometry's distance scale and turn-rate scales while driving "
        "and on the spot (docs/METHOD.md, calibrating the odometry)",
        node=SMOOTHER,
    )
    driving_speed: float = setting(
        0.02, "m/s: odometry faster than this turns with the driving scale", **_NON_NEGATIVE
    )
    calibration_sigma_distance: float = setting(
        0.1, "prior sigma of the distance scale (at 1)", minimum=0.0, exclusive=True, node=SMOOTHER
    )
    calibration_sigma_turn: float = setting(
        0.5,
        "prior sigma of the turn-rate scale while driving (at 1)",
        minimum=0.0,
        exclusive=True,
        node=SMOOTHER,
    )
    # MR.CLAM's robots seldom turn in place; with 0.5 the on-the-spot scale wandered to
    # 0.69 on Dataset 2's robot 2 (8 Hz commands) and took its map from 0.076 to 0.105 m
    calibration_sigma_turn_spot: float = setting(
        0.1,
        "prior sigma of the turn-rate scale on the spot (at 1)",
        minimum=0.0,
        exclusive=True,
        node=SMOOTHER,
    )

    fold_recovery: bool = setting(
        False,
        "a local map that fails its consistency check finds the odometry it refutes and "
        "solves again with it distrusted (docs/METHOD.md, a fold cannot persist)",
        node=SMOOTHER,
    )

    def options(self) -> LocalMapOptions:
        return LocalMapOptions(
            key_interval=self.key_interval or None,
            robust=robust_kernel(self.robust_kernel, self.robust_threshold),
            solver=SolverOptions(
                max_step_scale=self.converged_step_scale,
                cost_tolerance=self.converged_cost_tolerance,
            ),
            odometry_calibration=self.odometry_calibration,
            fold_recovery=self.fold_recovery,
            driving_speed=self.driving_speed,
            calibration_sigmas=(
                self.calibration_sigma_distance,
                self.calibration_sigma_turn,
                self.calibration_sigma_turn_spot,
            ),
        )

    @property
    def window(self) -> float | None:
        """``build_local_map``'s window."""
        return self.batch_window or None
