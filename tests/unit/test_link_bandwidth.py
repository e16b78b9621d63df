"""What a robot costs on the links (issue 54): the RobotInfo re-publication backs off, routers neither stamp samples
nor leave router links uncompressed, a robot stopped by a signal still lingers one heartbeat, and the messages of one
instant are published together. Measured by benchmarks/bandwidth.py; these pin the behaviour."""

from __future__ import annotations

from dataclasses import dataclass

import pytest

from robots.process import Instant, instants, single
from schemas.config import FleetSettings, RobotSettings, RouterSettings
from schemas.transport import linger_time, zenoh_config
from services.client import InfoSchedule


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def publish_times(schedule: InfoSchedule, clock: Clock, until: float, step: float = 0.25) -> list[float]:
    times = []
    while clock.now <= until:
        if schedule.due():
            schedule.published()
            times.append(clock.now - 100.0)
        clock.now += step
    return times


def test_the_robot_info_is_published_at_once_then_less_and_less_often_up_to_the_longest_period():
    clock = Clock()
    schedule = InfoSchedule(1.0, 30.0, clock)
    assert publish_times(schedule, clock, 100.0 + 130.0) == [0.0, 1.0, 3.0, 7.0, 15.0, 31.0, 61.0, 91.0, 121.0]


def test_a_new_robot_info_starts_the_back_off_again():
    clock = Clock()
    schedule = InfoSchedule(1.0, 30.0, clock)
    publish_times(schedule, clock, 100.0 + 40.0)
    schedule.restart()  # what RobotLink.publish_info(new_info) does, before it publishes
    schedule.published()
    start = clock.now
    assert [t - (start - 100.0) for t in publish_times(schedule, clock, start + 8.0)] == [1.0, 3.0, 7.0]


def test_a_longest_period_equal_to_the_first_publishes_every_period_as_before():
    clock = Clock()
    schedule = InfoSchedule(1.0, 1.0, clock)
    assert publish_times(schedule, clock, 100.0 + 5.0) == [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]
    assert InfoSchedule(2.0, 0.5).max_s == 2.0  # never shorter than the first period


def test_defaults_of_the_link_settings():
    settings = FleetSettings()
    assert settings.info_max_period_s == 30.0 and settings.heartbeat_period_s == 1.0
    assert RobotSettings().publish_together is True
    router = RouterSettings()
    assert router.router_timestamps is False and router.link_compression is True


def test_a_router_neither_stamps_samples_nor_leaves_its_router_links_uncompressed_by_default():
    conf = zenoh_config(RouterSettings(), mode="router")
    assert conf.get_json("timestamping/enabled") == "false"
    assert conf.get_json("transport/unicast/compression/enabled") == "true"
    conf = zenoh_config(RouterSettings(router_timestamps=True, link_compression=False), mode="router")
    assert conf.get_json("timestamping/enabled") == "true"
    assert conf.get_json("transport/unicast/compression/enabled") == "false"


def test_a_client_does_not_offer_compression():
    """Compression is negotiated: a link is compressed only when both ends offer it, so a client's link to its
    (local) router stays as it is."""
    conf = zenoh_config(FleetSettings(), mode="client")
    assert conf.get_json("transport/unicast/compression/enabled") == "false"


@pytest.mark.parametrize("configured, signal, heartbeat, expected", [
    (2.0, False, None, 2.0), (2.0, True, None, 1.0), (2.0, True, 1.0, 1.0), (0.5, True, 1.0, 0.5),
    (10.0, True, 3.0, 3.0), (10.0, False, 3.0, 10.0),
])
def test_a_robot_stopped_by_a_signal_lingers_a_second_or_one_heartbeat_period(configured, signal, heartbeat,
                                                                             expected):
    assert linger_time(configured, signal, heartbeat) == expected


@dataclass
class Event:
    stamp: float
    name: str


def test_events_of_one_stamp_are_published_together_in_their_order():
    events = [Event(0.0, "scan"), Event(0.1, "odom"), Event(0.1, "scan"), Event(0.2, "odom"), Event(0.3, "odom"),
              Event(0.3, "scan"), Event(0.3, "truth")]
    grouped = list(instants(iter(events)))
    assert [(i.stamp, [e.name for e in i.events]) for i in grouped] == [
        (0.0, ["scan"]), (0.1, ["odom", "scan"]), (0.2, ["odom"]), (0.3, ["odom", "scan", "truth"])]
    assert [e for i in grouped for e in i.events] == events
    assert list(instants(iter([]))) == []
    assert [i.events for i in single(iter(events[:2]))] == [[events[0]], [events[1]]]
    assert isinstance(grouped[0], Instant)
