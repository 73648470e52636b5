"""What C-SAM derives from each local map alone (docs/METHOD.md sections 4.5, 5, 6.1 and 6.4).

A :class:`LocalFactor` holds a local map's factorisation at its estimate and, on first use, its
local marginals; a :class:`LocalView` adds, on that factor, its rendezvous part (the marginal
square-root information of its rendezvous poses, which Algorithm 1 takes) and the cross covariance
``P_l,rho`` of its features with those poses (which association takes). :class:`LocalViewCache`
keeps them per robot while the map (and, for a view, its rendezvous poses) stay the same, as a live
merger joins again and again; it computes a factor ahead of the join when the map arrives
(:meth:`LocalViewCache.prepare`).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import cached_property
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray

from csam_ros.core.joining.alignment import RendezvousPart
from csam_ros.core.joining.association import MapFeatures
from csam_ros.core.joining.consistency import ConsistencyOptions, check_local_map
from csam_ros.core.joining.result import LocalMapCheck
from csam_ros.core.sam.covariance import (
    covariance_by_elimination,
    covariance_columns,
    factorize_at_estimate,
    upper_sqrt_information,
)
from csam_ros.core.sam.normal_equations import NormalEquations
from csam_ros.core.sam.selected_inverse import SelectedInverse
from csam_ros.core.smoothing.robot_map import RobotMap

Array = NDArray[np.float64]
T = TypeVar("T")
U = TypeVar("U")


@dataclass
class LocalFactor:
    """A local map's factorisation at its estimate and, on first use, its marginals from the
    factor's selected inverse: what a join derives from the map alone, whatever its
    rendezvous poses."""

    robot_map: RobotMap
    system: NormalEquations  # factorised at the map's estimate

    @cached_property
    def inverse(self) -> SelectedInverse:
        """The selected inverse of the map's factor, whence its marginals."""
        return SelectedInverse(self.system)

    @cached_property
    def sigma_phi(self) -> Array:
        """(N,) marginal heading sigmas of the poses."""
        headings = self.robot_map.problem.scalar_indices(self.robot_map.pose_ids)[2::3]
        return np.sqrt(np.maximum(self.inverse.entries(headings, headings), 0.0))

    @cached_property
    def feature_covariances(self) -> Array:
        """(F, 2, 2) marginal covariances of the features."""
        m = self.robot_map
        if len(m.feature_ids) == 0:
            return np.zeros((0, 2, 2))
        return self.inverse.blocks(m.problem, m.feature_ids)

    def with_marginals(self) -> LocalFactor:
        """This factor with its marginals computed (cached properties)."""
        self.sigma_phi, self.feature_covariances  # noqa: B018
        return self


def local_factor(m: RobotMap) -> LocalFactor:
    """The :class:`LocalFactor` of ``m`` (its marginals computed on first use)."""
    return LocalFactor(m, factorize_at_estimate(m.problem))


@dataclass
class LocalView:
    """What a join derives from one local map alone, for its given rendezvous poses: the
    marginal square-root information of those poses (``part``) and the cross covariance
    ``P_l,rho`` (F, 2, k) of the features with them (``cross``), from the map's
    :class:`LocalFactor`, which holds its marginals."""

    factor: LocalFactor
    rendezvous_poses: NDArray[np.int64]
    part: RendezvousPart | None  # None without rendezvous poses
    cross: Array | None


def local_view(
    m: RobotMap, rendezvous_poses: NDArray[np.int64], factor: LocalFactor | None = None
) -> LocalView:
    """The :class:`LocalView` of ``m`` for ``rendezvous_poses`` (on ``factor``, ``m``'s, when
    given; else a new one): the rendezvous part and
    ``P_l,rho`` both come from the covariance of the features and those poses. With no more
    feature than pose scalars (the dense work then a few times that of the rendezvous part
    itself), it is their joint covariance with the other poses eliminated along the
    trajectory (:func:`covariance_by_elimination`); otherwise, or where a map's other factors
    make that no band, the covariance columns of the poses (:func:`covariance_columns`)."""
    problem = m.problem
    factor = factor or local_factor(m)
    system = factor.system
    if len(rendezvous_poses) == 0:
        return LocalView(factor, rendezvous_poses, None, None)
    pose_columns = problem.scalar_indices(m.pose_ids[rendezvous_poses])
    selected = np.r_[pose_columns, problem.scalar_indices(m.feature_ids)]
    k = len(pose_columns)
    covariance = (
        covariance_by_elimination(system, selected, _other_scalars(m, selected))
        if len(selected) <= 2 * k
        else None
    )
    columns = (
        covariance_columns(system, pose_columns, selected)
        if covariance is None
        else covariance[:, :k]
    )
    block = columns[:k]
    root = upper_sqrt_information(0.5 * (block + block.T))
    part = RendezvousPart(rendezvous_poses, m.poses[rendezvous_poses], root)
    cross = columns[k:].reshape(len(m.feature_ids), 2, k)
    return LocalView(factor, rendezvous_poses, part, cross)


def _other_scalars(m: RobotMap, selected: NDArray[np.int64]) -> NDArray[np.int64]:
    """Every scalar of ``m``'s problem not ``selected``: its poses' in stamp order, then any
    other."""
    problem = m.problem
    poses = problem.scalar_indices(m.pose_ids)
    order = np.r_[poses, np.setdiff1d(np.arange(problem.dim), poses)]
    outside = np.ones(problem.dim, dtype=bool)
    outside[selected] = False
    return order[outside[order]]


def in_threads(function: Callable[[T], U], items: Sequence[T]) -> list[U]:
    """``[function(x) for x in items]`` in threads, one per core (for work that releases the
    interpreter lock: sparse factorisations and solves, LAPACK)."""
    workers = min(len(items), os.cpu_count() or 1)
    if workers < 2:
        return [function(x) for x in items]
    with ThreadPoolExecutor(workers, thread_name_prefix="csam") as pool:
        return list(pool.map(function, items))


class LocalViewCache:
    """:class:`LocalView` per robot, kept while its map is the same object and its rendezvous
    poses the same, and :class:`LocalFactor` per robot, kept while its map is the same object
    (a live merger replaces a map when a new one arrives, never changes it)."""

    def __init__(self) -> None:
        self._views: dict[str, LocalView] = {}
        self._factors: dict[str, LocalFactor] = {}
        self._checks: dict[str, tuple[RobotMap, ConsistencyOptions, LocalMapCheck]] = {}
        self.reused = 0
        self.built = 0

    def check(self, m: RobotMap, options: ConsistencyOptions) -> LocalMapCheck:
        """:func:`~csam_ros.core.joining.consistency.check_local_map` of ``m``, kept while ``m`` is
        the same object."""
        kept = self._checks.get(m.name)
        if kept is not None and kept[0] is m and kept[1] == options:
            return kept[2]
        check = check_local_map(m, options)
        self._checks[m.name] = (m, options, check)
        return check

    def factor(self, m: RobotMap) -> LocalFactor:
        """The cached :class:`LocalFactor` of ``m`` if it is of ``m`` itself, else a new one
        (then cached)."""
        kept = self._factors.get(m.name)
        if kept is not None and kept.robot_map is m:
            return kept
        self._factors[m.name] = factor = local_factor(m)
        return factor

    def prepare(self, maps: Sequence[RobotMap]) -> None:
        """Compute now, in threads, what later joins derive from each of ``maps`` alone
        whatever the rendezvous: its :class:`LocalFactor` with its marginals (a live merger
        prepares a map when it arrives, before the join that takes it)."""
        in_threads(lambda m: self.factor(m).with_marginals(), maps)

    def view(self, m: RobotMap, rendezvous_poses: NDArray[np.int64]) -> LocalView:
        """The cached view of ``m`` if it is still valid, else a new one (then cached)."""
        return self.views([m], [rendezvous_poses])[0]

    def views(
        self, maps: Sequence[RobotMap], rendezvous_poses: Sequence[NDArray[np.int64]]
    ) -> list[LocalView]:
        """:meth:`view` of each map; the new ones built in threads, one per core: their
        factorisations and solves release the interpreter lock."""
        out: list[LocalView | None] = []
        for m, poses in zip(maps, rendezvous_poses, strict=True):
            view = self._views.get(m.name)
            valid = (
                view is not None
                and view.factor.robot_map is m
                and np.array_equal(view.rendezvous_poses, poses)
            )
            out.append(view if valid else None)
        todo = [i for i, view in enumerate(out) if view is None]
        self.reused += len(out) - len(todo)
        self.built += len(todo)

        def build(i: int) -> LocalView:
            return local_view(maps[i], rendezvous_poses[i], self.factor(maps[i]))

        for i, view in zip(todo, in_threads(build, todo), strict=True):
            out[i] = self._views[maps[i].name] = view
        return [view for view in out if view is not None]


def map_features(m: RobotMap, view: LocalView, left_out: Sequence[int] = ()) -> MapFeatures | None:
    """A robot's features with their rendezvous gains ``K = P_l,rho P_rho,rho^-1`` and
    marginal covariances (the map's own when it carries them, else its view's), as
    association takes them; without the labels ``left_out``."""
    part, cross = view.part, view.cross
    if part is None or cross is None or len(m.feature_ids) == 0:
        return None
    root = part.sqrt_information
    gain = cross @ (root.T @ root)
    if m.feature_covariances is not None:
        covs = np.asarray(m.feature_covariances, dtype=float)
    else:
        covs = view.factor.feature_covariances
    keep = ~np.isin(m.feature_labels, left_out)
    return MapFeatures(m.feature_labels[keep], m.feature_positions[keep], covs[keep], gain[keep])
