"""What ``fleetslam viz`` (and ``fleetslam run --rerun``) draw and how often: a plain frozen model, never read
from the environment (the ``fleetslam viz`` settings class composes it)."""

from __future__ import annotations

from pydantic import Field

from schemas.contract import CoreConfig


class VizConfig(CoreConfig):
    """Throttles and drawing sizes of the Rerun scene."""

    map_hz: float = Field(2.0, gt=0, le=50, description="most landmark-map logs (points and covariance ellipses) per "
                          "second and map source; the latest map always gets logged")
    path_hz: float = Field(2.0, gt=0, le=50, description="most logs per second of each trajectory's growing segment")
    hypotheses_hz: float = Field(5.0, gt=0, le=50, description="most logs per second of each robot's MCL hypotheses")
    path_segment_points: int = Field(
        500, ge=2, le=100_000, description="a trajectory is drawn as segments of this many points: a full segment is "
        "logged once and never again, so a long run does not re-send its whole path")
    path_min_step_m: float = Field(0.01, ge=0, description="a trajectory point closer than this to the last kept one is "
                                   "skipped (a robot standing still adds nothing)")
    ellipse_confidence: float = Field(0.95, gt=0, lt=1, description="confidence of the landmark covariance ellipses "
                                      "(chi-square, 2 dof)")
    ellipse_vertices: int = Field(24, ge=8, le=256, description="vertices of each covariance ellipse")
    arrow_fraction: float = Field(0.1, gt=0, description="pose arrows are this fraction of the robot's sensor range long")
