"""Monte Carlo localization on a landmark map, in the six variants of Sehestedt and Schneider, "Monte Carlo
Localization in Highly Symmetric Environments".

One :class:`MonteCarloLocalizer` tracks one robot. Odometry moves the
particles (:meth:`predict`, Table 1 step 1); each scan runs the rest of the
variant's table (:meth:`update`). The filter only looks at its particles at a scan, so odometry is buffered
and applied once per scan (or every ``max_batch_s``), each particle drawing once from the controls integrated
into one Gaussian relative motion (:func:`robots.models.integrate_controls`, as FastSLAM predicts): at 67 Hz
odometry and a few scans a second, one draw per scan instead of twenty.

- ``mcl``: weigh, resample systematically (Table 1).
- ``kld``: weigh, resample with KLD-sampling: draw until n ≥ N(k) (Fox 2003, eq. 2).
- ``srl``: weigh, resample, replace N_s = (1 − P̃/P_t)·N particles by poses drawn
  from the scan (sensor resetting, eq. 1).
- ``kld_srl`` (Table 2): N from eq. 2 on the predicted set; if N > N_old add
  N − N_old poses drawn from the scan; weigh; resample to N.
- ``csrl`` (Table 3): weigh, cluster, two-stage resampling, and sensor
  resetting only while there is at most one significant cluster.
- ``cluster_kld_srl`` (Table 4): as kld_srl, but the sample size only shrinks
  while there is one significant cluster; two-stage resampling.

Every variant clusters the weighted set after each scan to report its
hypotheses, and detects a kidnapping (no cluster explains the scans for
``kidnap_scans`` scans in a row), after which it starts global localization
again from the scan. Poses drawn from a scan are weighed by the whole scan's
likelihood; a sample added before the update (KLD-SRL) enters the update
with the candidates' mean likelihood rather than its own, so the scan is not
counted twice for it, and with a prior weight of ``reset_prior`` times a
tracked particle's: a new hypothesis must explain the scans clearly better
than the tracked ones before it becomes significant. Poses drawn from a scan must also explain the robot's
last few scans, carried back along its odometry (:mod:`services.mcl.history`, ``history_scans``): one to three
detections fit many places, the scans before them far fewer (not with signatures: those name their landmarks).
A detection between the robot and a robot whose pose is known (:meth:`MonteCarloLocalizer.meet`) starts the
localization again from the poses it allows when no particle agrees with it (:mod:`services.mcl.meeting`).

Signatures: when the map has landmark ids and a scan's detections carry ids (``use_signatures``), each
detection is weighed against its own landmark only and poses are drawn around it
(:func:`~services.mcl.likelihood.signed_log_likelihood`); detections of landmarks not in the map are left
out. A robot among distinguishable landmarks is then localized from a couple of detections, symmetry or not.
After global localization a hypothesis that looks localized must also explain, by id, detections of two
landmarks ``localized_baseline_m`` apart; a signed detection it contradicts starts global localization again.
"""

from __future__ import annotations

import math
import typing
from dataclasses import dataclass

import numpy as np

from robots.gaussian import chi2_quantile, quad2, sqrt_psd, systematic_resample
from robots.kernels import integrate_controls as integrate_compiled
from robots.models import integrate_controls, robot_models, se2_compose, wrap_angle
from schemas.messages import RobotInfo
from services.mcl.clustering import Clusters, cluster_particles
from services.mcl.config import MclConfig
from services.mcl.history import ScanHistory
from services.mcl import meeting as meetings
from services.mcl.kld import bin_keys, kld_prefix_size, kld_sample_size, support
from services.mcl.likelihood import (
    LandmarkMap, MapCache, ScanModel, poses_from_signatures, scan_log_likelihood, signed_log_likelihood,
)
from services.mcl.resampling import two_stage_resample
from services.mcl.resetting import poses_from_scan, uniform_poses

VARIANTS: tuple[str, ...] = typing.get_args(MclConfig.model_fields["variant"].annotation)
ADAPTIVE = frozenset({"kld_srl", "cluster_kld_srl"})
CLUSTERED = frozenset({"csrl", "cluster_kld_srl"})
RESETTING = frozenset({"srl", "csrl"})
CONTRADICTION_GATE = chi2_quantile(0.999, 2)  # a signed detection farther than this (d²) contradicts a hypothesis


@dataclass
class Hypothesis:
    """One significant cluster: mean pose, covariance, weight share, particle count."""

    mean: np.ndarray
    cov: np.ndarray
    weight: float
    particles: int


@dataclass
class UpdateReport:
    """What one scan did to the filter."""

    particles_before: int
    particles_after: int
    added: int  # poses drawn from the scan (added by KLD-SRL, replaced by SRL, or a restart)
    quality: float  # P̃: mean match quality of the particles
    best_quality: float  # mean quality of the heaviest cluster
    hypotheses: int  # significant clusters
    kidnapped: bool  # the filter declared itself lost and restarted
    localized: bool


class MonteCarloLocalizer:
    """Particle filter over one robot's pose (x, y, θ) on a fixed landmark map."""

    def __init__(self, landmarks: np.ndarray, info: RobotInfo, config: MclConfig,
                 rng: np.random.Generator | None = None, landmark_ids: np.ndarray | None = None,
                 maps: MapCache | None = None):
        if config.variant not in VARIANTS:
            raise ValueError(f"unknown MCL variant {config.variant!r}; choose from {', '.join(VARIANTS)}")
        self.config = config
        self.variant = config.variant
        self.rng = rng if rng is not None else np.random.default_rng(config.seed)
        self.motion, _ = robot_models(info)
        self.model = ScanModel.from_spec(
            info.sensor, config.noise_scale, config.clutter_weight, config.miss_floor,
            config.view_margin_range, config.view_margin_bearing, config.match_sigmas,
        )
        self.map = self._prepared(landmarks, maps)
        self.slot_of: dict[int, int] = {}
        self._targets: np.ndarray | None = None  # landmarks of the current scan's signed detections
        self._set_ids(landmark_ids)
        self._particles = np.zeros((0, 3))
        self._pending: list[tuple[np.ndarray, float, np.ndarray]] = []  # (control, dt, covariance) not applied yet
        self._pending_s = 0.0
        self.weights = np.zeros(0)
        self.size = config.particles  # N_old: the sample size the next resampling draws
        self.clusters: Clusters | None = None
        self.significant = np.zeros(0, np.int64)
        self.restarts = 0
        self.kidnaps = 0
        self._localized_run = 0
        self._lost_run = 0
        self.contradictions = 0  # global localizations started again because a signed detection contradicted
        self._confirmed: set[tuple[float, float]] = set()  # landmarks the dominant hypothesis has explained by id
        self._must_confirm = False  # a global localization with signed detections waits for _confirmed's baseline
        self._global = False  # the particles come from a global localization (not from a known start pose)
        self.last_report: UpdateReport | None = None
        self.history = ScanHistory(config.history_scans, config.history_turn)
        self.meetings = 0  # detections between this robot and robots whose pose is known, checked against it
        self._met_afresh = False  # a meeting started the localization again: the next update is a fresh start
        if info.start_pose is not None:
            self.initialize_at(info.start_pose, info.start_pose_cov)

    def __setstate__(self, state: dict) -> None:
        """Unpickle (a service checkpoint); one written before the scan history or the meetings existed starts with
        an empty history and no meetings."""
        self.__dict__.update(state)
        if "particles" in state:  # written before odometry was buffered
            self.__dict__["_particles"] = self.__dict__.pop("particles")
        self.__dict__.setdefault("_pending", [])
        self.__dict__.setdefault("_pending_s", 0.0)
        if "history" not in state:
            self.history = ScanHistory(self.config.history_scans, self.config.history_turn)
        self.__dict__.setdefault("meetings", 0)
        self.__dict__.setdefault("_met_afresh", False)

    # ----------------------------------------------------------------- state

    @property
    def particles(self) -> np.ndarray:
        """The particles ``(n, 3)``, moved by the odometry buffered so far."""
        self._apply_pending()
        return self._particles

    @particles.setter
    def particles(self, poses: np.ndarray) -> None:
        """A new set of particles at the present time (the buffered odometry moved the set it replaces)."""
        self._particles = poses
        self._pending, self._pending_s = [], 0.0

    @property
    def initialized(self) -> bool:
        return self._particles.shape[0] > 0

    @property
    def count(self) -> int:
        return int(self._particles.shape[0])

    @property
    def localized(self) -> bool:
        return self._localized_run >= self.config.localized_scans and not self._unconfirmed()

    def _unconfirmed(self) -> bool:
        """Whether the hypothesis still has to explain two landmarks ``localized_baseline_m`` apart by id."""
        if not self._must_confirm or self.config.localized_baseline_m <= 0:
            return False
        if len(self._confirmed) < 2:
            return True
        points = np.array(sorted(self._confirmed))
        return float(np.max(np.linalg.norm(points[:, None] - points[None], axis=-1))) < self.config.localized_baseline_m

    def _contradicted(self, z: np.ndarray) -> bool:
        """Check the heaviest hypothesis of a global localization, dominant at the last scan and not confirmed
        yet, against the scan's signed detections: True if one lies outside the χ²(2) 0.999 gate of its landmark (the
        localization must start again), else their landmarks count towards the confirmation."""
        if self._targets is None or self.config.localized_baseline_m <= 0:
            return False
        self._must_confirm = self._must_confirm or self._global
        if not self._must_confirm or self.localized or not self._localized_run:
            return False  # check a hypothesis that was dominant at the last scan and is not localized yet
        best = self.best()
        if best is None:
            return False
        nu = self.model.sensor.innovation(z, self.model.sensor.observe(best[0], self._targets))
        if np.any(quad2(nu, self.model.information) > CONTRADICTION_GATE):
            return True
        self._confirmed.update(map(tuple, self._targets.tolist()))
        return False

    def set_map(self, landmarks: np.ndarray, landmark_ids: np.ndarray | None = None,
                maps: MapCache | None = None) -> None:
        """Replace the map (a newer estimate of it, with its landmark ids if it has them); the particles stay."""
        self.map = self._prepared(landmarks, maps)
        self._set_ids(landmark_ids)

    def _prepared(self, landmarks: np.ndarray, maps: MapCache | None) -> LandmarkMap:
        """The map prepared for this filter's sensor, from ``maps`` when given (shared with other filters)."""
        build = LandmarkMap if maps is None else maps.get
        return build(landmarks, self.model, self.config.lookup_cell, self.config.match_candidates)

    def _set_ids(self, landmark_ids: np.ndarray | None) -> None:
        if landmark_ids is None or not self.config.use_signatures:
            self.slot_of = {}
            return
        ids = np.asarray(landmark_ids).reshape(-1)
        if ids.size != self.map.count:
            raise ValueError(f"{ids.size} landmark ids for {self.map.count} landmarks")
        self.slot_of = {int(i): k for k, i in enumerate(ids.tolist())}

    def _signed(self, observations: np.ndarray, ids) -> np.ndarray:
        """The observations the scan is weighed by: with signatures (map and detections both with ids), those
        of mapped landmarks, remembering their landmarks for this scan; otherwise all of them."""
        z = np.asarray(observations, float).reshape(-1, 2)
        self._targets = None
        if not self.slot_of or ids is None:
            return z
        slots = np.array([self.slot_of.get(int(i), -1) for i in np.asarray(ids).reshape(-1)], np.int64)
        if slots.size != z.shape[0]:
            return z  # ids that do not match the detections: no signatures
        mapped = slots >= 0
        if mapped.any():
            self._targets = self.map.landmarks[slots[mapped]]
        return z[mapped]

    def initialize_at(self, pose: np.ndarray, cov: np.ndarray | None = None, count: int | None = None) -> None:
        """Position tracking: particles drawn around a known pose."""
        count = count or self.config.particles
        self.size = count
        cov = np.diag([1e-4, 1e-4, 1e-6]) if cov is None else np.asarray(cov, float)
        self._global, self._must_confirm, self._confirmed = False, False, set()
        self.particles = np.asarray(pose, float) + self.rng.standard_normal((count, 3)) @ sqrt_psd(cov).T
        self.particles[:, 2] = wrap_angle(self.particles[:, 2])
        self.weights = np.full(count, 1.0 / count)
        self._recluster(np.ones(count))

    def place(self, pose: np.ndarray, cov: np.ndarray) -> None:
        """Track from a pose found another way (the robot's meetings with placed robots), localized at once."""
        self.initialize_at(pose, cov)
        self._localized_run = self.config.localized_scans
        self._lost_run = 0
        self._met_afresh = False

    def initialize_global(self, observations: np.ndarray | None = None, count: int | None = None,
                          meeting: meetings.Meeting | None = None) -> None:
        """Global localization: ``count`` × ``reset_oversample`` poses from the scan and the map, or from a
        ``meeting`` with a robot whose pose is known (or ``count`` uniform ones); the update then weighs them by
        the scan and resamples to ``count``."""
        cfg = self.config
        count = count or cfg.particles
        self.size = count
        self.restarts += 1
        self._localized_run = 0
        self._lost_run = 0
        self._global, self._must_confirm, self._confirmed = True, False, set()
        if meeting is None and (cfg.init == "uniform" or observations is None):
            self.particles = uniform_poses(self.map, count, cfg.map_margin, self.rng)
            self.weights = np.full(count, 1.0 / count)
            self.clusters, self.significant = None, np.zeros(0, np.int64)
            return
        if meeting is not None:
            self.particles = meetings.draw(meeting, self.model.sensor, count * cfg.reset_oversample, self.rng)
        else:
            self.particles = self._scan_candidates(observations, count * cfg.reset_oversample)
        past = self._history_log_likelihood(self.particles)
        weights = np.exp(past - past.max())
        self.weights = weights / weights.sum()

    def _uses_history(self) -> bool:
        """Whether poses drawn from the current scan are weighed by the earlier scans too: only for a scan without
        signatures (one with them names its landmarks; the odometry's drift would only blur it)."""
        return self._targets is None and len(self.history) > 0

    def _history_log_likelihood(self, poses: np.ndarray) -> np.ndarray:
        """The earlier scans' log-likelihood of ``poses`` (:mod:`services.mcl.history`); zeros when not used."""
        if not self._uses_history():
            return np.zeros(poses.shape[0])
        return self.history.log_likelihood(poses, self._likelihood_of)

    def _scan_candidates(self, observations: np.ndarray, count: int) -> np.ndarray:
        cfg = self.config
        if self._targets is not None:
            return poses_from_signatures(observations, self._targets, self.model, count, self.rng)
        return poses_from_scan(observations, self.map, self.model, count, cfg.pair_sigmas, cfg.reset_jitter_xy,
                               cfg.reset_jitter_theta, cfg.map_margin, self.rng, cfg.reset_draws, cfg.compiled)

    def _likelihood(self, poses: np.ndarray, observations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self._scored(poses, observations, self._targets)

    def _scored(self, poses: np.ndarray, observations: np.ndarray,
                targets: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """(log-likelihood, match quality) of a scan at ``poses``; by id against ``targets`` when it has them."""
        if targets is not None:
            return signed_log_likelihood(poses, observations, targets, self.model)
        return scan_log_likelihood(poses, observations, self.map, self.model, self.config.chunk_particles,
                                   self.config.compiled)

    def _likelihood_of(self, poses: np.ndarray, observations: np.ndarray, targets: np.ndarray | None) -> np.ndarray:
        return self._scored(poses, observations, targets)[0]

    def _draw_from_scan(self, observations: np.ndarray, count: int) -> tuple[np.ndarray, float]:
        """``count`` poses drawn from p(y | x) over the map, and the log of the candidates' mean likelihood.

        With a scan history (:mod:`services.mcl.history`) and no signatures the candidates are drawn by the
        likelihood of the scan and of the earlier scans together, and the evidence is that of both, less the tracked
        particles' (weighted) likelihood of the earlier scans: those have already paid for them by surviving, a new
        pose has not.
        """
        candidates = self._scan_candidates(observations, count * self.config.reset_oversample)
        loglik, _ = self._likelihood(candidates, observations)
        reference = 0.0
        if self._uses_history():
            loglik = loglik + self.history.log_likelihood(candidates, self._likelihood_of)
            if self.initialized:
                tracked = self.history.log_likelihood(self.particles, self._likelihood_of)
                top = tracked.max()
                reference = float(top + math.log(np.dot(self.weights, np.exp(tracked - top)) / self.weights.sum()))
        top = loglik.max()
        likelihood = np.exp(loglik - top)
        chosen = candidates[systematic_resample(likelihood, count, self.rng)]
        return chosen, float(top + math.log(likelihood.mean())) - reference

    # ------------------------------------------------------------ prediction

    def predict(self, control: np.ndarray, dt: float, control_cov: np.ndarray) -> None:
        """Buffer one control (Table 1 step 1); it moves the particles when they are next looked at."""
        control = np.asarray(control, float)
        self.history.move(self.motion.step(self.history.odometry[None], control[None], dt)[0])
        if not self.initialized:
            return
        self._pending.append((control, float(dt), np.asarray(control_cov, float)))
        self._pending_s += max(float(dt), 0.0)
        if self._pending_s >= self.config.max_batch_s:
            self._apply_pending()

    def _apply_pending(self) -> None:
        """Move every particle by one draw from the buffered controls' relative motion N(Δ̄, s²·Σ_Δ) (s: the
        motion noise scale on the controls' std), then diffuse it by ``diffusion_xy`` and ``diffusion_theta``
        per √s of the time buffered."""
        if not self._pending:
            return
        controls, dts, covs = zip(*self._pending)
        span = self._pending_s
        self._pending, self._pending_s = [], 0.0
        integrate = integrate_compiled if self.config.compiled else integrate_controls
        delta, cov = integrate(self.motion, np.array(controls), np.array(dts), np.array(covs))
        cfg = self.config
        n = self._particles.shape[0]
        draws = delta + self.rng.standard_normal((n, 3)) @ (sqrt_psd(cov) * cfg.motion_noise_scale).T
        moved = se2_compose(self._particles, draws)
        spread = math.sqrt(span)
        moved[:, :2] += self.rng.normal(0.0, cfg.diffusion_xy * spread, size=(n, 2))
        moved[:, 2] = wrap_angle(moved[:, 2] + self.rng.normal(0.0, cfg.diffusion_theta * spread, size=n))
        self._particles = moved

    # ---------------------------------------------------------------- update

    def update(self, observations: np.ndarray, ids=None) -> UpdateReport:
        """Run the variant's table on one scan ``(n, 2)`` of (range, bearing), with its detections' landmark
        ``ids`` when it has them (signatures)."""
        cfg = self.config
        z = self._signed(observations, ids)
        fresh = not self.initialized or self._met_afresh
        self._met_afresh = False
        if not self.initialized:
            self.initialize_global(z)
        before = self.count
        added = 0
        override = np.zeros(0)
        if self.variant in ADAPTIVE and not fresh:
            needed = int(np.clip(kld_sample_size(support(self.particles, cfg.kld_bin_xy, cfg.kld_bin_theta),
                                                 cfg.kld_epsilon, cfg.kld_delta), cfg.min_particles, cfg.max_particles))
            if needed > self.size:
                added = needed - self.size
                new, log_evidence = self._draw_from_scan(z, added)
                self.particles = np.vstack([self.particles, new])
                self.weights = np.concatenate([self.weights, np.full(added, cfg.reset_prior * self.weights.mean())])
                override = np.full(added, log_evidence)
                self.size = needed
            elif needed < self.size and (self.variant == "kld_srl" or self.significant.size <= 1):
                self.size = needed
        loglik, quality = self._likelihood(self.particles, z)
        if override.size:
            loglik[-override.size:] = override
        self.reweigh(loglik, quality)
        best_quality = self._best_quality()
        kidnapped = self._check_lost(best_quality, float(quality.max()), z)
        contradicted = not kidnapped and self._contradicted(z)
        self.contradictions += int(contradicted)
        if kidnapped:
            self.history.clear()  # the odometry no longer ties the earlier scans to where the robot is now
        if kidnapped or contradicted:
            self.initialize_global(z)
            loglik, quality = self._likelihood(self.particles, z)
            self.reweigh(loglik, quality)
            added += self.count
            fresh = True
        mean_quality = float(quality.mean())
        hypotheses = int(self.significant.size)
        self._update_localized()
        added += self._resample(mean_quality, z, fresh)
        self.history.add(z, self._targets)
        self.last_report = UpdateReport(before, self.count, added, mean_quality, best_quality, hypotheses,
                                        kidnapped, self.localized)
        return self.last_report

    def meet(self, meeting: meetings.Meeting) -> bool:
        """A detection between this robot and a robot whose pose is known (:mod:`services.mcl.meeting`): where
        no particle agrees with it (or there are none yet), start global localization from the poses it allows,
        weighed by the scan history; the next scan's update weighs, clusters and resamples them. True when it
        started again.

        A meeting the main hypothesis explains keeps the filter from declaring itself lost (kidnapped) on the scans
        alone: early on, a partial map explains the true pose's scans poorly. A meeting that some particle agrees
        with does not weigh the particles: the detections of one meeting
        come ten a second with the same error in the other robot's pose, and weighing by each as if
        independent collapsed the particles onto the least wrong of them before the scans could speak (a
        robot placed 1.9 m off in the simulated arena)."""
        self.meetings += 1
        if self.initialized:
            _, d2 = meetings.log_likelihood(self.particles, meeting, self.model.sensor)
            if d2.min() <= meetings.GATE:
                best = self.best()
                explained = best is not None and meetings.log_likelihood(
                    best[0][None], meeting, self.model.sensor)[1][0] <= meetings.GATE
                if explained:  # the robot is not lost, whatever a partial map makes of its scans
                    self._lost_run = 0
                return False
        self.restart_from(meeting)
        return True

    def restart_from(self, meeting: meetings.Meeting) -> None:
        """Global localization from the poses a meeting allows (the next update is a fresh start)."""
        self.initialize_global(meeting=meeting)
        self._met_afresh = True

    def weigh(self, observations: np.ndarray, ids=None) -> None:
        """Weigh the particles by one scan and cluster them, without resampling (one-shot localization)."""
        z = self._signed(observations, ids)
        if not self.initialized:
            self.initialize_global(z)
        loglik, quality = self._likelihood(self.particles, z)
        self.reweigh(loglik, quality)

    def reweigh(self, loglik: np.ndarray, quality: np.ndarray) -> None:
        """Multiply the weights by the scan's likelihood, normalise, cluster."""
        logw = np.log(np.maximum(self.weights, 1e-300)) + loglik
        weights = np.exp(logw - logw.max())
        self.weights = weights / weights.sum()
        self._recluster(quality)

    def _recluster(self, quality: np.ndarray) -> None:
        cfg = self.config
        self.clusters = cluster_particles(self.particles, self.weights, quality, cfg.cluster_cell_xy, cfg.cluster_cell_theta,
                                          cfg.cluster_merge_xy, cfg.cluster_merge_theta, cfg.cluster_prune, cfg.compiled)
        self.significant = self.clusters.significant(cfg.cluster_min_weight, cfg.cluster_min_quality, cfg.max_hypotheses)

    def _best_quality(self) -> float:
        """Mean match quality of the heaviest cluster: how well the filter's main hypothesis explains the scan."""
        c = self.clusters
        return float(c.quality[0]) if c is not None and len(c) else 0.0

    def _check_lost(self, best_quality: float, particle_best: float, z: np.ndarray) -> bool:
        """Lost: no cluster has explained the scans for ``kidnap_scans`` scans, and poses drawn from the scan do
        clearly better (``kidnap_ratio``) than the best particle — with a partial map even the true pose
        explains a scan poorly, and starting again would not help."""
        cfg = self.config
        if len(z) < cfg.kidnap_min_observations:
            return False  # too few observations to tell a lost robot from an ambiguous view: the run neither grows nor ends
        self._lost_run = self._lost_run + 1 if best_quality < cfg.kidnap_quality else 0
        if self._lost_run < cfg.kidnap_scans or not cfg.kidnap_recovery:
            return False
        probe = self._scan_candidates(z, cfg.kidnap_probe)
        _, probe_quality = self._likelihood(probe, z)
        if probe_quality.max() <= cfg.kidnap_ratio * particle_best:
            return False
        self.kidnaps += 1
        return True

    def dominant(self) -> bool:
        """Does one hypothesis hold the weight now, compactly (``localized_*`` settings)?"""
        cfg = self.config
        c = self.clusters
        if c is None or not self.significant.size:
            return False
        top = int(self.significant[0])
        cov = c.cov[top]
        return bool(c.weight[top] >= cfg.localized_weight and math.sqrt(max(cov[0, 0] + cov[1, 1], 0.0)) <= cfg.localized_std_xy
                    and math.sqrt(max(cov[2, 2], 0.0)) <= cfg.localized_std_theta)

    def _update_localized(self) -> None:
        self._localized_run = self._localized_run + 1 if self.dominant() else 0
        if not self._localized_run:
            self._confirmed = set()  # what an earlier hypothesis explained does not confirm the next one

    def _resample(self, mean_quality: float, z: np.ndarray, fresh: bool) -> int:
        """The variant's resampling step to ``self.size`` samples; returns how many poses it drew from the scan."""
        cfg = self.config
        target = self.size
        if self.variant == "kld" and not fresh:
            # Fox's rule over the draws in random order; the draws are binned before the next motion step spreads
            # them (one step's motion noise rarely leaves a 0.5 m × 10° bin), so copies of one parent share a bin
            draws = systematic_resample(self.weights, cfg.max_particles, self.rng)
            draws = draws[self.rng.permutation(draws.size)]
            keys = bin_keys(self.particles[draws], cfg.kld_bin_xy, cfg.kld_bin_theta)
            n = kld_prefix_size(keys, cfg.kld_epsilon, cfg.kld_delta, cfg.min_particles, cfg.max_particles)
            self.size = n
            self._take(draws[:n], np.full(n, 1.0 / n))
            return 0
        if self.variant in CLUSTERED and self.significant.size > 1:
            # right after a (re)start the weights reflect where candidates happened to fall, not evidence: forget them
            memory = 0.0 if fresh else cfg.cluster_memory
            index, weights = two_stage_resample(self.weights, self.clusters.labels, self.significant, target, self.rng,
                                                memory)
            self._take(index, weights)
            return 0
        if self.variant in CLUSTERED and self.significant.size == 1:
            index, weights = two_stage_resample(self.weights, self.clusters.labels, self.significant, target, self.rng)
        else:
            index = systematic_resample(self.weights, target, self.rng)
            weights = np.full(target, 1.0 / target)
        self._take(index, weights)
        if self.variant in RESETTING and not fresh:
            return self._sensor_reset(mean_quality, z)
        return 0

    def _take(self, index: np.ndarray, weights: np.ndarray) -> None:
        self.particles = self.particles[index]
        self.weights = weights

    def _sensor_reset(self, mean_quality: float, z: np.ndarray) -> int:
        """Eq. 1: replace N_s = (1 − P̃/P_t)·N random particles by poses drawn from the scan."""
        replace = int(self.count * max(0.0, 1.0 - mean_quality / self.config.srl_threshold))
        if replace <= 0:
            return 0
        slots = self.rng.choice(self.count, size=replace, replace=False)
        self.particles[slots], _ = self._draw_from_scan(z, replace)
        self.weights[slots] = 1.0 / self.count
        self.weights /= self.weights.sum()
        return replace

    # --------------------------------------------------------------- outputs

    def hypotheses(self) -> list[Hypothesis]:
        """The significant clusters, heaviest first (the heaviest cluster when none is significant)."""
        c = self.clusters
        if c is None or len(c) == 0:
            return []
        chosen = self.significant if self.significant.size else np.array([0])
        return [Hypothesis(c.mean[j].copy(), c.cov[j].copy(), float(c.weight[j]), int(c.count[j])) for j in chosen]

    def best(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(mean, covariance) of the heaviest hypothesis; None before the first scan."""
        found = self.hypotheses()
        return (found[0].mean, found[0].cov) if found else None
