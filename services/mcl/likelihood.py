"""Scan likelihood on a landmark map with unknown correspondence (Sehestedt and Schneider,
"Monte Carlo Localization in Highly Symmetric Environments", Table 1 step 2).

Each observation is scored against its best-matching landmark (the smallest
Mahalanobis distance of the range-bearing innovation), mixed with a uniform
clutter floor so that one false detection cannot zero a good particle:

    p(z_j | x) = (1 − ε) · N(z_j; h(x, m*), R) + ε / V,   V = (r_max − r_min) · fov.

Landmarks that a particle predicts well inside its view but that no
observation matched add the negative information log p_miss each; without it
every pose of a regular grid looks alike, and a symmetric map cannot be told
apart at its borders.

Candidate landmarks come from two precomputed grids (:class:`CellIndex`):
landmarks near an observation's end point (for matching) and landmarks within
range of the sensor (for the negative information), so the cost is bounded by
the local density, not the size of the map: vectorised over particles ×
observations × a handful of candidates.
"""

from __future__ import annotations

import hashlib
import math
import threading
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from robots.models import RangeBearingSensor, transform_points
from schemas.messages import SensorSpec
from services.mcl import kernels

FAR = 1e9  # position of the padding landmark that no query ever matches


class CellIndex:
    """For every cell of a regular grid, the landmarks within ``radius`` of any point of the cell.

    With ``limit``, only the ``limit`` landmarks nearest the cell's centre are
    listed. Rows are padded with the index ``L`` (a landmark at infinity);
    points outside the grid get a row of padding only.
    """

    def __init__(self, landmarks: np.ndarray, cell: float, radius: float, limit: int | None = None):
        landmarks = np.asarray(landmarks, float).reshape(-1, 2)
        self.count = landmarks.shape[0]
        self.cell = float(cell)
        if self.count == 0:
            self.origin = np.zeros(2)
            self.shape = (1, 1)
            self.table = np.zeros((1, 1), np.int64)
            return
        # two empty cells of margin beyond the reach: points off the grid are clipped onto them
        self.origin = landmarks.min(0) - radius - 3 * cell
        extent = landmarks.max(0) + radius + 3 * cell - self.origin
        self.shape = tuple(int(v) for v in np.ceil(extent / cell).astype(int))
        ix, iy = np.meshgrid(np.arange(self.shape[0]), np.arange(self.shape[1]), indexing="ij")
        centres = self.origin + (np.stack([ix.ravel(), iy.ravel()], -1) + 0.5) * cell
        reach = radius + cell * math.sqrt(0.5)
        tree = cKDTree(landmarks)
        if limit is not None:
            # nearest first; the neighbours beyond the reach come last, with the index L, which pads
            _, index = tree.query(centres, k=limit, distance_upper_bound=reach)
            index = index.reshape(len(centres), -1)
            self.table = np.ascontiguousarray(index[:, :max(1, int((index < self.count).sum(1).max()))])
            return
        lists = tree.query_ball_point(centres, reach)
        lengths = np.fromiter((len(item) for item in lists), np.int64, len(lists))
        width = max(1, int(lengths.max()))
        self.table = np.full((len(lists), width), self.count, np.int64)
        if lengths.sum():
            rows = np.repeat(np.arange(len(lists)), lengths)
            cols = np.arange(lengths.sum()) - np.repeat(np.cumsum(lengths) - lengths, lengths)
            self.table[rows, cols] = np.concatenate([np.asarray(item, np.int64) for item in lists if len(item)])

    def lookup(self, points: np.ndarray) -> np.ndarray:
        """Candidate landmark indices ``(..., width)`` for points ``(..., 2)`` (``L`` pads)."""
        cells = (np.asarray(points, float) - self.origin) * (1.0 / self.cell)
        ix = np.clip(cells[..., 0].astype(np.int64), 0, self.shape[0] - 1)
        iy = np.clip(cells[..., 1].astype(np.int64), 0, self.shape[1] - 1)
        return self.table[ix * self.shape[1] + iy]


@dataclass
class ScanModel:
    """What the likelihood needs from a robot's sensor and the filter settings."""

    sensor: RangeBearingSensor
    noise_cov: np.ndarray  # (2, 2) covariance used by the likelihood (sensor's, scaled)
    min_range: float
    max_range: float
    fov: float
    clutter_weight: float
    miss_probability: float
    margin_range: float
    margin_bearing: float
    gate: float  # squared Mahalanobis gate of a match

    @classmethod
    def from_spec(cls, spec: SensorSpec, noise_scale: float, clutter_weight: float, miss_floor: float,
                  margin_range: float, margin_bearing: float, match_sigmas: float) -> "ScanModel":
        return cls(
            sensor=RangeBearingSensor(tuple(float(v) for v in spec.offset)),
            noise_cov=np.asarray(spec.noise_cov, float) * noise_scale**2,
            min_range=spec.min_range, max_range=spec.max_range, fov=spec.fov,
            clutter_weight=clutter_weight,
            miss_probability=max(1.0 - spec.detection_probability, miss_floor),
            margin_range=margin_range, margin_bearing=margin_bearing, gate=match_sigmas**2,
        )

    @property
    def full_circle(self) -> bool:
        return self.fov >= 2 * math.pi - 1e-9

    @property
    def information(self) -> np.ndarray:
        """The inverse of ``noise_cov`` (2, 2): every Mahalanobis distance of a detection uses it."""
        return np.linalg.inv(self.noise_cov)

    @property
    def log_gauss_norm(self) -> float:
        return -math.log(2 * math.pi) - 0.5 * math.log(np.linalg.det(self.noise_cov))

    @property
    def log_floor(self) -> float:
        volume = max(self.max_range - self.min_range, 1e-6) * min(self.fov, 2 * math.pi)
        return math.log(self.clutter_weight / volume)

    @property
    def log_peak(self) -> float:
        """Log-likelihood of one observation that matches its landmark exactly."""
        return float(np.logaddexp(math.log1p(-self.clutter_weight) + self.log_gauss_norm, self.log_floor))

    def match_radius(self) -> float:
        """Largest distance (m) between an observation's end point and a landmark inside the gate."""
        sigma_r, sigma_b = np.sqrt(np.diag(self.noise_cov))
        return math.sqrt(self.gate) * math.hypot(sigma_r, self.max_range * sigma_b)

    def inner_view(self, observations: np.ndarray) -> np.ndarray:
        """Mask of predicted (range, bearing) well inside the sensor's limits (sure to be detected)."""
        r, phi = observations[..., 0], observations[..., 1]
        inside = (r <= self.max_range - self.margin_range) & (r >= self.min_range + self.margin_range)
        if not self.full_circle:
            inside &= np.abs(phi) <= 0.5 * self.fov - self.margin_bearing
        return inside


class LandmarkMap:
    """A landmark map prepared for one sensor: padded positions, candidate grids, landmark pairs.

    An observation is matched against the ``candidates`` landmarks nearest to
    its grid cell's centre (within the gate's reach), the best of which is its
    best-matching landmark.
    """

    def __init__(self, landmarks: np.ndarray, model: ScanModel, cell: float, candidates: int):
        self.landmarks = np.asarray(landmarks, float).reshape(-1, 2)
        self.count = self.landmarks.shape[0]
        self.padded = np.vstack([self.landmarks, [FAR, FAR]])
        self.padded32 = self.padded.astype(np.float32)
        self.match_index = CellIndex(self.landmarks, cell, model.match_radius(), candidates)
        self.view_index = CellIndex(self.landmarks, max(cell, model.max_range / 8), model.max_range)
        self.pair_first, self.pair_second, self.pair_distance = landmark_pairs(self.landmarks, 2 * model.max_range)

    def bounds(self, margin: float) -> tuple[np.ndarray, np.ndarray]:
        """(low, high) corners of the map's bounding box grown by ``margin``."""
        if self.count == 0:
            return np.full(2, -margin), np.full(2, margin)
        return self.landmarks.min(0) - margin, self.landmarks.max(0) + margin


class MapCache:
    """The last few :class:`LandmarkMap` built, by landmarks and by what the map takes from the sensor.

    Every robot of a fleet with the same sensor, and every localization query, weighs against the same map: built
    once, not once per robot and query (a 200-landmark map takes longer to prepare than a 1000-particle query takes
    to answer). Used from the stream and from the query worker, so under a lock; a pickled cache (a checkpoint)
    comes back empty.
    """

    def __init__(self, size: int = 4):
        self.size = size
        self._maps: dict[tuple, LandmarkMap] = {}
        self._lock = threading.Lock()

    def get(self, landmarks: np.ndarray, model: ScanModel, cell: float, candidates: int) -> LandmarkMap:
        landmarks = np.ascontiguousarray(landmarks, float).reshape(-1, 2)
        key = (hashlib.blake2b(landmarks.tobytes(), digest_size=16).digest(), landmarks.shape[0],
               model.match_radius(), float(model.max_range), float(cell), int(candidates))
        with self._lock:
            found = self._maps.pop(key, None)
            if found is not None:
                self._maps[key] = found  # most recently used last
                return found
        built = LandmarkMap(landmarks, model, cell, candidates)
        with self._lock:
            self._maps[key] = built
            while len(self._maps) > self.size:
                self._maps.pop(next(iter(self._maps)))
        return built

    def __len__(self) -> int:
        return len(self._maps)

    def __getstate__(self) -> dict:
        return {"size": self.size}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["size"])


def landmark_pairs(landmarks: np.ndarray, max_distance: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every ordered pair of distinct landmarks closer than ``max_distance``, sorted by distance."""
    if landmarks.shape[0] < 2:
        empty = np.zeros(0, np.int64)
        return empty, empty, np.zeros(0)
    pairs = cKDTree(landmarks).query_pairs(max_distance, output_type="ndarray")
    first = np.concatenate([pairs[:, 0], pairs[:, 1]])
    second = np.concatenate([pairs[:, 1], pairs[:, 0]])
    distance = np.linalg.norm(landmarks[first] - landmarks[second], axis=-1)
    order = np.argsort(distance, kind="stable")
    return first[order], second[order], distance[order]


def scan_log_likelihood(poses: np.ndarray, observations: np.ndarray, lmap: LandmarkMap, model: ScanModel,
                        chunk: int = 400, compiled: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Log-likelihood ``(P,)`` of one scan ``(n, 2)`` for each pose ``(P, 3)``, and its match quality ``(P,)``.

    The observed points are computed once in the robot frame (q_j, with the
    sensor offset) and carried to the world by each particle's rotation and
    translation. The innovation of observation j against landmark m is taken
    in the frame of the observation's ray (unit direction u_j, range r_j): with
    d = R(θ)ᵀ(m − e_j) the landmark's offset from the end point e_j,
    ν ≈ (−d·u_j, −d·u_j⊥ / r_j), the (range, bearing) innovation to first order,
    exact up to O(|d|² / r_j) — far below the noise inside the gate, and free of
    trigonometry per candidate. The particles are processed ``chunk`` at a time
    in single precision, so that the temporaries stay in the processor's cache.

    The quality is the per-observation geometric mean of p / p_peak, in (0, 1]:
    1 for a scan that matches the map exactly, near ε/(V·p_peak) when nothing
    matches. Sensor resetting (eq. 1) and the kidnap detector compare it with
    their thresholds, independently of the number of observations.

    ``compiled`` runs the numba kernel of :mod:`services.mcl.kernels` (double precision, one pass per
    particle); False, this numpy reference.
    """
    poses = np.asarray(poses, float).reshape(-1, 3)
    z = np.asarray(observations, float).reshape(-1, 2)
    count, n = poses.shape[0], z.shape[0]
    loglik = np.empty(count)
    if n and lmap.count and compiled and kernels.AVAILABLE:
        loglik = _compiled_log_likelihood(poses, z, lmap, model)
    elif n and lmap.count:
        scan = _ScanTerms.build(z, model)
        for start in range(0, count, chunk):
            part = slice(start, start + chunk)
            loglik[part] = _chunk_log_likelihood(poses[part], scan, lmap, model)
    else:
        cos_t, sin_t = np.cos(poses[:, 2]), np.sin(poses[:, 2])
        position, _ = model.sensor.sensor_position(poses)
        missed = expected_visible(cos_t, sin_t, position, lmap, model)
        loglik[:] = n * model.log_floor + missed * math.log(model.miss_probability)
    quality = np.exp((loglik - n * model.log_peak) / max(n, 1))
    return loglik, quality


@dataclass
class _ScanTerms:
    """What one scan contributes to every particle's likelihood, computed once per scan."""

    bearings: np.ndarray  # (n,)
    body: np.ndarray  # (n, 2) observed points in the robot frame
    ranges: np.ndarray  # (n, 1) float32
    ux: np.ndarray  # (n, 1) float32 ray directions in the robot frame
    uy: np.ndarray
    info: np.ndarray  # (2, 2) float32 information matrix of (range, bearing)
    match_scale: float  # (1 − ε) · Gaussian normaliser
    floor: float  # ε / V

    @classmethod
    def build(cls, z: np.ndarray, model: ScanModel) -> "_ScanTerms":
        return cls(
            bearings=z[:, 1],
            body=model.sensor.inverse(np.zeros(3), z),
            ranges=np.maximum(z[:, 0], 1e-6)[:, None].astype(np.float32),
            ux=np.cos(z[:, 1])[:, None].astype(np.float32),
            uy=np.sin(z[:, 1])[:, None].astype(np.float32),
            info=model.information.astype(np.float32),
            match_scale=(1.0 - model.clutter_weight) * math.exp(model.log_gauss_norm),
            floor=math.exp(model.log_floor),
        )


def _compiled_log_likelihood(poses: np.ndarray, z: np.ndarray, lmap: LandmarkMap, model: ScanModel) -> np.ndarray:
    """:func:`scan_log_likelihood` by the numba kernel, with the same model and candidate grids."""
    match, view = lmap.match_index, lmap.view_index
    a, b = model.sensor.offset
    half = 0.5 * model.fov - model.margin_bearing
    return kernels.scan_log_likelihood_kernel(
        np.ascontiguousarray(poses), model.sensor.inverse(np.zeros(3), z), np.maximum(z[:, 0], 1e-6), z[:, 1].copy(),
        np.cos(z[:, 1]), np.sin(z[:, 1]), model.information,
        (1.0 - model.clutter_weight) * math.exp(model.log_gauss_norm), math.exp(model.log_floor), lmap.padded,
        match.table, match.origin, match.cell, match.shape[0], match.shape[1],
        view.table, view.origin, view.cell, view.shape[0], view.shape[1],
        float(a), float(b), model.gate, model.max_range - model.margin_range, model.min_range + model.margin_range,
        half, model.full_circle, math.log(model.miss_probability),
    )


def _chunk_log_likelihood(poses: np.ndarray, scan: _ScanTerms, lmap: LandmarkMap, model: ScanModel) -> np.ndarray:
    """Log-likelihood of a few hundred poses: best matches, clutter floor, negative information."""
    cos_t, sin_t = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    position, _ = model.sensor.sensor_position(poses)
    ends = transform_points(poses[:, None, :], scan.body[None, :, :]).astype(np.float32)  # (P, n, 2)
    candidates = lmap.match_index.lookup(ends)  # (P, n, K); padding sits at infinity
    dx = lmap.padded32[candidates, 0] - ends[..., 0, None]
    dy = lmap.padded32[candidates, 1] - ends[..., 1, None]
    c, s = cos_t.astype(np.float32)[:, None, None], sin_t.astype(np.float32)[:, None, None]
    bx, by = c * dx + s * dy, c * dy - s * dx  # offset in the robot frame
    radial = bx * scan.ux + by * scan.uy
    across = (by * scan.ux - bx * scan.uy) / scan.ranges
    info = scan.info
    m2 = info[0, 0] * radial * radial + 2 * info[0, 1] * radial * across + info[1, 1] * across * across
    if candidates.shape[-1] > 1:
        best = np.argmin(m2, axis=-1)[..., None]
        m2, radial, across, candidates = (np.take_along_axis(a, best, -1) for a in (m2, radial, across, candidates))
    m2, radial, across, ids = m2[..., 0], radial[..., 0], across[..., 0], candidates[..., 0]  # best match (P, n)
    loglik = np.log(scan.match_scale * np.exp(-0.5 * m2) + scan.floor).sum(1, dtype=np.float64)
    # negative information: landmarks this particle predicts well inside its view that no observation matched
    inner = model.inner_view(np.stack([scan.ranges[:, 0] + radial, scan.bearings + across], -1))
    ids = np.where((m2 <= model.gate) & inner, ids, -1)
    ids.sort(axis=1)
    distinct = ids >= 0
    distinct[:, 1:] &= ids[:, 1:] != ids[:, :-1]
    missed = np.maximum(expected_visible(cos_t, sin_t, position, lmap, model) - distinct.sum(1), 0)
    return loglik + missed * math.log(model.miss_probability)


def expected_visible(cos_t: np.ndarray, sin_t: np.ndarray, position: np.ndarray, lmap: LandmarkMap,
                     model: ScanModel) -> np.ndarray:
    """Number of landmarks ``(P,)`` each pose (heading cos/sin, sensor at ``position``) predicts well inside its view.

    The bearing test |φ| ≤ h is done as d·heading ≥ |d|·cos h (valid for h ≤ π), without an arctangent.
    """
    if lmap.count == 0:
        return np.zeros(position.shape[0], np.int64)
    candidates = lmap.view_index.lookup(position)  # (P, Kv)
    dx = lmap.padded[candidates, 0] - position[:, None, 0]
    dy = lmap.padded[candidates, 1] - position[:, None, 1]
    r2 = dx * dx + dy * dy
    far, near = model.max_range - model.margin_range, model.min_range + model.margin_range
    inside = (r2 <= far * far) & (r2 >= near * near)
    if not model.full_circle:
        half = max(0.5 * model.fov - model.margin_bearing, 0.0)
        along = cos_t[:, None] * dx + sin_t[:, None] * dy
        inside &= along >= np.sqrt(r2) * math.cos(half)
    return inside.sum(1)


def signed_log_likelihood(poses: np.ndarray, observations: np.ndarray, targets: np.ndarray,
                          model: ScanModel) -> tuple[np.ndarray, np.ndarray]:
    """Log-likelihood ``(P,)`` and match quality ``(P,)`` of a scan whose detections carry landmark ids
    (signatures): observation j is compared with its own landmark ``targets[j]`` only, with the same
    Gaussian-plus-clutter-floor model as :func:`scan_log_likelihood` (no search for a best match, so a
    symmetric map is no longer ambiguous)."""
    poses = np.asarray(poses, float).reshape(-1, 3)
    z = np.asarray(observations, float).reshape(-1, 2)
    n = z.shape[0]
    if n == 0:
        return np.zeros(poses.shape[0]), np.ones(poses.shape[0])
    predicted = model.sensor.observe(poses[:, None, :], targets[None, :, :])
    nu = model.sensor.innovation(z[None], predicted)
    m2 = np.einsum("pji,ik,pjk->pj", nu, model.information, nu)
    match = (1.0 - model.clutter_weight) * math.exp(model.log_gauss_norm)
    loglik = np.log(match * np.exp(-0.5 * m2) + math.exp(model.log_floor)).sum(1)
    return loglik, np.exp((loglik - n * model.log_peak) / n)


def poses_from_signatures(observations: np.ndarray, targets: np.ndarray, model: ScanModel, count: int,
                          rng: np.random.Generator) -> np.ndarray:
    """``count`` poses ``(count, 3)`` that put one random observation of the scan on its own landmark: the
    sensor on the circle of the measured range around the landmark, the heading from the measured bearing
    (range and bearing jittered by their noise)."""
    z = np.asarray(observations, float).reshape(-1, 2)
    pick = rng.integers(z.shape[0], size=count)
    sigma = np.sqrt(np.diag(model.noise_cov))
    r = np.maximum(z[pick, 0] + rng.normal(0.0, sigma[0], count), 1e-3)
    bearing = z[pick, 1] + rng.normal(0.0, sigma[1], count)
    direction = rng.uniform(-math.pi, math.pi, count)  # world direction from the sensor to the landmark
    return model.sensor.pose_seeing(targets[pick], np.stack([r, bearing], -1), direction)
