"""Every particle's landmark map as padded arrays (one EKF per landmark).

Slot ``s`` of particle ``p`` holds a landmark iff ``valid[p, s]``. New
landmarks of a particle go after its high-water mark ``used[p]``; deleted ones
leave holes that :meth:`LandmarkMap.compact` squeezes out when room runs short,
and the capacity doubles when that is not enough (amortised O(1) growth). This
dense map serves per-particle association (nn, mht), where each particle has
landmarks of its own; with known or shared association a landmark has one slot
in every particle and :class:`central.fastslam.aligned_map.AlignedMap` shares
unchanged blocks between particles instead.
Resampling is a gather along the particle axis. The functions after the class
are the EKF of a landmark seen from a pose: predicted detection, update, creation.
"""

from __future__ import annotations

import numpy as np

from robots.gaussian import LOG_2PI, inv2, quad2, sandwich2
from robots.models import RangeBearingSensor


class LandmarkMap:
    """Means ``(P, C, 2)``, covariances ``(P, C, 2, 2)``, existence scores, hit counts, labels, valid mask."""

    EMPTY = {"mean": 0.0, "cov": 0.0, "exist": 0.0, "hits": 0, "label": -1, "valid": False}  # a free slot

    def __init__(self, particles: int, capacity: int = 16):
        self.mean = np.zeros((particles, capacity, 2))
        self.cov = np.zeros((particles, capacity, 2, 2))
        self.exist = np.zeros((particles, capacity))
        self.hits = np.zeros((particles, capacity), np.int32)
        self.label = np.full((particles, capacity), -1, np.int64)
        self.valid = np.zeros((particles, capacity), bool)
        self.used = np.zeros(particles, np.int64)

    @property
    def particles(self) -> int:
        return self.valid.shape[0]

    @property
    def capacity(self) -> int:
        return self.valid.shape[1]

    def flat(self, particle: np.ndarray, slot: np.ndarray) -> np.ndarray:
        """Row of (particle, slot) in the flattened arrays (one index array is cheaper than two)."""
        return particle * self.capacity + slot

    def mean_rows(self) -> np.ndarray:
        """``mean`` as ``(P·C, 2)`` (a view: writes go through)."""
        return self.mean.reshape(-1, 2)

    def cov_rows(self) -> np.ndarray:
        """``cov`` as ``(P·C, 2, 2)`` (a view: writes go through)."""
        return self.cov.reshape(-1, 2, 2)

    def counts(self) -> np.ndarray:
        """Landmarks per particle ``(P,)``."""
        return self.valid.sum(1)

    def reserve(self, extra: int, compact: bool = True) -> None:
        """Make room for ``extra`` more slots after every particle's high-water mark."""
        if int(self.used.max(initial=0)) + extra <= self.capacity:
            return
        if compact:
            self.compact()
        need = int(self.used.max(initial=0)) + extra
        if need > self.capacity:
            self._grow(max(need, 2 * self.capacity))

    def _grow(self, capacity: int) -> None:
        extra = capacity - self.capacity
        for name, empty in self.EMPTY.items():
            array = getattr(self, name)
            setattr(self, name, np.concatenate([array, np.full((array.shape[0], extra) + array.shape[2:], empty,
                                                               array.dtype)], 1))

    def compact(self) -> None:
        """Move every particle's valid slots to the front, keeping their order."""
        order = np.argsort(~self.valid, axis=1, kind="stable")
        take = lambda a: np.take_along_axis(a, order.reshape(order.shape + (1,) * (a.ndim - 2)), 1)  # noqa: E731
        self.mean, self.cov, self.exist = take(self.mean), take(self.cov), take(self.exist)
        self.hits, self.label, self.valid = take(self.hits), take(self.label), take(self.valid)
        self.used = self.valid.sum(1).astype(np.int64)

    def gather(self, particle: np.ndarray, slot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(means, covariances) of landmark ``slot`` of ``particle`` (broadcast index arrays)."""
        return self.mean[particle, slot], self.cov[particle, slot]

    def select(self, index: np.ndarray) -> None:
        """Keep particles ``index`` (with repetition): the gather of resampling and of MHT splitting.

        Only the slots below the highest high-water mark are copied; the rest of the capacity is free in every
        particle and is reset to the empty-slot values (whatever stale data it held is never read: a slot is
        written whole when a landmark is appended to it)."""
        top = int(self.used.max(initial=0))

        for name, empty in self.EMPTY.items():
            array = getattr(self, name)
            out = np.empty((len(index),) + array.shape[1:], array.dtype)
            out[:, :top] = array[index, :top]
            out[:, top:] = empty
            setattr(self, name, out)
        self.used = self.used[index]

    def append(self, particle: np.ndarray, mean: np.ndarray, cov: np.ndarray, exist: float, label: np.ndarray) -> np.ndarray:
        """Add landmarks to ``particle`` (sorted, repeats allowed); returns their slots. Call :meth:`reserve` first."""
        first = np.searchsorted(particle, particle)
        slot = self.used[particle] + np.arange(particle.size) - first
        self.mean[particle, slot] = mean
        self.cov[particle, slot] = cov
        self.exist[particle, slot] = exist
        self.hits[particle, slot] = 1
        self.label[particle, slot] = label
        self.valid[particle, slot] = True
        np.add.at(self.used, particle, 1)
        return slot


def predict(landmarks: LandmarkMap, sensor: RangeBearingSensor, pose: np.ndarray, particle: np.ndarray,
            slot: np.ndarray, r: np.ndarray) -> tuple:
    """(ẑ, H, S, S⁻¹, |S|) of landmark ``slot`` of ``particle`` seen from ``pose`` (broadcast over any leading
    shape), S = H Σ Hᵀ + R."""
    flat = landmarks.flat(particle, slot)
    zhat, h = sensor.observe_with_jacobian(pose, landmarks.mean_rows()[flat])
    s = sandwich2(h, landmarks.cov_rows()[flat]) + r
    s_inv, det = inv2(s)
    return zhat, h, s, s_inv, det


def update(landmarks: LandmarkMap, sensor: RangeBearingSensor, particle: np.ndarray, z: np.ndarray, slot: np.ndarray,
           terms: tuple, exist_hit: float, exist_max: float) -> np.ndarray:
    """EKF update of landmark ``slot`` of ``particle`` by detection ``z`` (one pair per row), given their
    :func:`predict` ``terms``; one more hit, existence score up by ``exist_hit`` (at most ``exist_max``).
    Returns the log-likelihood log N(ν; 0, S) of each pair."""
    zhat, h, s, s_inv, det = terms
    flat = landmarks.flat(particle, slot)
    means, covs = landmarks.mean_rows(), landmarks.cov_rows()
    exist, hits = landmarks.exist.reshape(-1), landmarks.hits.reshape(-1)
    sig = covs[flat]
    nu = sensor.innovation(z, zhat)
    gain = sig @ np.swapaxes(h, -1, -2) @ s_inv
    means[flat] += (gain @ nu[..., None])[..., 0]
    covs[flat] = sig - sandwich2(gain, s)
    exist[flat] = np.minimum(exist[flat] + exist_hit, exist_max)
    hits[flat] += 1
    return -0.5 * quad2(nu, s_inv) - 0.5 * np.log(np.maximum(det, 1e-300)) - LOG_2PI


def create(landmarks: LandmarkMap, sensor: RangeBearingSensor, pose: np.ndarray, particle: np.ndarray, z: np.ndarray,
           r: np.ndarray, exist: float, label: np.ndarray) -> np.ndarray:
    """New landmarks of ``particle`` (sorted) at the inverse observation of ``z`` from ``pose``, with the
    sensor noise ``r`` carried into the map; returns their slots (call :meth:`LandmarkMap.reserve` first)."""
    mean = sensor.inverse(pose, z)
    _, g = sensor.inverse_jacobians(pose, z)
    return landmarks.append(particle, mean, sandwich2(g, r), exist, label)
