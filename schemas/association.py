"""Messages of the data-association queryable (``{prefix}/assoc/{method}``, DESIGN §2 and §4).

An :class:`AssociationRequest` describes one scan's single-frame assignment
problem (paper 000, eqs. 6-8) in one of two forms:

- *predicted form*: the predicted observations ``predicted`` (N, 2) of the
  candidate landmarks and their innovation covariances ``innovation_covs``
  (N, 2, 2) = H P Hᵀ + R; optionally ``joint_cov`` (2N, 2N), the joint
  covariance H P Hᵀ of the predicted observations *without* the measurement
  noise (JCBB needs it; its diagonal blocks plus ``noise`` are the
  innovation covariances);
- *landmark form*: landmark means ``landmarks`` (N, 2) and covariances
  ``landmark_covs`` (N, 2, 2), the robot ``pose`` (and ``pose_cov``), the
  sensor offset; optionally ``joint_cov`` (3+2N, 3+2N), the full covariance
  of [pose, landmarks] (otherwise pose and landmarks are taken as independent).

Measurements are (range, bearing) in the sensor frame; ``noise`` is their
covariance R. The cost model (DESIGN §4) is the negative log-likelihood ratio
of "measurement m comes from landmark n" against "m is a new feature or
clutter and n was missed":

    c_nm = ½ νᵀS⁻¹ν + ½ ln|2πS| + ln λ − ln(P_D / (1 − P_D)),

with λ = ``clutter_density`` + ``new_feature_density`` (per unit of
measurement space, 1/(m·rad)) and P_D = ``detection_probability``. A pair is a
candidate only inside the chi-square gate of ``gate_probability``. (The paper's
"dummy cost 0" is the special case λ = 1, P_D = ½.)

An :class:`AssociationReply` gives per measurement a landmark index, or
``NEW`` (-1: outside every landmark's new-feature gate, start a feature) or
``CLUTTER`` (-2: unassigned but too close to a landmark to start one) or, when the request asks for
``unique_pairs``, ``AMBIGUOUS`` (-3: JCBB paired it, but another hypothesis pairs as many without that
pairing: neither a match nor a new feature), per
landmark whether it was missed, the total cost Σ c_nm of the chosen pairs
(the all-dummy hypothesis costs 0), the solve time and the method used;
IHGR adds its first LP objective (a lower bound) and the gap of its rounded
solution above it. A solve cut by the service's time budget answers with its
best so far (``truncated``); a request the service will not solve gets
``reply_err("reason: detail")`` (``invalid``, ``bad_covariance``,
``too_large``, ``busy``, ``expired``, ``deadline``, ``solve_error``...).
"""

from __future__ import annotations

import math
from typing import ClassVar, Literal

import numpy as np
from pydantic import Field, model_validator

from schemas.messages import Array, Covariance2, Covariance3, Message, Pose

NEW = -1
CLUTTER = -2
AMBIGUOUS = -3
METHODS = ("nn", "greedy", "ihgr", "exact", "jcbb", "auto")


class AssociationRequest(Message):
    """One scan's association problem (see the module docstring for the two forms)."""

    SCHEMA_VERSION: ClassVar[int] = 1

    request_id: int = Field(0, ge=0, description="echoed in the reply")
    measurements: Array(None, 2) = Field(description="(M, 2) measured (range, bearing)")
    noise: Covariance2 = Field(description="measurement noise covariance R of (range, bearing)")
    predicted: Array(None, 2) | None = Field(None, description="(N, 2) predicted (range, bearing) [predicted form]")
    innovation_covs: Array(None, 2, 2) | None = Field(None, description="(N, 2, 2) innovation covariances S [predicted form]")
    landmarks: Array(None, 2) | None = Field(None, description="(N, 2) landmark means [landmark form]")
    landmark_covs: Array(None, 2, 2) | None = Field(None, description="(N, 2, 2) landmark covariances [landmark form]")
    pose: Pose | None = Field(None, description="robot pose (x, y, θ) [landmark form]")
    pose_cov: Covariance3 | None = Field(None, description="robot pose covariance [landmark form]; zero if absent")
    sensor_offset: Array(2) = Field(default_factory=lambda: np.zeros(2), description="sensor (a, b) in the body frame")
    joint_cov: Array(None, None, symmetric=True) | None = Field(
        None, description="(2N, 2N) covariance of the predicted observations, or (3+2N, 3+2N) of [pose, landmarks]"
    )
    gate_probability: float = Field(0.99, gt=0.0, lt=1.0, allow_inf_nan=False, description="chi-square gate probability")
    new_feature_gate_probability: float = Field(
        0.999999, gt=0.0, lt=1.0, allow_inf_nan=False,
        description="an unassigned measurement starts a feature only outside this gate of every landmark",
    )
    clutter_density: float = Field(1e-3, ge=0.0, allow_inf_nan=False, description="false alarms per m·rad")
    new_feature_density: float = Field(1e-3, ge=0.0, allow_inf_nan=False, description="new features per m·rad")
    detection_probability: float = Field(0.9, gt=0.0, lt=1.0, allow_inf_nan=False, description="P_D of a landmark in view")
    ihgr_tie_margin: float = Field(
        0.05, ge=0.0, le=1.0, description="IHGR: fractional values this close to the largest are a tie (enumerated)"
    )
    jcbb_max_nodes: int = Field(20_000, ge=1, description="JCBB search budget (interpretation-tree nodes)")
    unique_pairs: bool = Field(
        False, description="JCBB (and auto when it picks JCBB): a pairing that another hypothesis with as many "
        "jointly compatible pairings does without is answered AMBIGUOUS (-3), not paired; one more JCBB search per pair"
    )
    auto_jcbb_max_measurements: int = Field(
        12, ge=0, description="auto: JCBB when a joint covariance is given and at most this many measurements are gated"
    )

    @model_validator(mode="after")
    def _consistent(self) -> "AssociationRequest":
        predicted_form = self.predicted is not None or self.innovation_covs is not None
        landmark_form = self.landmarks is not None or self.landmark_covs is not None or self.pose is not None
        if predicted_form == landmark_form:
            raise ValueError("give either predicted + innovation_covs, or landmarks + landmark_covs + pose")
        if predicted_form:
            if self.predicted is None or self.innovation_covs is None:
                raise ValueError("predicted form needs both predicted and innovation_covs")
            n, joint_dim = self.predicted.shape[0], 2 * self.predicted.shape[0]
            if self.innovation_covs.shape[0] != n:
                raise ValueError(f"{n} predicted observations but {self.innovation_covs.shape[0]} innovation covariances")
        else:
            if self.landmarks is None or self.landmark_covs is None or self.pose is None:
                raise ValueError("landmark form needs landmarks, landmark_covs and pose")
            n, joint_dim = self.landmarks.shape[0], 3 + 2 * self.landmarks.shape[0]
            if self.landmark_covs.shape[0] != n:
                raise ValueError(f"{n} landmarks but {self.landmark_covs.shape[0]} landmark covariances")
        if self.joint_cov is not None and self.joint_cov.shape != (joint_dim, joint_dim):
            raise ValueError(f"joint_cov has shape {self.joint_cov.shape}, expected ({joint_dim}, {joint_dim})")
        if self.measurements.size and (np.any(self.measurements[:, 0] < 0) or np.any(np.abs(self.measurements[:, 1]) > math.pi + 1e-9)):
            raise ValueError("measurements need range >= 0 and bearing in [-π, π]")
        if self.clutter_density + self.new_feature_density <= 0.0:
            raise ValueError("clutter_density + new_feature_density must be > 0 (the cost of leaving a measurement unassigned)")
        return self

    @property
    def size(self) -> tuple[int, int]:
        """(M measurements, N landmarks)."""
        n = self.predicted.shape[0] if self.predicted is not None else self.landmarks.shape[0]
        return int(self.measurements.shape[0]), int(n)


class AssociationReply(Message):
    """The chosen association of one scan."""

    SCHEMA_VERSION: ClassVar[int] = 1

    request_id: int = Field(0, ge=0)
    method: Literal["nn", "greedy", "ihgr", "exact", "jcbb"]
    assignment: Array(None, kind="int") = Field(description="(M,) landmark index, -1 new feature, -2 clutter, -3 ambiguous (unique_pairs)")
    missed: Array(None, kind="bool") = Field(description="(N,) landmark got no measurement")
    cost: float = Field(allow_inf_nan=False, description="Σ c_nm over the chosen pairs (all-dummy = 0)")
    solve_time_ms: float = Field(ge=0.0, allow_inf_nan=False)
    components: int | None = Field(None, ge=0, description="IHGR: connected components of the gate graph with two or more pairs")
    gated_pairs: int = Field(0, ge=0)
    lp_objective: float | None = Field(None, description="IHGR: optimum of the first LP relaxation (lower bound)")
    gap: float | None = Field(None, description="IHGR: cost − lp_objective (≥ 0; 0 means provably optimal)")
    lp_solves: int = Field(0, ge=0, description="IHGR: LPs solved")
    joint_nis: float | None = Field(None, description="JCBB: joint NIS of the chosen hypothesis")
    truncated: bool = Field(False, description="the search budget (JCBB's nodes, or the service's time budget for "
                            "greedy, IHGR and JCBB) ran out: the best found so far")
