"""The track stage with worker processes: centroids decoded by workers while one model is tracked,
messages encoded ahead with a guess of the brightest track, and the helpers behind them."""

from __future__ import annotations

import operator
import pickle
from pathlib import Path

import pytest

from starlog.io import LogReader, LogWriter, json_message_type, topics
from starlog.io.stack import StackedLog
from starlog.stages import simulate_log
from starlog.stages import track as track_stage
from starlog.stages._blocks import channel_blocks
from starlog.stages._parallel import _Pool, ordered_map, process_pool
from starlog.stages.centroid import centroid_log
from starlog.stages.track import track_log
from tests.conftest import small_config

TOPIC = topics.centroid_topic("GAUSSFIT")


@pytest.fixture(scope="module")
def chunked_centroids(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A centroid channel in many small chunks (so in several blocks of 64 frames), as another writer may cut it."""
    folder = tmp_path_factory.mktemp("chunked")
    simulate_log(small_config(width=64, height=64, n_stars=3, n_frames=300, margin=10.0), folder / "sim.mcap")
    centroid_log(folder / "sim.mcap", folder / "cen.mcap", methods="GAUSSFIT")
    out = folder / "chunked.mcap"
    with LogReader(folder / "cen.mcap") as log, LogWriter(out, chunk_size=1024) as writer:
        channel = writer.add_channel(TOPIC, json_message_type("starlog.Centroids"))
        for _, _, message in log.raw_messages([TOPIC]):
            writer.write(channel, log_time=message.log_time, data=message.data)
    return out


def _track(source: Path, output: Path, workers: int, models: str = "STATIC") -> bytes:
    track_log(source, output, method="GAUSSFIT", models=models, tracker={"sigma_floor": 0.05}, workers=workers)
    return output.read_bytes()


def test_the_fixture_cuts_the_channel_into_several_blocks(chunked_centroids: Path) -> None:
    with LogReader(chunked_centroids) as log:
        assert len(channel_blocks(log, TOPIC, track_stage.BLOCK_FRAMES)) >= 4


@pytest.mark.parametrize("models", ["STATIC", "all"])
def test_workers_give_the_bytes_of_one_process(chunked_centroids: Path, tmp_path: Path, models: str) -> None:
    """One model: decoded by workers, encoded ahead; several: tracked by workers. The same bytes as serially."""
    assert _track(chunked_centroids, tmp_path / "w2.mcap", 2, models) == _track(chunked_centroids, tmp_path / "w1.mcap",
                                                                                  1, models)


def test_blocks_encoded_with_a_wrong_guess_are_encoded_again(chunked_centroids: Path, tmp_path: Path,
                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    serial = _track(chunked_centroids, tmp_path / "w1.mcap", 1)
    guesses: list[int | None] = []
    right_guess = track_stage._Speculation.guess

    def wrong_every_other_time(tracker: object) -> int | None:
        guess = right_guess(tracker)  # type: ignore[arg-type]
        if guess is not None and len(guesses) % 2 == 0:
            guess += 1000
        guesses.append(guess)
        return guess

    monkeypatch.setattr(track_stage._Speculation, "guess", staticmethod(wrong_every_other_time))
    assert _track(chunked_centroids, tmp_path / "w2.mcap", 2) == serial
    assert any(g is not None and g >= 1000 for g in guesses) and any(g is not None and g < 1000 for g in guesses)
    assert not list(tmp_path.glob(".w2.mcap.track-*")), "the encoded blocks' folder is removed"


def test_ordered_map_computes_here_until_the_workers_are_up() -> None:
    items = [(2, k) for k in range(7)]
    not_started = _Pool(max_workers=1)  # its workers are never started: every item is computed here
    here: list[tuple[int, int]] = []

    def locally(*item: int) -> int:
        here.append(item)
        return operator.pow(*item)

    assert list(ordered_map(not_started, operator.pow, items, window=2, until_ready=locally)) == [2**k for k in range(7)]
    assert here == items
    not_started.shutdown()
    with process_pool(1) as pool:
        results = list(ordered_map(pool, operator.pow, items, window=2, until_ready=operator.pow))
    assert results == [2**k for k in range(7)]


def test_a_stacked_log_pickles_for_a_worker_to_read(chunked_centroids: Path, tmp_path: Path) -> None:
    stack = StackedLog.of(chunked_centroids)
    with LogWriter(tmp_path / "side.mcap", base=stack) as writer:
        channel = writer.add_channel("/extra", json_message_type("starlog.Centroids"))
        writer.write(channel, log_time=1, data=b'{"frame":0,"method":"GAUSSFIT","stars":[]}')
    stacked = stack.extend(tmp_path / "side.mcap")
    copy = pickle.loads(pickle.dumps(stacked))
    assert copy.files() == stacked.files() == (chunked_centroids, tmp_path / "side.mcap")
    assert copy.digest() == stacked.digest()
    with LogReader(stacked) as a, LogReader(copy) as b:
        assert [m.payload for m in a.messages([TOPIC, "/extra"])] == [m.payload for m in b.messages([TOPIC, "/extra"])]
    # a copy hashes its data section again when it is extended
    assert pickle.loads(pickle.dumps(stack)).extend(tmp_path / "side.mcap").digest() == stacked.digest()
