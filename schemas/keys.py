"""Key expressions of DESIGN §2, built from one prefix (setting ``FLEETSLAM_PREFIX``)."""

from __future__ import annotations

import re
from dataclasses import dataclass

from schemas.messages import ROBOT_ID_PATTERN

ROBOT_STREAMS = ("odom", "scan", "truth")
_ROBOT_ID = re.compile(ROBOT_ID_PATTERN)


def check_robot_id(robot_id: str) -> str:
    """Return ``robot_id`` if it is a valid id (letters, digits, ``_``, ``-``), else raise ValueError."""
    if not _ROBOT_ID.match(robot_id):
        raise ValueError(f"invalid robot id {robot_id!r}: use letters, digits, '_' or '-' (at most 64)")
    return robot_id


@dataclass(frozen=True)
class Keys:
    """Builders for every key expression under one prefix."""

    prefix: str = "fleet"

    def robot(self, robot_id: str, stream: str) -> str:
        return f"{self.prefix}/robots/{check_robot_id(robot_id)}/{stream}"

    def info(self, robot_id: str) -> str:
        return self.robot(robot_id, "info")

    def history(self, robot_id: str) -> str:
        """A robot's queryable answering with the odometry and scans it kept (for a restarted service)."""
        return f"{self.prefix}/robots/{check_robot_id(robot_id)}/history"

    def alive(self, robot_id: str) -> str:
        return self.robot(robot_id, "alive")

    def session_token(self, robot_id: str, zid: str) -> str:
        """The liveliness token a robot's Zenoh session declares besides :meth:`alive`: it names the session, so a
        service knows which one owns the robot id (the first to hold it) and refuses the others' messages."""
        return f"{self.alive(robot_id)}/{zid}"

    def odom(self, robot_id: str) -> str:
        return self.robot(robot_id, "odom")

    def scan(self, robot_id: str) -> str:
        return self.robot(robot_id, "scan")

    def truth(self, robot_id: str) -> str:
        return self.robot(robot_id, "truth")

    @property
    def all_robots(self) -> str:
        return f"{self.prefix}/robots/*/*"

    def all_robot_stream(self, stream: str) -> str:
        return f"{self.prefix}/robots/*/{stream}"

    @property
    def alive_any(self) -> str:
        return f"{self.prefix}/robots/*/alive"

    @property
    def session_tokens_any(self) -> str:
        return f"{self.prefix}/robots/*/alive/*"

    @property
    def world_truth(self) -> str:
        return f"{self.prefix}/world/truth"

    @property
    def central_estimate(self) -> str:
        return f"{self.prefix}/central/estimate"

    @property
    def central_state(self) -> str:
        return f"{self.prefix}/central/state"

    @property
    def dslam_map(self) -> str:
        return f"{self.prefix}/dslam/map"

    @property
    def dslam_state(self) -> str:
        return f"{self.prefix}/dslam/state"

    def dslam_pose(self, robot_id: str) -> str:
        return f"{self.prefix}/dslam/pose/{check_robot_id(robot_id)}"

    def assoc(self, method: str) -> str:
        return f"{self.prefix}/assoc/{method}"

    def mcl_pose(self, robot_id: str) -> str:
        return f"{self.prefix}/mcl/{check_robot_id(robot_id)}/pose"

    @property
    def mcl_localize(self) -> str:
        return f"{self.prefix}/mcl/localize"

    @property
    def eval_stats(self) -> str:
        return f"{self.prefix}/eval/stats"

    def stats(self, service: str) -> str:
        return f"{self.prefix}/{service}/stats"

    @property
    def all_stats(self) -> str:
        return f"{self.prefix}/**/stats"

    @property
    def everything(self) -> str:
        return f"{self.prefix}/**"

    def parse_robot_key(self, key: str) -> tuple[str, str] | None:
        """Split ``{prefix}/robots/{rid}/{stream}`` into (rid, stream); None if it is not one."""
        head = f"{self.prefix}/robots/"
        if not key.startswith(head):
            return None
        parts = key[len(head):].split("/")
        if len(parts) != 2 or not _ROBOT_ID.match(parts[0]):
            return None
        return parts[0], parts[1]

    def parse_session_token(self, key: str) -> tuple[str, str] | None:
        """Split ``{prefix}/robots/{rid}/alive/{zid}`` into (rid, zid); None if it is not one."""
        head = f"{self.prefix}/robots/"
        parts = key[len(head):].split("/") if key.startswith(head) else []
        if len(parts) != 3 or parts[1] != "alive" or not _ROBOT_ID.match(parts[0]) or not parts[2]:
            return None
        return parts[0], parts[2]
