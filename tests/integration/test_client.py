"""The RobotLink example of docs/robots.md, run as written against ``fleetslam demo``: a robot of one's own joins
the secured demo as ``guest``, is fused by central, and reads its pose back; and RobotLink's own checks."""

import os
import re
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from schemas.config import FleetSettings
from schemas.messages import RobotInfo, SensorSpec
from services.client import RobotLink
from tests.helpers import REPO, free_port, wait_until

pytestmark = pytest.mark.integration


def _docs_block(heading: str, language: str) -> str:
    """The first ``language`` code block after ``heading`` in docs/robots.md."""
    text = (REPO / "docs" / "robots.md").read_text()
    section = text[text.index(heading):]
    return re.search(rf"```{language}\n(.*?)```", section, re.S).group(1)


def test_the_docs_example_robot_joins_the_demo_and_reads_its_central_pose(tmp_path):
    example = tmp_path / "my_robot.py"
    example.write_text(_docs_block("## A robot of your own, in Python", "python"))
    command = _docs_block("Run it against the demo", "bash").splitlines()[1]
    assert command.startswith("FLEETSLAM_ZENOH_USER=guest") and command.endswith("python my_robot.py")
    port = free_port()
    env = {key: value for key, value in os.environ.items() if not key.startswith("FLEETSLAM_")}
    env.update(PYTHONUNBUFFERED="1", PYTHONPATH=str(REPO))
    demo = subprocess.Popen([sys.executable, "-m", "services.cli", "demo", "--duration", "90", "--port", str(port),
                             "--robots", "1", "--unknown-start-robots", "0", "--out", str(tmp_path / "demo")],
                            cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines: list[str] = []
    try:
        wait_until(lambda: (lines.append(demo.stdout.readline()), "a robot of your own" in lines[-1])[1], 90,
                   what="the demo's line for a robot of one's own")
        assigned = dict(re.findall(r"(FLEETSLAM_\w+)=(\S+)", command))
        assert assigned["FLEETSLAM_ZENOH_PASSWORD_FILE"] == ".fleetslam/secrets/guest.password"
        assert (tmp_path / assigned["FLEETSLAM_ZENOH_PASSWORD_FILE"]).is_file()
        robot = subprocess.run([sys.executable, example.name], cwd=tmp_path, timeout=120, capture_output=True,
                               text=True, env={**env, **assigned, "FLEETSLAM_ZENOH_CONNECT": f"tcp/127.0.0.1:{port}"})
        assert robot.returncode == 0, robot.stdout + robot.stderr
        fused = re.search(r"central: \[(.*?)\] true: \[(.*?)\]", robot.stdout)
        assert fused, robot.stdout + robot.stderr
        estimate, truth = (np.array(group.split(), float) for group in fused.groups())
        assert np.hypot(*(estimate - truth)[:2]) < 0.5, robot.stdout
    finally:
        if demo.poll() is None:
            demo.send_signal(signal.SIGINT)
        try:
            demo.wait(timeout=60)
        except subprocess.TimeoutExpired:
            demo.kill()
            demo.wait()


def _info(robot_id: str = "link1") -> RobotInfo:
    return RobotInfo(robot_id=robot_id, stamp=0.0, motion_model="unicycle",
                     sensor=SensorSpec(max_range=8.0, fov=np.pi, noise_cov=np.diag([0.01, 0.001])),
                     start_pose=np.zeros(3), start_pose_cov=np.eye(3) * 1e-4, odom_rate_hz=10, scan_rate_hz=10)


def test_a_link_refuses_time_going_backwards_and_bad_shapes_before_publishing(router):
    with RobotLink.connect(_info(), FleetSettings(zenoh_connect=router.endpoint), follow_estimates=False) as link:
        link.odometry(0.1, [0.2, 0.0], np.eye(2) * 1e-3, stamp=10.0)
        with pytest.raises(ValueError, match="time_backwards"):
            link.odometry(0.1, [0.2, 0.0], np.eye(2) * 1e-3, stamp=9.0)
        with pytest.raises(ValueError):
            link.scan([1.0, 2.0], [0.1], stamp=10.0)
        with pytest.raises(ValueError):
            link.odometry(0.1, [float("nan"), 0.0], np.eye(2) * 1e-3, stamp=11.0)
        assert link.counts["odom"] == 1 and link.counts["scan"] == 0 and link.counts["info"] == 1
