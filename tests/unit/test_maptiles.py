"""Maps sent by the tiles that changed (schemas.maptiles, services.mapfeed): receivers hold the producer's map, the
steady cost follows what changed rather than the map's size, a missed delta is caught and mended by a full map."""

from __future__ import annotations

import numpy as np
import pytest

from schemas.codec import DecodeError, decode, encode
from schemas.maptiles import TiledMap, TileSender, tile_keys
from schemas.messages import Estimate, MapEstimate
from services.mapfeed import MapFeed, tile_block


def _map(rng: np.random.Generator, n: int, side: float) -> tuple[np.ndarray, np.ndarray]:
    means = rng.uniform(0.0, side, (n, 2))
    covs = np.tile(np.diag([0.04, 0.04]), (n, 1, 1)) * rng.uniform(0.5, 2.0, (n, 1, 1))
    return means, covs


def _step(rng: np.random.Generator, means, covs, near: np.ndarray, radius: float = 6.0):
    """Landmarks within ``radius`` of ``near`` move and shrink (observed); one is born there, one dies far away."""
    means, covs = means.copy(), covs.copy()
    seen = np.hypot(*(means - near).T) < radius
    means[seen] += rng.normal(0.0, 0.05, (int(seen.sum()), 2))
    covs[seen] *= 0.8
    means = np.vstack([means, near + rng.normal(0.0, 2.0, 2)])
    covs = np.concatenate([covs, np.diag([0.1, 0.1])[None]])
    far = np.flatnonzero(~np.append(seen, True))
    if far.size and rng.random() < 0.2:
        keep = np.ones(means.shape[0], bool)
        keep[far[0]] = False
        means, covs = means[keep], covs[keep]
    return means, covs


def _sorted_rows(means, covs=None):
    order = np.lexsort((means[:, 1], means[:, 0]))
    return means[order], None if covs is None else covs[order]


def test_a_receiver_of_every_delta_holds_the_map_within_the_tolerance():
    rng = np.random.default_rng(0)
    means, covs = _map(rng, 400, 100.0)
    sender, receiver = TileSender(10.0, 0.0, 0.0), TiledMap()
    for seq in range(40):
        near = rng.uniform(0.0, 100.0, 2)
        means, covs = _step(rng, means, covs, near)
        block = sender.delta(means, covs)
        assert block.full == (seq == 0)
        assert receiver.take(seq, block)
        got_means, got_covs, _ = receiver.landmarks()
        want_means, want_covs = _sorted_rows(means, covs)
        got_means, got_covs = _sorted_rows(got_means, got_covs)
        np.testing.assert_array_equal(got_means, want_means)  # tolerance 0: exactly the producer's map
        np.testing.assert_array_equal(got_covs, want_covs)


def test_with_a_tolerance_small_moves_are_not_sent_and_the_receiver_stays_within_it():
    rng = np.random.default_rng(1)
    means, covs = _map(rng, 200, 50.0)
    sender, receiver = TileSender(10.0, 0.05, 0.5), TiledMap()
    receiver.take(0, sender.delta(means, covs))
    nudged = means + rng.normal(0.0, 0.005, means.shape)  # far below 5 cm: nothing to send
    block = sender.delta(nudged, covs)
    assert block.tiles.shape[0] == 0 and block.means.shape[0] == 0
    assert receiver.take(1, block)
    got, _, _ = receiver.landmarks()
    nearest = np.hypot(*(got[:, None, :] - nudged[None, :, :]).transpose(2, 0, 1)).min(axis=0)
    assert got.shape == nudged.shape and nearest.max() < 0.05


def test_the_steady_cost_follows_what_changed_not_the_map_size():
    sizes = {}
    for n, side in ((100, 100.0), (10_000, 1000.0)):
        rng = np.random.default_rng(2)
        means, covs = _map(rng, n, side)
        sender = TileSender(10.0, 0.01, 0.1)
        sender.delta(means, covs)  # the first, full message
        total = 0
        for seq in range(1, 21):
            means, covs = _step(rng, means, covs, near=np.array([50.0, 50.0]))
            block = sender.delta(means, covs)
            total += block.means.shape[0]
        sizes[n] = total
    full = TileSender(10.0, 0.01, 0.1).delta(*_map(np.random.default_rng(2), 10_000, 1000.0)).means.shape[0]
    assert full == 10_000
    assert sizes[10_000] <= 2 * sizes[100], sizes  # the same neighbourhood changes: about the same landmarks sent


def test_a_missed_delta_is_caught_and_a_full_reply_with_the_deltas_after_it_mends_the_map():
    rng = np.random.default_rng(3)
    means, covs = _map(rng, 300, 80.0)
    sender, receiver = TileSender(10.0, 0.0, 0.0), TiledMap()
    assert receiver.take(0, sender.delta(means, covs))
    means, covs = _step(rng, means, covs, near=np.array([20.0, 20.0]))
    sender.delta(means, covs)  # seq 1: lost on the way
    means, covs = _step(rng, means, covs, near=np.array([60.0, 60.0]))
    assert not receiver.take(2, sender.delta(means, covs)), "a gap must be reported"
    means, covs = _step(rng, means, covs, near=np.array([40.0, 10.0]))
    reply = sender.snapshot(means, covs)  # the state query's answer: full, repeating the next number (3)
    means, covs = _step(rng, means, covs, near=np.array([10.0, 70.0]))
    delta3 = sender.delta(means, covs)
    assert receiver.take(3, delta3) is False  # arrives before the reply: kept
    assert receiver.take(3, reply, reply=True)
    got, _, _ = receiver.landmarks()
    np.testing.assert_array_equal(_sorted_rows(got)[0], _sorted_rows(means)[0])


def test_a_tile_that_changed_for_a_full_reply_and_changed_back_is_sent_again():
    """The reply held a tile's passing state; the map went back to what the subscribers hold. Without the owed
    tiles the next delta would not list it and the receiver that applied the reply would keep the passing state."""
    means = np.array([[1.0, 1.0], [15.0, 15.0]])
    sender = TileSender(10.0, 0.0, 0.0)
    sender.delta(means)
    passing = means + np.array([[0.5, 0.0], [0.0, 0.0]])
    receiver = TiledMap()
    receiver.take(1, sender.snapshot(passing), reply=True)
    block = sender.delta(means)
    assert block.tiles.tolist() == [[0, 0]]
    assert receiver.take(1, block)
    np.testing.assert_array_equal(_sorted_rows(receiver.landmarks()[0])[0], means)


def test_ids_travel_with_their_landmarks_and_tiles_are_named_by_floor():
    means = np.array([[-0.5, 0.5], [9.99, 10.0], [25.0, -3.0]])
    ids = np.array([7, 3, 11])
    block = TileSender(10.0, 0.0, 0.0).delta(means, ids=ids)
    assert sorted(map(tuple, block.tiles.tolist())) == [(-1, 0), (0, 1), (2, -1)]
    receiver = TiledMap()
    receiver.take(0, block)
    got_means, _, got_ids = receiver.landmarks()
    assert dict(zip(got_ids.tolist(), map(tuple, got_means.tolist()))) == {7: (-0.5, 0.5), 3: (9.99, 10.0),
                                                                             11: (25.0, -3.0)}
    assert len(set(tile_keys(means, 10.0).tolist())) == 3


def _estimate(block, seq: int) -> Estimate:
    return Estimate(seq=seq, stamp=float(seq), robots=[], landmarks=block.means, landmark_covs=block.covs,
                    full=block.full, tile_size=block.tile_size, tiles=block.tiles, tile_counts=block.counts,
                    particles=10, effective_particles=10.0)


def test_tiled_messages_cross_the_codec_and_bad_tiles_are_refused():
    rng = np.random.default_rng(4)
    means, covs = _map(rng, 50, 30.0)
    message = _estimate(TileSender(10.0, 0.0, 0.0).delta(means, covs), 0)
    again = decode(encode(message), Estimate)
    np.testing.assert_array_equal(again.tiles, message.tiles)
    body = message.model_dump()
    with pytest.raises(DecodeError, match="tile_counts do not add up"):
        bad = Estimate.model_construct(**{**body, "tile_counts": body["tile_counts"] + 1})
        decode(encode(bad), Estimate)
    with pytest.raises(DecodeError, match="needs tile_size"):
        decode(encode(Estimate.model_construct(**{**body, "full": False, "tile_size": 0.0})), Estimate)
    with pytest.raises(DecodeError, match="listed twice"):
        twice = {**body, "tiles": np.vstack([body["tiles"][:1]] * 2), "tile_counts": np.array([50, 0])}
        decode(encode(Estimate.model_construct(**twice)), Estimate)


def test_an_untiled_full_message_is_the_whole_map():
    message = MapEstimate(seq=4, stamp=1.0, landmarks=np.array([[1.0, 2.0], [30.0, 4.0]]), landmark_ids=np.array([5, 6]))
    tiles = TiledMap()
    assert tiles.take(message.seq, tile_block(message))
    assert sorted(tiles.landmarks()[2].tolist()) == [5, 6]


class _Session:
    def __init__(self):
        self.asked: list[str] = []

    def get(self, key, callback, timeout):
        self.asked.append(key)


class _Shell:
    def __init__(self):
        self.session = _Session()


def test_the_feed_gives_whole_maps_and_asks_for_a_full_one_when_it_joins_late():
    rng = np.random.default_rng(5)
    means, covs = _map(rng, 100, 40.0)
    sender, shell = TileSender(10.0, 0.0, 0.0), _Shell()
    feed = MapFeed(shell, Estimate, "fleet/central/state", "central_state")
    sender.delta(means, covs)  # seq 0, before the feed started
    means, covs = _step(rng, means, covs, near=np.array([10.0, 10.0]))
    assert feed.take(_estimate(sender.delta(means, covs), 1)) is None
    assert shell.session.asked == ["fleet/central/state"]
    assert feed.take(_estimate(sender.delta(means, covs), 2)) is None
    assert shell.session.asked == ["fleet/central/state"], "asked again before ask_every_s"
    whole = feed.take(_estimate(sender.snapshot(means, covs), 3), reply=True)
    assert whole is not None and whole.full and whole.landmarks.shape[0] == means.shape[0]
    np.testing.assert_array_equal(_sorted_rows(whole.landmarks)[0], _sorted_rows(means)[0])


def test_after_a_missed_delta_the_feed_keeps_the_map_before_the_gap_until_a_full_one_mends_it():
    rng = np.random.default_rng(6)
    means, covs = _map(rng, 100, 40.0)
    sender, shell = TileSender(10.0, 0.0, 0.0), _Shell()
    feed = MapFeed(shell, Estimate, "fleet/central/state", "central_state")
    before = feed.take(_estimate(sender.delta(means, covs), 0))
    moved, moved_covs = _step(rng, means, covs, near=np.array([10.0, 10.0]))
    sender.delta(moved, moved_covs)  # seq 1: lost
    stale = feed.take(_estimate(sender.delta(moved, moved_covs), 2))
    assert shell.session.asked == ["fleet/central/state"]
    np.testing.assert_array_equal(stale.landmarks, before.landmarks)
    mended = feed.take(_estimate(sender.snapshot(moved, moved_covs), 3), reply=True)
    np.testing.assert_array_equal(_sorted_rows(mended.landmarks)[0], _sorted_rows(moved)[0])
