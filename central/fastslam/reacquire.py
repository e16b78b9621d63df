"""Re-acquisition: a robot that has been blind too long is put back on the map by one rigid correction.

Why. With unknown association, a robot that sees no landmark for a while (MR.CLAM: half a minute of turning
with the camera on empty floor) comes back with a pose error its particles do not cover: the other robots'
scans resample the shared particles, so its position spread collapses to a centimetre. The gate then pairs its
first detection with whichever mapped landmark lies nearest the dead-reckoned prediction (on MR.CLAM often the
neighbouring cluster, a metre away), and the FastSLAM 2.0 proposal, which cannot move a robot whose position
is that certain, turns it by 20–60° instead. The robot then maps its own rotated copy of the landmarks and
drags the robots that see it along.

What. Each robot carries the covariance of its dead reckoning (``drift``): the odometry's own covariance
propagated along the path, plus the heading variance per radian turned that the robot announces
(``RobotInfo.turn_slip_var``, wheel slip), conditioned at each match on the matched detections
(:func:`condition`: one landmark leaves the turn about it free, so that part of the drift stays). Once the
drift's heading σ exceeds ``reacquire_heading_sd`` or its position σ ``reacquire_position_sd``, the robot's
scans are no longer associated one at a time: their detections are kept, as points placed from the robot's dead-reckoned mean
pose, over the last ``reacquire_window_s``. Every ``reacquire_every_s`` a search over rigid corrections — a
turn about the robot's position, then a shift, both within 3σ of the drift and at most
``reacquire_max_turn`` / ``reacquire_max_shift_m`` — lets every (point, confirmed landmark) pair vote for the
shift that joins them (a Hough transform), and scores the best shifts of each turn by the detections they
bring within ``reacquire_inlier_m`` of a confirmed landmark. The best correction is taken when it brings at
least ``reacquire_min_detections``, reaching landmarks at least ``reacquire_span_m`` apart (one landmark
leaves the turn free), and no distinct correction comes within ``reacquire_margin`` detections of it. The
robot's particles are moved by it, its drift starts again from zero and the scan is associated as usual.
Failing that rule, a correction within ``reacquire_confirm_sigmas`` of the drift (capped) that explains as many
detections as any is taken too (:func:`confirm`): on MR.CLAM the map has about eight landmarks, a robot sees one at
a time, and a robot counted as lost while its dead reckoning held (0.1–0.3 m off) stayed blind for up to 280 s,
drifting until a wrong correction took it. And the drift is a prior, not only a window: each correction's
detections are scored less ``reacquire_prior_weight`` times its squared size in σ of the drift, so a far
correction must explain clearly more than a near one (seed 18: a robot 0.2 m off was turned by 19° and moved
1.1 m, 3.5σ, on 26 detections of a dead-reckoned window, against fewer for the near ones). A blind robot's
detections neither update nor start landmarks (counted as ``detections_blind``): what it would map from a pose it
does not know is what this guards against.

The robots a robot sees speak too (``reacquire_by_robots``). A wrong correction leaves a robot sure of a wrong pose:
its drift restarts from zero, it matches the copies it maps, and nothing above counts it as lost again. Its
detections of other robots do: when most of the last ``reacquire_robots_window_s`` of them, of two robots at least,
are explained by no particle (:func:`contradicted`), its drift is widened to the search's limits (:func:`widened`)
and it is held. While it is held, each of its robot detections joins the window as a point with the robot it saw,
and every correction the vote scores also counts the robot detections it brings near their robot
(:func:`robot_count`): a robot is a landmark only its own detections may reach.

D-SLAM's re-acquisition (:meth:`services.dslam.core.DSlam._held`) uses the same window and search with its own
:class:`SearchRule`: a robot there is lost when its own position std passes a limit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from central.fastslam import kernels
from robots.gaussian import block_diagonal, chi2_quantile, ekf_covariance_update
from robots.models import fit_se2, se2_compose, se2_inverse, wrap_angle

if TYPE_CHECKING:
    from central.fastslam.config import FastSlamConfig
    from central.fastslam.core import FastSlam
    from central.fastslam.lifecycle import RobotState

TURN_STEP = math.radians(1.5)  # the turns tried, this far apart
ROBOT_GATE = chi2_quantile(0.999, 2)  # a robot detection beyond it (d²) contradicts the two robots' poses
POINT_QUANTUM = 0.05  # m: the same landmark seen again from about the same place votes once, with its count
SHIFTS_PER_TURN = 4  # the best-voted shifts of each turn scored in full
DISTINCT_TURN = math.radians(8.0)  # a correction this far in turn, or ...
DISTINCT_SHIFT = 1.6  # ... in shift (inlier radii: 0.4 m at 0.25) from the best is another hypothesis
SIGMAS = 3.0  # the search window in σ of the drift


@dataclass(frozen=True)
class SearchRule:
    """When :func:`search` takes a correction: it brings ``min_detections`` detections within ``inlier`` (m) of a
    landmark, reaching ``min_landmarks`` distinct landmarks at least ``span`` (m) apart, and no distinct correction
    comes within ``margin`` detections of it. Failing that, with ``confirm_sigmas`` > 0, a correction within
    ``confirm_sigmas`` of the drift (at most ``confirm_max_turn`` rad and ``confirm_max_shift`` m) is taken when it
    brings ``min_detections`` detections onto a landmark and no correction brings ``margin`` more: the dead
    reckoning was right, and the landmarks it reaches need not pin the turn (:func:`confirm`). With ``prior_weight``
    > 0 every correction counts its detections less ``prior_weight`` times its squared size in σ of the drift
    (:func:`prior_d2`), and these scores are what the rules compare. With ``robots_veto`` > 0 and at least that many
    robot detections in the window, a correction that brings fewer than half of them near their robots is refused:
    the robots that contradicted the robot would contradict it again. ``compiled``: the vote by its numba kernel.
    FastSLAM's comes from its config (:meth:`central.fastslam.config.FastSlamConfig.reacquire_rule`), D-SLAM's from
    its config and the sensor's noise (:mod:`services.dslam.core`)."""

    min_detections: int
    inlier: float
    span: float
    margin: float
    min_landmarks: int = 2
    compiled: bool = True
    confirm_sigmas: float = 0.0
    confirm_max_turn: float = 0.0
    confirm_max_shift: float = 0.0
    prior_weight: float = 0.0
    confirm_tolerance: float = 0.0
    robots_veto: int = 0


@dataclass
class BlindWindow:
    """The detections of a robot that is re-acquiring the map: world points from its dead-reckoned pose."""

    tried: float = -math.inf
    stamps: list = field(default_factory=list)
    points: list = field(default_factory=list)
    robots: list = field(default_factory=list)  # (stamp, [point, the seen robot's position]) of robot detections
    contradicted: bool = False  # held because its detections of other robots contradicted it
    reckoned: np.ndarray | None = None  # the robot's estimate at the last add, before that scan's odometry
    odometry: np.ndarray = field(default_factory=lambda: np.zeros(3))  # Δ̄ applied to the robot since (its frame)
    added: int = 0  # detections added since the robot was held
    candidate: tuple | None = None  # (world transform 3x3, agreeing searches, ``added`` then): :meth:`confirms`

    def add(self, stamp: float, points: np.ndarray, window_s: float) -> None:
        self.stamps.append(stamp)
        self.points.append(points)
        self.added += len(points)
        old = 0
        while self.stamps[old] < stamp - window_s:
            old += 1
        del self.stamps[:old], self.points[:old]
        drop_before(self.robots, stamp - window_s)

    def follow(self, pose: np.ndarray, pending: np.ndarray | None) -> None:
        """Keep the window in the frame of the robot's estimate ``pose`` ``(3,)``, which includes the buffered
        odometry ``pending`` (Δ̄ in the robot's frame): where the estimate moved otherwise than by the odometry
        applied since the last add (:meth:`moved`) and ``pending``, the kept points move with it. In one filter over
        the fleet the other robots' scans and the robot detections resample the particles, and with them a held
        robot's pose; a correction found for points placed from the pose before would be applied to the pose after
        (MR.CLAM: a robot its robot detections had brought back within 3° was turned 35° off by its window)."""
        before = pose if pending is None else se2_compose(pose, se2_inverse(pending))
        if self.reckoned is not None:
            expected = se2_compose(self.reckoned, self.odometry)
            turn, shift = wrap_angle(before[2] - expected[2]), before[:2] - expected[:2]
            self.points = [turned(points, expected[:2], turn) + shift for points in self.points]
            self.robots = [(stamp, np.r_[turned(pair[:2], expected[:2], turn) + shift, pair[2:]])
                           for stamp, pair in self.robots]
            if self.candidate is not None:  # the candidate took the points where they were: A' = A ∘ jump⁻¹
                jump = rigid(turn, expected[:2], shift)
                self.candidate = (self.candidate[0] @ np.linalg.inv(jump),) + self.candidate[1:]
        self.reckoned, self.odometry = np.array(before, float), np.zeros(3)

    def confirms(self, correction: Correction, position: np.ndarray, needed: int, fresh: int,
                 apart_m: float) -> bool:
        """Whether ``correction`` (found now, the robot at ``position``) is the ``needed``-th of searches in a row
        that agree on one rigid transform of the window (turn within ``DISTINCT_TURN``, the robot moved to within
        ``apart_m`` of the same place), each with at least ``fresh`` detections added since the one before: a
        correction is taken on independent confirmations, not on one window's chance alignment (MR.CLAM 1: a
        robot turned 42° by one search mapped a turned copy for 200 s)."""
        transform = rigid(correction.turn, correction.centre, correction.shift)
        agreeing = 1
        if self.candidate is not None:
            before, count, added = self.candidate
            if self.added - added < fresh:
                return False  # the same detections again: no new evidence yet, keep the candidate
            turn_apart = abs(wrap_angle(math.atan2(transform[1, 0], transform[0, 0])
                                        - math.atan2(before[1, 0], before[0, 0])))
            here = np.r_[position, 1.0]
            if turn_apart <= DISTINCT_TURN and np.hypot(*((transform - before) @ here)[:2]) <= apart_m:
                agreeing = count + 1
        self.candidate = (transform, agreeing, self.added)
        return agreeing >= needed

    def moved(self, delta: np.ndarray) -> None:
        """The robot's particles were moved by the odometry Δ̄ ``delta`` (its frame): not a jump of its estimate."""
        self.odometry = se2_compose(self.odometry, delta)

    def __setstate__(self, state: dict) -> None:
        """Restore a pickled window (a checkpoint), also one written before it kept robot detections or its pose."""
        state.setdefault("robots", [])
        state.setdefault("contradicted", False)
        state.setdefault("reckoned", None)
        state.setdefault("odometry", np.zeros(3))
        state.setdefault("added", 0)
        state.setdefault("candidate", None)
        self.__dict__.update(state)

    def robot_pairs(self) -> np.ndarray | None:
        """``(n, 4)``: each kept robot detection's point (from the dead-reckoned pose) and where that robot was."""
        return np.array([pair for _, pair in self.robots]) if self.robots else None

    def due(self, stamp: float, every_s: float) -> bool:
        """Whether a search is due at ``stamp`` (at most one every ``every_s``); if so it counts as tried."""
        if stamp - self.tried < every_s:
            return False
        self.tried = stamp
        return True


@dataclass(frozen=True)
class Correction:
    """A rigid correction of a robot's pose: turn by ``turn`` about ``centre``, then shift by ``shift``."""

    turn: float
    shift: np.ndarray
    centre: np.ndarray
    detections: float  # detections brought onto a landmark
    landmarks: int  # distinct landmarks they reach

    def apply(self, poses: np.ndarray) -> np.ndarray:
        """The poses ``(..., 3)`` corrected."""
        out = np.array(poses, float, copy=True)
        out[..., :2] = turned(out[..., :2], self.centre, self.turn) + self.shift
        out[..., 2] = wrap_angle(out[..., 2] + self.turn)
        return out


def rigid(turn: float, centre: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """The world transform (3x3, homogeneous) of turning by ``turn`` about ``centre`` and then shifting by ``shift``."""
    c, s = math.cos(turn), math.sin(turn)
    rotation = np.array([[c, -s], [s, c]])
    out = np.eye(3)
    out[:2, :2] = rotation
    out[:2, 2] = np.asarray(centre, float) + np.asarray(shift, float) - rotation @ np.asarray(centre, float)
    return out


def turned(points: np.ndarray, centre: np.ndarray, turn: float) -> np.ndarray:
    """``points`` ``(..., 2)`` turned by ``turn`` about ``centre``."""
    c, s = math.cos(turn), math.sin(turn)
    d = points - centre
    return np.stack([c * d[..., 0] - s * d[..., 1], s * d[..., 0] + c * d[..., 1]], -1) + centre


def accumulate(drift: np.ndarray | None, heading: float, delta: np.ndarray, cov: np.ndarray,
               turn_slip_var: float) -> np.ndarray:
    """The drift covariance (world frame) after one more relative motion ``delta`` (robot frame, covariance ``cov``)
    from a pose with ``heading``: the heading's uncertainty carried into position along the path (the
    composition's Jacobian), plus the motion's own noise, plus ``turn_slip_var`` per radian turned."""
    drift = np.zeros((3, 3)) if drift is None else drift
    c, s = math.cos(heading), math.sin(heading)
    jac = np.eye(3)
    jac[0, 2] = -(s * delta[0] + c * delta[1])
    jac[1, 2] = c * delta[0] - s * delta[1]
    rot = np.eye(3)
    rot[:2, :2] = [[c, -s], [s, c]]
    out = jac @ drift @ jac.T + rot @ cov @ rot.T
    out[2, 2] += turn_slip_var * abs(float(delta[2]))
    return out


def condition(drift: np.ndarray, h_x: np.ndarray, noise: np.ndarray) -> np.ndarray:
    """The drift after the robot matched confirmed landmarks: the Kalman update of the covariance ``drift`` by the
    detections' pose Jacobians ``h_x`` ``(n, 2, 3)`` and their noise ``(n, 2, 2)`` (the sensor's plus the
    landmark's). One landmark leaves the turn about it free, so the drift keeps what the match cannot pin, and a
    robot that saw one landmark at a time comes back to re-acquisition sooner, instead of starting from zero at
    every match (MR.CLAM: a robot 49° off matched one landmark and went on for a minute as if its heading were
    known)."""
    h = h_x.reshape(-1, 3)
    return ekf_covariance_update(drift, h, block_diagonal(noise))


def lost(config: FastSlamConfig, drift: np.ndarray | None) -> bool:
    """Whether a robot's drift (its dead reckoning, conditioned on its matches) is beyond what scan-by-scan
    association can trust."""
    if drift is None:
        return False
    return bool(drift[2, 2] > config.reacquire_heading_sd ** 2
                or max(drift[0, 0], drift[1, 1]) > config.reacquire_position_sd ** 2)


def drop_before(items: list, oldest: float) -> None:
    """Drop the leading ``items`` (tuples in time order, their stamp first) stamped before ``oldest``."""
    old = 0
    while old < len(items) and items[old][0] < oldest:
        old += 1
    del items[:old]


def note_robot_detection(robot: RobotState, stamp: float, seen: str, explained: bool, window_s: float) -> None:
    """Keep the robot's detection of robot ``seen`` (whether some particle explains it) for :func:`contradicted`;
    those older than ``window_s`` are dropped."""
    robot.robot_checks.append((stamp, seen, explained))
    drop_before(robot.robot_checks, stamp - window_s)


def contradicted(robot: RobotState, stamp: float, window_s: float, least: int) -> bool:
    """Whether the robot's own detections of other robots over the last ``window_s`` say its pose is wrong: at least
    ``least`` of them unexplained (beyond :data:`ROBOT_GATE` for every particle in FastSLAM, for the two poses'
    Gaussians in D-SLAM), of two robots at least, and four in five of them unexplained. A robot that took a wrong
    correction matches the copies it maps and its drift says it is sure; the robots it sees say otherwise (MR.CLAM
    Dataset 1, seed 0, against the run with barcodes: 91 % of the detections made by a robot more than 1 m or 20°
    off lie beyond the gate, 3 % of those between two robots that are not; Dataset 6 against Vicon: 77 % and 7 %)."""
    checks = robot.robot_checks
    drop_before(checks, stamp - window_s)
    unexplained = [seen for _, seen, explained in checks if not explained]
    return len(unexplained) >= least and len(set(unexplained)) >= 2 and len(unexplained) >= 0.8 * len(checks)


def widened(drift: np.ndarray | None, max_shift: float, max_turn: float) -> np.ndarray:
    """The drift (or pose covariance) of a robot its detections of others contradict: its own plus a third of the
    search's limits (``max_shift``, ``max_turn``) as σ, so that it is lost and searched for that far."""
    out = np.zeros((3, 3)) if drift is None else np.array(drift, float)
    return out + np.diag([(max_shift / SIGMAS) ** 2] * 2 + [(max_turn / SIGMAS) ** 2])


def search(points: np.ndarray, landmarks: np.ndarray, centre: np.ndarray, turn_limit: float, shift_limit: float,
           rule: SearchRule, sigmas: tuple[float, float] | None = None,
           robot_pairs: np.ndarray | None = None, robots_needed: bool = False) -> Correction | None:
    """The rigid correction (turn ≤ ``turn_limit`` about ``centre``, shift ≤ ``shift_limit``) that brings the most
    ``points`` ``(n, 2)`` within ``rule.inlier`` of ``landmarks`` ``(K, 2)``, or None when it is not clearly the
    one (too few detections or landmarks, landmarks too close together, or a distinct correction nearly as good).
    ``sigmas`` (the drift's σ heading, σ position) lets ``rule``'s confirmation and prior weigh the corrections.
    ``robot_pairs`` ``(n, 4)`` (a detection's point, where the robot it saw was) add to each correction the robot
    detections it brings within twice ``rule.inlier`` of their robot: a robot is a landmark only its own
    detections may reach. ``robots_needed`` (a robot its robot detections contradicted): with ``rule.robots_veto``,
    no correction until that many of them are in the window and it brings half of them near their robots."""
    if points.shape[0] < rule.min_detections or landmarks.shape[0] < max(rule.min_landmarks, 2):
        return None
    cells, weights = np.unique(np.round(points / POINT_QUANTUM) * POINT_QUANTUM, axis=0, return_counts=True)
    inlier = rule.inlier
    turns = np.arange(-turn_limit, turn_limit + 1e-12, TURN_STEP) if turn_limit > 0.0 else np.zeros(1)
    vote = kernels.vote if rule.compiled else vote_reference
    scored = vote(cells, weights, landmarks, np.asarray(centre, float), turns, shift_limit, inlier, SHIFTS_PER_TURN)
    if not scored:
        return None
    if robot_pairs is not None:
        scored = [(count + robot_count(robot_pairs, centre, turn, shift, 2.0 * inlier), turn, shift, reached)
                  for count, turn, shift, reached in scored]
    if sigmas is not None and rule.prior_weight > 0.0:
        scored = [(count - rule.prior_weight * prior_d2(turn, shift, sigmas), turn, shift, reached)
                  for count, turn, shift, reached in scored]
    scored.sort(key=lambda item: -item[0])
    taken = clear_best(scored, landmarks, rule)
    if taken is None and sigmas is not None and rule.confirm_sigmas > 0.0:
        taken = confirm(scored, rule, sigmas)
    if taken is None:
        return None
    detections, turn, shift, reached = taken
    pairs = 0 if robot_pairs is None else robot_pairs.shape[0]
    if rule.robots_veto > 0 and (pairs >= rule.robots_veto or robots_needed) and (
            pairs < rule.robots_veto or 2 * robot_count(robot_pairs, centre, turn, shift, 2.0 * inlier) < pairs):
        return None
    return refine(cells, weights, landmarks, centre, turn, shift, inlier, detections, int(np.unique(reached).size))


def robots_fit(pairs: np.ndarray | None, centre: np.ndarray, min_pairs: int, min_spread: float,
               max_residual: float) -> Correction | None:
    """The rigid correction, at any turn, that brings a held robot's detections of other robots ``pairs``
    ``(n, 4)`` (a detection's point, where the robot it saw was) onto those robots by least squares (Kabsch), turned
    about ``centre``; None unless it is determined and consistent: at least ``min_pairs`` of them, their points
    spread at least ``min_spread`` (RMS, m) so the turn is fixed, each brought within ``max_residual`` of its robot.
    A robot placed or corrected half a turn off (MR.CLAM Dataset 1: placed 155° off at 25 s on a map of a few
    landmarks) is beyond any search of the landmarks within the caps, and takes the cap's wrong corrections one
    after another; the robots it sees put it back."""
    if pairs is None or pairs.shape[0] < min_pairs:
        return None
    seen, robots = pairs[:, :2], pairs[:, 2:]
    if math.sqrt(float(np.mean(np.sum((seen - seen.mean(0)) ** 2, 1)))) < min_spread:
        return None
    turn = float(fit_se2(seen, robots)[2])
    moved = turned(seen, centre, turn)
    shift = robots.mean(0) - moved.mean(0)
    if np.max(np.hypot(*(moved + shift - robots).T)) > max_residual:
        return None
    return Correction(turn, shift, np.asarray(centre, float).copy(), float(pairs.shape[0]), 0)


def robot_count(pairs: np.ndarray, centre: np.ndarray, turn: float, shift: np.ndarray, radius: float) -> int:
    """How many robot detections ``pairs`` ``(n, 4)`` the correction brings within ``radius`` of the robot seen."""
    moved = turned(pairs[:, :2], centre, turn) + shift
    return int(np.count_nonzero(np.hypot(*(moved - pairs[:, 2:]).T) < radius))


def clear_best(scored: list, landmarks: np.ndarray, rule: SearchRule) -> tuple | None:
    """The best of the vote's ``scored`` corrections (sorted by score, best first: detections, less the prior if
    any) when it is clearly the one:
    enough detections, reaching landmarks far enough apart, no distinct correction within ``rule.margin``."""
    detections, turn, shift, reached = scored[0]
    if detections < rule.min_detections:
        return None
    distinct_shift = DISTINCT_SHIFT * rule.inlier
    tied = [item for item in scored if item[0] == detections and abs(item[1] - turn) <= DISTINCT_TURN
            and np.hypot(*(item[2] - shift)) <= distinct_shift]
    middle = 0.5 * (min(item[1] for item in tied) + max(item[1] for item in tied))
    _, turn, shift, reached = min(tied, key=lambda item: abs(item[1] - middle))  # the middle of the turns that
    # explain as much, not the edge of that band (the first found)
    hit = landmarks[np.unique(reached)]
    if hit.shape[0] < rule.min_landmarks or np.max(np.hypot(*(hit[:, None] - hit[None]).transpose(2, 0, 1))) < rule.span:
        return None
    for other, other_turn, other_shift, _ in scored[1:]:
        if abs(other_turn - turn) > DISTINCT_TURN or np.hypot(*(other_shift - shift)) > distinct_shift:
            if other > detections - rule.margin:
                return None
            break
    return detections, turn, shift, reached


def confirm(scored: list, rule: SearchRule, sigmas: tuple[float, float]) -> tuple | None:
    """The correction nearest the dead reckoning among the vote's ``scored`` ones within ``rule.confirm_sigmas`` of
    the drift (σ heading, σ position: ``sigmas``), when it explains ``rule.min_detections`` and nothing explains
    ``rule.margin`` more. One landmark in view leaves the turn free (:func:`clear_best` refuses it), but the
    drift's own Gaussian does not: a robot counted as lost while its dead reckoning held comes back at once
    instead of staying blind for minutes among landmarks it sees one at a time (MR.CLAM)."""
    heading_sd, position_sd = sigmas
    turn_limit = min(rule.confirm_sigmas * heading_sd, rule.confirm_max_turn)
    shift_limit = min(rule.confirm_sigmas * position_sd, rule.confirm_max_shift)
    near = [item for item in scored if abs(item[1]) <= turn_limit and np.hypot(*item[2]) <= shift_limit]
    if not near:
        return None
    best = max(item[0] for item in near)
    if best < rule.min_detections or best < scored[0][0] - rule.margin:
        return None
    return min((item for item in near if item[0] >= best - rule.confirm_tolerance),
               key=lambda item: prior_d2(item[1], item[2], sigmas))


def prior_d2(turn: float, shift: np.ndarray, sigmas: tuple[float, float]) -> float:
    """Squared Mahalanobis size of a correction against the drift (σ heading, σ position)."""
    return (turn / sigmas[0]) ** 2 + float(shift @ shift) / sigmas[1] ** 2


def search_window(window: BlindWindow, centre: np.ndarray, heading_sd: float, position_sd: float, max_turn: float,
                  max_shift: float, landmarks, rule: SearchRule) -> Correction | None:
    """:func:`search` over a held window's points: turns about ``centre`` within ``SIGMAS`` of ``heading_sd`` (at
    most ``max_turn``), shifts within ``SIGMAS`` of ``position_sd`` plus the inlier radius (at most ``max_shift``),
    against ``landmarks(point, radius)``: the landmark means the points can reach after such a correction."""
    points = np.concatenate(window.points)
    if not points.shape[0]:
        return None
    turn_limit = min(SIGMAS * heading_sd, max_turn)
    shift_limit = min(SIGMAS * position_sd + rule.inlier, max_shift)
    reach = float(np.hypot(*(points - centre).T).max()) + shift_limit + rule.inlier
    return search(points, landmarks(centre, reach), centre, turn_limit, shift_limit, rule, (heading_sd, position_sd),
                  window.robot_pairs(), window.contradicted)


def vote_reference(cells: np.ndarray, weights: np.ndarray, landmarks: np.ndarray, centre: np.ndarray,
                   turns: np.ndarray, shift_limit: float, inlier: float, shifts_per_turn: int
                   ) -> list[tuple[float, float, np.ndarray, np.ndarray]]:
    """The Hough vote of :func:`search`, in numpy (the reference of :func:`central.fastslam.kernels.vote`): for each
    of ``turns`` about ``centre``, every (cell, landmark) pair within ``shift_limit`` votes for the shift joining
    them, binned on an ``inlier`` grid, each cell once per bin with its weight; the ``shifts_per_turn`` best bins
    (ties: the lower bin key first) are scored at the mean of their shifts. Returns, per scored shift, turn by turn
    and best bin first: (detections brought within ``inlier`` of a landmark, turn, shift, the landmark each reaches)."""
    n, k = cells.shape[0], landmarks.shape[0]
    owner = np.repeat(np.arange(n), k)
    scored: list[tuple[float, float, np.ndarray, np.ndarray]] = []
    for turn in turns:
        moved = turned(cells, centre, turn)
        shifts = (landmarks[None, :, :] - moved[:, None, :]).reshape(-1, 2)
        inside = np.hypot(shifts[:, 0], shifts[:, 1]) <= shift_limit
        if not inside.any():
            continue
        shifts, voters = shifts[inside], owner[inside]
        cell = np.floor(shifts / inlier).astype(np.int64)
        cell -= cell.min(0)
        key = cell[:, 0] * (int(cell[:, 1].max()) + 1) + cell[:, 1]
        votes_of = np.unique(key * n + voters)  # each point votes once per cell
        voted_cells, slot = np.unique(votes_of // n, return_inverse=True)
        votes = np.bincount(slot, weights=weights[votes_of % n])
        for best in np.argsort(-votes, kind="stable")[:shifts_per_turn]:
            shift = shifts[key == voted_cells[best]].mean(0)
            gap = np.hypot(*((moved + shift)[:, None, :] - landmarks[None]).transpose(2, 0, 1))
            near = gap.min(1) < inlier
            scored.append((float(near @ weights), float(turn), shift, gap.argmin(1)[near]))
    return scored


def refine(points: np.ndarray, weights: np.ndarray, landmarks: np.ndarray, centre: np.ndarray, turn: float,
           shift: np.ndarray, inlier: float, detections: float, reached: int) -> Correction:
    """The correction at ``turn`` with the shift that joins the points it brings within ``inlier`` of a landmark to
    those landmarks on average (weighted by their counts): the vote's grid is coarser than the detections. The turn
    is not fitted by least squares: over a window of dead-reckoned scans the points are not rigid, and on MR.CLAM
    a least-squares turn over nearest-landmark pairs (a cluster's neighbour among them) placed robots worse (80
    seeds: 12 with a robot above 1.5 m against 3)."""
    centre = np.asarray(centre, float)
    moved = turned(points, centre, turn)
    gap = np.hypot(*((moved + shift)[:, None, :] - landmarks[None]).transpose(2, 0, 1))
    near = gap.min(1) < inlier
    w = weights[near].astype(float)
    return Correction(turn, w @ (landmarks[gap.argmin(1)[near]] - moved[near]) / w.sum(), centre.copy(), detections,
                      reached)


def beyond_caps(window: BlindWindow, centre: np.ndarray, max_turn: float, max_shift: float, min_pairs: int,
                min_spread: float, max_residual: float) -> Correction | None:
    """The robots' fit (:func:`robots_fit`, the last three arguments) of a window held because the robots
    contradicted it, when the fit lies beyond the search's caps ``max_turn``, ``max_shift``, where no search of the
    landmarks can reach, and the pose as it is leaves most of the robot detections farther than ``max_residual``
    from their robots; None otherwise (within the caps the search weighs the robot detections with the landmarks).
    On MR.CLAM Dataset 6 the fits of windows held for their drift, with 6 to 8 detections spread 0.5 to 0.7 m and
    residuals up to 0.4 m, all took robots that were 0.2 to 0.4 m off 20 to 70° away."""
    if not window.contradicted:
        return None
    pairs = window.robot_pairs()
    fit = robots_fit(pairs, centre, min_pairs, min_spread, max_residual)
    if fit is None or (abs(fit.turn) <= max_turn and float(np.hypot(*fit.shift)) <= max_shift):
        return None
    if 2 * robot_count(pairs, centre, 0.0, np.zeros(2), max_residual) >= pairs.shape[0]:
        return None  # the pose as it is explains half of them: the robots do not say it is that far off
    return fit


def step(slam: FastSlam, robot: RobotState, pose: np.ndarray, z: np.ndarray, landmarks,
         pending: np.ndarray | None = None) -> str:
    """What to do with the scan ``z`` of ``robot`` (predicted mean ``pose``, which includes the buffered odometry
    ``pending``): ``"associate"`` it (the robot is not lost), ``"hold"`` it for re-acquisition, or associate it from
    the pose just ``"corrected"``.
    ``landmarks(point, radius)`` gives the means of the confirmed landmarks within ``radius`` of ``point`` (called
    only for a search)."""
    config = slam.config
    stamp = robot.last_scan_stamp
    if robot.blind is None:
        if config.reacquires_by_robots and contradicted(robot, stamp, config.reacquire_robots_window_s,
                                                       config.reacquire_robots_min):
            robot.drift = widened(robot.drift, config.reacquire_max_shift_m, config.reacquire_max_turn)
            robot.robot_checks.clear()
            slam.counts["reacquire_contradicted"] += 1
            robot.blind = BlindWindow(contradicted=True)
        elif not lost(config, robot.drift):
            return "associate"
        else:
            robot.blind = BlindWindow()
        slam.counts["reacquire_started"] += 1
    window = robot.blind
    window.follow(pose, pending)
    window.add(stamp, robot.sensor.inverse(pose, z), config.reacquire_window_s)
    if window.due(stamp, config.reacquire_every_s):
        drift = robot.drift  # a held robot matches nothing: only a correction resets its drift
        correction = beyond_caps(window, pose[:2], config.reacquire_max_turn, config.reacquire_max_shift_m,
                                 config.reacquire_robots_fit_min, config.reacquire_robots_fit_spread_m,
                                 config.reacquire_robots_fit_residual_m) if config.reacquires_by_robots else None
        if correction is not None:
            slam.counts["reacquired_by_robots"] += 1
        else:
            correction = search_window(window, pose[:2], math.sqrt(drift[2, 2]), math.sqrt(max(drift[0, 0], drift[1, 1])),
                                       config.reacquire_max_turn, config.reacquire_max_shift_m, landmarks,
                                       config.reacquire_rule)
            if correction is not None and not window.confirms(
                    correction, pose[:2], config.reacquire_confirmations, config.reacquire_min_detections,
                    DISTINCT_SHIFT * config.reacquire_inlier_m):
                slam.counts["reacquire_unconfirmed"] += 1
                correction = None
        if correction is not None:
            col = robot.index
            slam.pose[:, col] = correction.apply(slam.pose[:, col])
            robot.blind, robot.drift = None, None
            slam.counts["reacquired"] += 1
            return "corrected"
    slam.counts["detections_blind"] += z.shape[0]
    return "hold"
