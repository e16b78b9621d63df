"""How loose a robot's announced odometry covariance is, measured from the robot's own landmark detections.

A robot announces the covariance of its odometry; a filter should draw what the odometry really does, no more and no
less. Announcements are often loose (Victoria Park announces the ACFR example's σ 0.7 m/s and 7°, several times its
real scatter) and sometimes right (MR.CLAM's were fitted against Vicon), so one fixed scale fitted to one data set
is wrong for the other. This estimator learns, per robot, the gain g by which the announced covariance should be
multiplied, from data the filter cannot bias:

- the robot's dead reckoning is kept on its own (the controls' means composed, never corrected);
- each detection of a landmark (by the association's id) is placed in the dead-reckoned frame; when the robot
  detects the same landmark again, the two places differ by the dead reckoning's error in between and the two
  detections' own errors (landmarks stand still). Their difference d has covariance
  C(g) = g·D + P₁ + P₂, D the dead reckoning's covariance between the two detections carried to the landmark's
  place (every increment's error, its heading part levered from where the increment ended to the landmark:
  :func:`displacement_cov`, kept as running sums so any interval costs O(1)), P₁, P₂ the detections' own;
- a pair counts only when the odometry's part is at least the sensor's (g·tr D ≥ tr(P₁ + P₂)): otherwise the pair
  says nothing about g. The first detection of a landmark stays the anchor until such a pair is made;
- g follows the median of d² = dᵀC(g)⁻¹d (a quantile tracker, Robbins-Monro): up by 2^step when d² exceeds the
  χ²(2) median (2 ln 2), down when not, the step shrinking as pairs come (:meth:`OdometryNoiseGain.step_gain`). Where it settles, half the pairs lie beyond the median: C(g) fits. The
  median, not the mean, so a wrong association or wheel slip's heavy tail cannot throw it.

It is the online form of ``benchmarks/odometry_noise.py``'s check (pairs of detections of one landmark against the
model's prediction), with the shared association's ids instead of a distance gate.

The same pairs measure a robot's turn scale s (its true turn is s × what its odometry says; MR.CLAM's robots
over-count their turns by 4–10 %), which no covariance can stand for: an error that always has one
sign adds up over every turn, and a robot that turns blind comes back with its heading tens of degrees off. A turn
of the dead reckoning over-counted by ε_k at the increment ending at x_k moves the place of a landmark at p by
ε_k·J(p − x_k). With ε_k = (1 − s)·Δθ_k that is d ≈ (1 − s)·v, v = J(p·ΣΔθ_k − ΣΔθ_k x_k) (two more running
sums). A pair's estimate of 1 − s, vᵀd/|v|², has the σ √(tr(P₁ + P₂))/|v| from the detections alone; it counts
when that is at most ``TURN_SCALE_SD`` (0.1). Pairs with shorter levers (small turns, where MR.CLAM's odometry
over-counts more in proportion) drew the scale 3–5 % below what the large turns show. Each counted pair steps the
scale by the same kind of quantile tracker (the median, so a wrong association cannot throw it), and the motion
turns by s × the odometry's turn (:attr:`OdometryNoiseGain.turn_scale`): the pairs then measure what is left of it.
"""

from __future__ import annotations

import math

import numpy as np

from robots.models import wrap_angle

CHI2_2_MEDIAN = 2.0 * math.log(2.0)
TURN_SCALE_BOUNDS = (0.8, 1.25)  # a turn scale beyond these is not an odometry's calibration to learn
TURN_SCALE_SD = 0.1  # a pair counts for the turn scale when it measures it this well (σ of its estimate)


def increment_sums(cov: np.ndarray, heading: float, end: np.ndarray) -> list[float]:
    """The running sums one dead-reckoning increment adds (:func:`displacement_cov`): its covariance ``cov`` (in the
    robot's frame at ``heading``, turned here into the world frame) and ``w`` = J·``end`` (J the quarter turn,
    ``end`` where the increment ended): Q_xx (4), Q_xθ (2), Q_xθ wᵀ (4), Q_θθ, Q_θθ w (2), Q_θθ w wᵀ (4)."""
    c, s = math.cos(heading), math.sin(heading)
    a00, a01, a02 = cov[0][0], cov[0][1], cov[0][2]
    a11, a12, t = cov[1][1], cov[1][2], cov[2][2]
    r00, r01 = c * a00 - s * a01, c * a01 - s * a11  # R Σ_xx Rᵀ, R Σ_xθ
    r10, r11 = s * a00 + c * a01, s * a01 + c * a11
    q00, q01, q11 = r00 * c - r01 * s, r00 * s + r01 * c, r10 * s + r11 * c
    b0, b1 = c * a02 - s * a12, s * a02 + c * a12
    w0, w1 = -float(end[1]), float(end[0])
    return [q00, q01, q01, q11, b0, b1, b0 * w0, b0 * w1, b1 * w0, b1 * w1,
            t, t * w0, t * w1, t * w0 * w0, t * w0 * w1, t * w1 * w0, t * w1 * w1]


def displacement_cov(sums, point) -> tuple[float, float, float]:
    """Covariance (xx, xy, yy) of where a landmark at ``point`` is placed, from the dead reckoning's errors of the
    increments whose :func:`increment_sums` add up to ``sums``: each increment's error ε moves the place by
    ε_xy + ε_θ·J(point − x_k), so the covariance is Σ_k B_k Q_k B_kᵀ, B_k = [I | J(point − x_k)], which expands
    into the running sums of Q_xx, Q_xθ, Q_xθ w_kᵀ, Q_θθ, Q_θθ w_k and Q_θθ w_k w_kᵀ (w_k = J x_k):
    A + b uᵀ + u bᵀ − C − Cᵀ + q u uᵀ − u mᵀ − m uᵀ + W with u = J·point."""
    a00, a01, _, a11, b0, b1, c00, c01, c10, c11, q, m0, m1, w00, w01, _, w11 = sums[:17]
    u0, u1 = -float(point[1]), float(point[0])
    xx = a00 + 2.0 * b0 * u0 - 2.0 * c00 + q * u0 * u0 - 2.0 * u0 * m0 + w00
    xy = a01 + b0 * u1 + u0 * b1 - c01 - c10 + q * u0 * u1 - u0 * m1 - m0 * u1 + w01
    yy = a11 + 2.0 * b1 * u1 - 2.0 * c11 + q * u1 * u1 - 2.0 * u1 * m1 + w11
    return xx, xy, yy


class OdometryNoiseGain:
    """One robot's gain on its announced odometry covariance (module docstring). ``move`` with each applied motion
    (the announced covariance, not the scaled one), ``scan`` with the scan's detections of identified landmarks."""

    def __init__(self, gain: float = 1.0, min_gain: float = 2.0**-6, max_gain: float = 1.0, step: float = 0.02,
                 first_step: float = 0.5, turn_scale_bounds: tuple[float, float] | None = None,
                 turn_step: float = 0.002, turn_first_step: float = 0.03):
        self.gain = float(min(max(gain, min_gain), max_gain))
        self.min_gain, self.max_gain, self.step, self.first_step = min_gain, max_gain, step, first_step
        self.pose = [0.0, 0.0, 0.0]  # dead reckoning, in its own frame
        self.sums = [0.0] * 20  # increment_sums' 17, then ΣΔθ, ΣΔθ x, ΣΔθ y (the turn scale's)
        self.anchors: dict[int, tuple[list, np.ndarray, np.ndarray]] = {}  # id → (sums, place, its covariance)
        self.pairs = 0
        self.turn_scale = 1.0  # what the motion should multiply the odometry's turn by (1 while it does not adapt)
        self.turn_scale_bounds = turn_scale_bounds  # None: the turn scale stays 1
        self.turn_step, self.turn_first_step = turn_step, turn_first_step
        self.turn_pairs = 0

    def move(self, delta, cov) -> None:
        """Compose one motion (``delta`` in the robot's frame, its announced covariance ``cov``) onto the dead
        reckoning and add its error to the running sums."""
        x, y, heading = self.pose
        dx, dy, dt = (float(v) for v in delta)
        c, s = math.cos(heading), math.sin(heading)
        self.pose = [x + c * dx - s * dy, y + s * dx + c * dy, float(wrap_angle(heading + dt))]
        added = increment_sums(np.asarray(cov, float).tolist(), heading, self.pose)
        added += [dt, dt * self.pose[0], dt * self.pose[1]]
        self.sums = [a + b for a, b in zip(self.sums, added)]

    def scan(self, offset: tuple[float, float], ids, z, r) -> None:
        """:meth:`detect` for detections ``z`` ``(m, 2)`` (range, bearing) of landmarks ``ids`` by a sensor at
        ``offset`` (a, b) on the robot with noise ``r`` ``(2, 2)``, placed from the dead reckoning
        (:meth:`robots.models.RangeBearingSensor.inverse` and its Jacobian in the detection, in scalars)."""
        x, y, heading = self.pose
        a, b = offset
        c, s = math.cos(heading), math.sin(heading)
        px, py = x + a * c - b * s, y + a * s + b * c
        (r00, r01), (_, r11) = np.asarray(r, float).tolist()
        places, covs = [], []
        for distance, bearing in np.asarray(z, float).tolist():
            cb, sb = math.cos(heading + bearing), math.sin(heading + bearing)
            places.append((px + distance * cb, py + distance * sb))
            g00, g01, g10, g11 = cb, -distance * sb, sb, distance * cb  # G R Gᵀ, G = d(place)/d(range, bearing)
            t00, t01, t10, t11 = g00 * r00 + g01 * r01, g00 * r01 + g01 * r11, g10 * r00 + g11 * r01, g10 * r01 + g11 * r11
            xy = t00 * g10 + t01 * g11
            covs.append(((t00 * g00 + t01 * g01, xy), (xy, t10 * g10 + t11 * g11)))
        self.detect(ids, places, covs)

    def detect(self, ids, places, place_covs) -> None:
        """Detections of landmarks ``ids`` ``(m,)`` placed at ``places`` ``(m, 2)`` from the dead reckoning, with the
        sensor's share of their covariance ``place_covs`` ``(m, 2, 2)``: pair each with its landmark's anchor and step
        the gain by the pairs that speak about it."""
        for lid, place, cov in zip(list(ids), places, place_covs):
            anchor = self.anchors.get(lid)
            if anchor is None:
                self.anchors[lid] = (self.sums, place, cov)
                continue
            sums, before, before_cov = anchor
            between = [a - b for a, b in zip(self.sums, sums)]
            xx, xy, yy = displacement_cov(between, place)
            s00, s01, s11 = cov[0][0] + before_cov[0][0], cov[0][1] + before_cov[0][1], cov[1][1] + before_cov[1][1]
            if self.gain * (xx + yy) < s00 + s11:
                continue  # the sensor's error would decide: this pair says nothing about the odometry
            self.anchors[lid] = (self.sums, place, cov)
            t00, t01, t11 = self.gain * xx + s00, self.gain * xy + s01, self.gain * yy + s11
            d0, d1 = place[0] - before[0], place[1] - before[1]
            self.step_turn_scale(between[17:], place, (d0, d1), s00 + s11)
            d2 = (t11 * d0 * d0 - 2.0 * t01 * d0 * d1 + t00 * d1 * d1) / (t00 * t11 - t01 * t01)
            self.step_gain(d2 > CHI2_2_MEDIAN)
            self.pairs += 1

    def step_turn_scale(self, turn_sums, place, d, sensor_trace: float) -> None:
        """One pair's say on the turn scale (module docstring): ``turn_sums`` (ΣΔθ, ΣΔθ x, ΣΔθ y) between its two
        detections, ``place`` the second, ``d`` their difference, ``sensor_trace`` tr(P₁ + P₂)."""
        if self.turn_scale_bounds is None:
            return
        turned, mx, my = turn_sums
        w0, w1 = place[0] * turned - mx, place[1] * turned - my
        v0, v1 = -w1, w0  # v = J·w
        lever = v0 * v0 + v1 * v1
        if lever * TURN_SCALE_SD**2 < sensor_trace:
            return  # the detections' own errors would blur what the turns between them did
        over = (v0 * d[0] + v1 * d[1]) / lever  # 1 − s of what is left: > 0 when the odometry over-counts
        if over == 0.0:
            return
        size = max(self.turn_step, self.turn_first_step / math.sqrt(self.turn_pairs + 1.0))
        low, high = self.turn_scale_bounds
        self.turn_scale = min(max(self.turn_scale * 2.0 ** (-size if over > 0 else size), low), high)
        self.turn_pairs += 1

    def step_gain(self, looser: bool) -> None:
        """One step of the quantile tracker, in powers of 2: ``first_step``/√(pairs + 1), at least ``step``, so
        the first pairs move the gain fast (a short run has few) and later ones only refine it."""
        size = max(self.step, self.first_step / math.sqrt(self.pairs + 1.0))
        gain = self.gain * 2.0 ** (size if looser else -size)
        self.gain = min(max(gain, self.min_gain), self.max_gain)
