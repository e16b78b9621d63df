"""Robots that detect each other: a detection between a robot being localized and a robot whose pose is known.

Collaborative Monte Carlo localization (Fox, Burgard, Kruppa and Thrun, "A probabilistic approach to
collaborative multi-robot localization", Autonomous Robots 8(3), 2000, §3.2): when robot A, whose pose is known
(Gaussian), and robot B, being localized, detect each other, B's belief is multiplied by the density of where the
detection puts B. Two cases:

- A saw B at (r, b) in A's sensor frame: B's position is A's sensor position plus r in direction θ_A + b, with
  the covariance of A's pose and of the detection carried through; B's heading is free;
- B saw A at (r, b) in B's sensor frame: A's position is a landmark of known identity for B (a signature), its
  covariance added to the detection's.

Where B's particles all disagree with a meeting (no particle within the gate), B's localization starts again
from poses the meeting allows (:func:`draw`): a robot lost on the twin of a symmetric map is found at once.

A robot's meetings also place it without a map (:class:`MeetingLog`): each is kept with the robot's
dead-reckoned pose then, and the pose of the odometry frame in the world that explains them all is a small
least-squares problem (three unknowns). Its solution is taken when it is consistent, precise and unique (no
other local minimum nearly as good): early in a run the anchor's map may hold too few landmarks for MCL, and a
map without landmark ids can be nearly symmetric, the robots' own ids are not.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from robots.gaussian import chi2_quantile
from robots.models import (RangeBearingSensor, compose_start_jacobian, robot_models, se2_between, se2_compose,
                           se2_inverse, wrap_angle)
from schemas.contract import OdomEvent, ScanEvent

GATE = chi2_quantile(0.999, 2)  # a particle farther than this (d²) from the meeting disagrees with it
_FORWARD_STEP = math.sqrt(np.finfo(float).eps)  # scipy's 2-point relative step (_forward_differences)


@dataclass(frozen=True)
class Meeting:
    """One detection between the robot being localized and another robot: ``other_pose`` ``(3,)`` with
    ``other_cov`` ``(3, 3)``; ``z`` (range, bearing) with ``noise_cov`` ``(2, 2)``; ``by_other``: the other robot's
    sensor (``other_sensor``) made the detection, else this robot's did. ``other_id`` names the other robot: the
    meetings with one robot share its pose error, which a fix counts once (:meth:`MeetingLog.solve`); None
    (meetings logged before it was kept): each meeting's error counted as its own."""

    other_pose: np.ndarray
    other_cov: np.ndarray
    z: np.ndarray
    noise_cov: np.ndarray
    by_other: bool
    other_sensor: RangeBearingSensor = RangeBearingSensor()
    other_id: str | None = None

    def position_terms(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``by_other``: where the detection puts this robot (mean ``(2,)``), d(position)/d(other's pose) ``(2, 3)``
        and the detection's own covariance there ``(2, 2)``."""
        pose, z = np.asarray(self.other_pose, float), np.asarray(self.z, float)
        g_pose, g_z = self.other_sensor.inverse_jacobians(pose, z)
        return self.other_sensor.inverse(pose, z), g_pose, g_z @ self.noise_cov @ g_z.T

    def position(self) -> tuple[np.ndarray, np.ndarray]:
        """``by_other``: where the detection puts this robot (mean ``(2,)``, covariance ``(2, 2)``: the other's pose
        and the detection's noise carried through)."""
        mean, g_pose, detection_cov = self.position_terms()
        return mean, g_pose @ self.other_cov @ g_pose.T + detection_cov


def log_likelihood(poses: np.ndarray, meeting: Meeting, sensor: RangeBearingSensor) -> tuple[np.ndarray, np.ndarray]:
    """(log-likelihood ``(P,)``, squared Mahalanobis distance ``(P,)``) of the meeting at this robot's ``poses``
    ``(P, 3)`` (``sensor``: this robot's). The log-likelihood is Gaussian, capped at the gate: a meeting that no
    particle explains does not single out the least wrong ones."""
    poses = np.asarray(poses, float).reshape(-1, 3)
    if meeting.by_other:
        mean, cov = meeting.position()
        d = poses[:, :2] - mean
        d2 = np.einsum("pi,ij,pj->p", d, np.linalg.inv(cov), d)
        return -0.5 * np.minimum(d2, GATE), d2
    other = np.asarray(meeting.other_pose[:2], float)[None]
    predicted, h_other = sensor.observe_with_jacobian(poses[:, None, :], other[None])  # (P, 1, 2), (P, 1, 2, 2)
    nu = sensor.innovation(np.asarray(meeting.z, float), predicted[:, 0])
    cov = meeting.noise_cov + h_other[:, 0] @ meeting.other_cov[:2, :2] @ np.swapaxes(h_other[:, 0], -1, -2)
    d2 = np.einsum("pi,pij,pj->p", nu, np.linalg.inv(cov), nu)
    return -0.5 * np.minimum(d2, GATE) - 0.5 * np.log(np.linalg.det(cov)), d2


def draw(meeting: Meeting, sensor: RangeBearingSensor, count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` poses ``(count, 3)`` the meeting allows: by the other robot, positions from the detection's
    Gaussian and any heading; by this robot, its sensor on the circle of the measured range around the other
    robot (jittered by that robot's covariance), the heading from the measured bearing."""
    if meeting.by_other:
        mean, cov = meeting.position()
        position = rng.multivariate_normal(mean, cov, count)
        return np.column_stack([position, rng.uniform(-math.pi, math.pi, count)])
    sigma = np.sqrt(np.diag(meeting.noise_cov))
    other = rng.multivariate_normal(np.asarray(meeting.other_pose[:2], float), meeting.other_cov[:2, :2], count)
    r = np.maximum(meeting.z[0] + rng.normal(0.0, sigma[0], count), 1e-3)
    bearing = meeting.z[1] + rng.normal(0.0, sigma[1], count)
    direction = rng.uniform(-math.pi, math.pi, count)  # world direction from this robot's sensor to the other robot
    return sensor.pose_seeing(other, np.stack([r, bearing], -1), direction)


@dataclass(frozen=True)
class MeetingFix:
    """Where a robot's meetings put it now: ``pose`` ``(3,)``, ``cov`` ``(3, 3)``, from ``meetings`` meetings
    with χ² ``chi2``."""

    pose: np.ndarray
    cov: np.ndarray
    meetings: int
    chi2: float


@dataclass(frozen=True)
class _Logged:
    odometry: np.ndarray  # the robot's dead-reckoned pose at the meeting
    turned: float
    meeting: Meeting


class MeetingLog:
    """One robot's recent meetings with placed robots, each at its dead-reckoned pose then, and the pose they
    give it now (:meth:`solve`). Meetings older than ``max_turn`` radians turned are dropped (odometry drifts in
    turns), and all but the last ``max_meetings``."""

    def __init__(self, max_meetings: int = 40, max_turn: float = 1.0, min_meetings: int = 3,
                 max_std_xy: float = 0.3, max_std_theta: float = 0.1, headings: int = 12):
        self.max_turn = max_turn
        self.min_meetings = min_meetings
        self.max_std_xy = max_std_xy
        self.max_std_theta = max_std_theta
        self.headings = headings
        self.odometry = np.zeros(3)  # dead-reckoned pose in an arbitrary frame
        self.turned = 0.0
        self.entries: deque[_Logged] = deque(maxlen=max_meetings)

    def __len__(self) -> int:
        return len(self.usable())

    def move(self, pose: np.ndarray) -> None:
        """The dead-reckoned pose after one odometry reading."""
        self.turned += abs(float(wrap_angle(pose[2] - self.odometry[2])))
        self.odometry = np.asarray(pose, float).copy()

    def add(self, meeting: Meeting) -> None:
        self.entries.append(_Logged(self.odometry.copy(), self.turned, meeting))

    def usable(self) -> list[_Logged]:
        return [e for e in self.entries if self.turned - e.turned <= self.max_turn]

    def latest(self) -> Meeting | None:
        return self.entries[-1].meeting if self.entries else None

    def contradicts(self, pose: np.ndarray, sensor: RangeBearingSensor) -> bool:
        """Whether the robot at ``pose`` now (carried back along the odometry to each meeting) is outside the
        gate of one of its usable meetings (``sensor``: its own)."""
        for entry in self.usable():
            then = se2_compose(pose, se2_between(self.odometry, entry.odometry))
            if log_likelihood(then[None], entry.meeting, sensor)[1][0] > GATE:
                return True
        return False

    def solve(self, sensor: RangeBearingSensor) -> MeetingFix | None:
        """The robot's pose now from its usable meetings (``sensor``: its own), or None while they do not fix it:
        too few, inconsistent (χ² beyond its 99.9 % quantile), imprecise (``max_std_xy``, ``max_std_theta``) or
        ambiguous (a second minimum, found from another of ``headings`` starting headings, within the χ²(3) 99 %
        quantile of the best and elsewhere). The unknowns are the odometry frame's pose in the world and, per
        placed robot met, the error of its estimated pose (with its covariance as a prior): ten meetings with one
        robot do not know its pose ten times better than one does."""
        entries = self.usable()
        if len(entries) < self.min_meetings:
            return None
        odometry = np.array([e.odometry for e in entries])
        # the minima, found from every starting heading with the frame alone (each meeting's error its own: three
        # unknowns, cheap), then refined with the placed robots' shared errors (tens of milliseconds each)
        free, _ = _residual_function(entries, odometry, sensor, shared=False)
        minima: list[np.ndarray] = []
        for heading in np.linspace(-math.pi, math.pi, self.headings, endpoint=False):
            frame = least_squares(_one(free), _start(entries[0], odometry[0], heading, sensor), method="lm",
                                  jac=_forward_differences(free), x_scale=[1.0, 1.0, 0.1]).x
            if not any(_same_frame(frame, other) for other in minima):
                minima.append(frame)
        batch, others = _residual_function(entries, odometry, sensor)
        residuals = _one(batch)
        solutions = []
        for frame in minima:
            fit = least_squares(residuals, np.concatenate([frame, np.zeros(3 * others)]), method="lm",
                                jac=_forward_differences(batch), x_scale=[1.0, 1.0, 0.1] + [0.1, 0.1, 0.01] * others)
            solutions.append((2.0 * fit.cost, fit.x, fit.jac))
        solutions.sort(key=lambda item: item[0])
        chi2, unknowns, jacobian = solutions[0]
        dof = residuals(unknowns).size - unknowns.size  # the priors' residuals balance their unknowns
        if dof <= 0 or chi2 > chi2_quantile(0.999, dof):
            return None
        information = jacobian.T @ jacobian
        if np.linalg.cond(information) > 1e12:
            return None
        frame = unknowns[:3]
        lever = compose_start_jacobian(frame, self.odometry)
        pose = se2_compose(frame, self.odometry)
        cov = lever @ np.linalg.inv(information)[:3, :3] @ lever.T
        if math.sqrt(cov[0, 0] + cov[1, 1]) > self.max_std_xy or math.sqrt(cov[2, 2]) > self.max_std_theta:
            return None
        margin = chi2_quantile(0.99, 3)
        for other_chi2, other_unknowns, _ in solutions[1:]:
            other = se2_compose(other_unknowns[:3], self.odometry)
            apart = math.hypot(*(other[:2] - pose[:2])) > 0.5 or abs(wrap_angle(other[2] - pose[2])) > 0.3
            if apart and other_chi2 <= chi2 + margin:
                return None
        pose[2] = wrap_angle(pose[2])
        return MeetingFix(pose, 0.5 * (cov + cov.T), len(entries), float(chi2))


def _same_frame(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two frames are one minimum (within 1 cm and 0.01 rad)."""
    return math.hypot(*(a[:2] - b[:2])) < 0.01 and abs(wrap_angle(a[2] - b[2])) < 0.01


def _residual_function(entries: list[_Logged], odometry: np.ndarray, sensor: RangeBearingSensor,
                       shared: bool = True):
    """(whitened residuals ``(B, m)`` of every meeting for a batch ``(B, n)`` of unknowns, how many placed robots'
    pose errors are unknowns).

    The unknowns are the frame (the world pose of the odometry's origin) and, per placed robot named by the
    meetings (``shared``), an error δ ``(3,)`` added to every pose of it the meetings hold, with its covariance
    as a prior (one residual block per robot). A meeting with a named robot is weighed by the detection's noise
    alone, its prediction moved by δ to first order; a meeting with an unnamed one (or without ``shared``)
    carries that robot's covariance itself."""
    names = sorted({e.meeting.other_id for e in entries if shared and e.meeting.other_id is not None})
    group = np.array([names.index(e.meeting.other_id) if e.meeting.other_id in names else len(names)
                      for e in entries], np.int64)  # len(names): the row of zeros (no shared error)
    prior_whiten = []
    for name in names:
        covs = [e.meeting.other_cov for e in entries if e.meeting.other_id == name]
        prior_whiten.append(np.linalg.inv(np.linalg.cholesky(np.mean(covs, 0) + 1e-12 * np.eye(3))))
    prior_whiten = np.array(prior_whiten).reshape(-1, 3, 3)
    named = group < len(names)

    seen = [k for k, e in enumerate(entries) if e.meeting.by_other]
    saw = [k for k, e in enumerate(entries) if not e.meeting.by_other]
    means, whiten, shift = [], [], []
    for k in seen:
        meeting = entries[k].meeting
        mean, g_pose, detection_cov = meeting.position_terms()  # one inverse and its Jacobians per meeting
        cov = detection_cov if named[k] else g_pose @ meeting.other_cov @ g_pose.T + detection_cov
        means.append(mean)
        whiten.append(np.linalg.inv(np.linalg.cholesky(cov)))
        shift.append(g_pose)  # how the placed robot's error δ moves the position
    means, whiten = np.array(means).reshape(-1, 2), np.array(whiten).reshape(-1, 2, 2)
    shift = np.array(shift).reshape(-1, 2, 3)
    others = np.array([entries[k].meeting.other_pose[:2] for k in saw], float).reshape(-1, 2)
    other_covs = np.array([entries[k].meeting.other_cov[:2, :2] if not named[k] else np.zeros((2, 2))
                           for k in saw], float).reshape(-1, 2, 2)
    z = np.array([entries[k].meeting.z for k in saw], float).reshape(-1, 2)
    noise = np.array([entries[k].meeting.noise_cov for k in saw], float).reshape(-1, 2, 2)

    def residuals(unknowns: np.ndarray) -> np.ndarray:
        batch = unknowns.shape[0]
        errors = np.concatenate([unknowns[:, 3:].reshape(batch, -1, 3), np.zeros((batch, 1, 3))], 1)[:, group]
        poses = se2_compose(unknowns[:, None, :3], odometry)
        moved = means + np.einsum("kij,bkj->bki", shift, errors[:, seen])
        out = [np.einsum("kij,bkj->bki", whiten, poses[:, seen, :2] - moved).reshape(batch, -1)]
        if saw:
            predicted, h_other = sensor.observe_with_jacobian(poses[:, saw, None, :], others[:, None, :])
            h_other = h_other[..., 0, :, :]
            nu = sensor.innovation(z, predicted[..., 0, :]) - np.einsum("bkij,bkj->bki", h_other, errors[:, saw, :2])
            cov = noise + h_other @ other_covs @ np.swapaxes(h_other, -1, -2)
            out.append(np.einsum("bkij,bkj->bki", np.linalg.inv(np.linalg.cholesky(cov)), nu).reshape(batch, -1))
        out.append(np.einsum("gij,bgj->bgi", prior_whiten, unknowns[:, 3:].reshape(batch, -1, 3)).reshape(batch, -1))
        return np.concatenate(out, 1)

    return residuals, len(names)


def _one(batch):
    """The residuals of one vector of unknowns, from a function of a batch ``(B, n)`` of them."""
    return lambda unknowns: batch(unknowns[None])[0]


def _forward_differences(batch):
    """The Jacobian of ``batch``'s residuals by forward differences, scipy's ``jac="2-point"`` steps (√ε·max(1, |x|),
    signed as x), with every shifted copy of the unknowns evaluated in one call of ``batch`` instead of one each:
    the solves are dominated by numpy's per-call overhead on a few meetings."""
    def jacobian(unknowns: np.ndarray) -> np.ndarray:
        step = _FORWARD_STEP * np.where(unknowns >= 0.0, 1.0, -1.0) * np.maximum(1.0, np.abs(unknowns))
        taken = (unknowns + step) - unknowns
        values = batch(np.vstack([unknowns, unknowns + np.diag(step)]))
        return ((values[1:] - values[0]) / taken[:, None]).T

    return jacobian


def _start(entry: _Logged, odometry: np.ndarray, heading: float, sensor: RangeBearingSensor) -> np.ndarray:
    """A frame with the given heading that puts the robot where its first meeting says."""
    meeting = entry.meeting
    theta = heading + odometry[2]  # the robot's heading at the meeting
    if meeting.by_other:
        position = meeting.position()[0]
    else:  # the sensor at the measured range from the other robot, looking at it with the measured bearing
        position = sensor.pose_seeing(meeting.other_pose[:2], meeting.z, theta + meeting.z[1])[:2]
    c, s = math.cos(heading), math.sin(heading)
    return np.array([position[0] - (c * odometry[0] - s * odometry[1]),
                     position[1] - (s * odometry[0] + c * odometry[1]), heading])



@dataclass(frozen=True)
class Sighting:
    """A detection in a scan between ``subject`` (being localized) and ``other`` (placed): ``by_other``, the other
    robot's sensor made it; ``z`` (range, bearing)."""

    subject: str
    other: str
    by_other: bool
    z: np.ndarray


class MeetingDesk:
    """The meetings of a fleet, offline (:class:`services.placement.FleetPlacer`) and live (the MCL service) alike:
    each robot's models and :class:`MeetingLog` (its dead reckoning fed by :meth:`move`), which detections of a
    scan are meetings (:meth:`sightings`), and what a meeting does to the robot (:meth:`meet`). A solve takes
    tens of milliseconds with a full log: live, where meetings keep coming at the scan rate of every robot that
    sees the robot, it runs every ``solve_every`` meetings."""

    def __init__(self, solve_every: int = 1):
        self.solve_every = solve_every
        self.logs: dict[str, MeetingLog] = {}
        self.models: dict[str, tuple] = {}
        self.unsolved: dict[str, int] = {}  # meetings added since the robot's last solve

    def add_robot(self, info) -> None:
        """Know a robot (its RobotInfo): its models, and a meeting log that starts from here."""
        self.models[info.robot_id] = robot_models(info)
        self.logs[info.robot_id] = MeetingLog()

    def move(self, event: OdomEvent) -> None:
        """One odometry reading of a known robot moves its dead-reckoned pose."""
        log = self.logs.get(event.robot_id)
        if log is not None:
            motion = self.models[event.robot_id][0]
            log.move(motion.step(log.odometry[None], np.asarray(event.control, float)[None], event.dt)[0])

    @staticmethod
    def sightings(event: ScanEvent, localizing, placed) -> list[Sighting]:
        """The scan's detections between a robot ``localizing(rid)`` and a robot ``placed(rid)``, either way."""
        observer = event.robot_id
        found = []
        for rid, r, b in zip(event.robot_ids, np.asarray(event.robot_ranges, float).tolist(),
                             np.asarray(event.robot_bearings, float).tolist()):
            if placed(observer) and localizing(rid):
                found.append(Sighting(rid, observer, True, np.array([r, b])))
            elif localizing(observer) and placed(rid):
                found.append(Sighting(observer, rid, False, np.array([r, b])))
        return found

    def meeting(self, sighting: Sighting, other_pose, other_cov, noise_cov) -> Meeting:
        """The :class:`Meeting` of a sighting, the placed robot at ``other_pose`` (``other_cov``)."""
        return Meeting(np.asarray(other_pose, float), np.asarray(other_cov, float), sighting.z,
                       np.asarray(noise_cov, float), sighting.by_other, self.models[sighting.other][1], sighting.other)

    def meet(self, subject: str, meeting: Meeting, mcl=None, solve: bool = True) -> tuple[bool, MeetingFix | None]:
        """Keep a meeting for ``subject``, check its localizer ``mcl`` (if any) against it: (whether the
        localization started again from the meeting, the pose its meetings now fix — None while they do not, or
        without ``solve``, or before ``solve_every`` meetings were added since the last solve)."""
        restarted = bool(mcl is not None and mcl.meet(meeting))
        log = self.logs[subject]
        log.add(meeting)
        self.unsolved[subject] = self.unsolved.get(subject, 0) + 1
        if not solve or self.unsolved[subject] < self.solve_every:
            return restarted, None
        self.unsolved[subject] = 0
        return restarted, log.solve(self.models[subject][1])

    def contradicts(self, rid: str, pose) -> bool:
        """Whether ``pose`` (the robot's now) lies outside the gate of one of its recent meetings."""
        return rid in self.logs and self.logs[rid].contradicts(np.asarray(pose, float), self.models[rid][1])

    def latest(self, rid: str) -> Meeting | None:
        return self.logs[rid].latest() if rid in self.logs else None


class PlacedPoses:
    """Live: where the placed robots are at the moment a scan is handled, from estimates that lag behind it.

    An estimate gives a robot's pose at its own stamp; the robot's dead-reckoned poses (:attr:`MeetingDesk.logs`,
    kept here for ``trail`` readings) carry it to the scan's instant: the world pose of the odometry's origin is
    taken at the estimate's stamp, and the robot is that frame composed with its dead-reckoned pose then. The estimate's
    covariance is kept as it is (the odometry between the two instants, under a second, adds little)."""

    def __init__(self, trail: int = 600, ahead_s: float = 0.25):
        self.trail = trail
        self.ahead_s = ahead_s
        self.stamps: dict[str, deque] = {}
        self.odometry: dict[str, deque] = {}
        self.frames: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        self.pending: dict[str, deque] = {}  # estimates ahead of the robot's dead reckoning, oldest first

    def move(self, rid: str, stamp: float, odometry: np.ndarray) -> None:
        """The robot's dead-reckoned pose after its reading at ``stamp``; an estimate that waited for it is taken."""
        if rid not in self.stamps:
            self.stamps[rid], self.odometry[rid] = deque(maxlen=self.trail), deque(maxlen=self.trail)
        self.stamps[rid].append(float(stamp))
        self.odometry[rid].append(np.asarray(odometry, float).copy())
        waiting = self.pending.get(rid)
        while waiting and waiting[0][0] <= stamp + 1e-9:
            self._take(rid, *waiting.popleft())

    def estimate(self, rid: str, stamp: float, pose, cov) -> None:
        """The robot's estimated pose at ``stamp``: taken now if its dead reckoning reaches that stamp, kept until
        it does if the estimate is ahead of it (up to ``trail`` estimates), dropped if it is older than the trail."""
        stamps = self.stamps.get(rid)
        if stamps and stamp <= stamps[-1] + 1e-9:
            self._take(rid, stamp, pose, cov)
        else:
            self.pending.setdefault(rid, deque(maxlen=self.trail)).append((float(stamp), pose, cov))

    def _take(self, rid: str, stamp: float, pose, cov) -> None:
        if stamp < self.stamps[rid][0] - 1e-9:
            return
        frame = se2_compose(np.asarray(pose, float), se2_inverse(self._odometry_at(rid, stamp)))
        self.frames[rid] = (frame, np.asarray(cov, float))

    def _odometry_at(self, rid: str, stamp: float) -> np.ndarray:
        """The robot's dead-reckoned pose after its last reading at or before ``stamp`` (not before the first)."""
        k = int(np.searchsorted(np.asarray(self.stamps[rid]), stamp + 1e-9, side="right")) - 1
        return self.odometry[rid][max(k, 0)]

    def __contains__(self, rid: str) -> bool:
        return rid in self.frames

    def pose_at(self, rid: str, stamp: float) -> tuple[np.ndarray, np.ndarray] | None:
        """(pose, covariance) of a robot with an estimate at ``stamp`` (its last reading at or before it: a robot's
        held scans can be handled after the others' later readings); None when its readings do not span that
        instant (older than the trail, or later than its last reading by more than ``ahead_s``)."""
        if rid not in self.frames:
            return None
        stamps = self.stamps[rid]
        if stamp < stamps[0] - 1e-9 or stamp > stamps[-1] + self.ahead_s:
            return None
        frame, cov = self.frames[rid]
        pose = se2_compose(frame, self._odometry_at(rid, stamp))
        pose[2] = wrap_angle(pose[2])
        return pose, cov

    def forget(self, rid: str) -> None:
        for table in (self.stamps, self.odometry, self.frames, self.pending):
            table.pop(rid, None)
