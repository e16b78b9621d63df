"""Messages of the one-shot global localization queryable ``{prefix}/mcl/localize`` (DESIGN §2).

A :class:`LocalizeRequest` carries one scan (ranges, bearings in the sensor
frame) and the sensor that took it; the MCL service draws poses from the scan
and its current map (sensor resetting), weighs them by the whole scan, clusters
them and answers with every significant hypothesis in a
:class:`LocalizeReply`. A request that names a robot the service tracks and
carries no scan is answered with that robot's current belief instead. A
request the service will not solve gets ``reply_err("reason: detail")``:
``invalid`` (a sensor noise covariance that is not positive definite),
``too_large`` (more work than the service's limits), ``busy`` (its queue is
full), ``expired`` or ``deadline`` (out of time), ``no_map``, ``no_sensor``.
"""

from __future__ import annotations

import math

import numpy as np
from pydantic import Field, model_validator

from schemas.messages import Array, Covariance3, FiniteFloat, Message, Pose, PoseHypothesis, RobotId, SensorSpec


class LocalizeRequest(Message):
    """Where could a robot be, given this scan and the service's map?"""

    request_id: int = Field(0, ge=0, description="echoed in the reply")
    robot_id: RobotId | None = Field(None, description="a tracked robot: its sensor is used, and without a scan its belief")
    ranges: Array(None, nonnegative=True) = Field(default_factory=lambda: np.zeros(0))
    bearings: Array(None) = Field(default_factory=lambda: np.zeros(0))
    sensor: SensorSpec | None = Field(None, description="the sensor that took the scan (else the tracked robot's)")
    particles: int | None = Field(None, ge=10, le=50_000, description="sample size (default: the service's setting; "
                                  "above its max_localize_particles the request is refused)")
    seed: int = Field(0, ge=0, description="seed of the draw")

    @model_validator(mode="after")
    def _lengths_agree(self) -> "LocalizeRequest":
        if self.ranges.shape[0] != self.bearings.shape[0]:
            raise ValueError(f"{self.ranges.shape[0]} ranges but {self.bearings.shape[0]} bearings")
        if np.any(np.abs(self.bearings) > math.pi + 1e-9):
            raise ValueError("bearing outside [-π, π]")
        return self

    @property
    def observations(self) -> np.ndarray:
        return np.stack([self.ranges, self.bearings], -1)


class LocalizeReply(Message):
    """The hypotheses (heaviest first), the best pose, and whether one hypothesis dominates."""

    request_id: int = Field(0, ge=0)
    robot_id: RobotId | None = None
    stamp: FiniteFloat = Field(description="service wall clock (s) of the answer")
    source: str = Field(description="scan: drawn from the request's scan; track: the tracked robot's belief")
    best_pose: Pose
    best_cov: Covariance3
    localized: bool
    hypotheses: list[PoseHypothesis] = Field(default_factory=list)
    particles: int = Field(ge=0)
    map_landmarks: int = Field(ge=0)
    variant: str = ""
