"""The live benchmark's figures of a recorded live run (bags/map_joining, a `csam demo`): the
lag lines, the final joined map's time after the data against an independent reading of the
bag, the landmark metrics; and the machine's yardstick absent without its data set."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from mcap.reader import make_reader

from csam_ros.bag import BagWriter, read_bag
from csam_ros.bench import live, smoothing
from csam_ros.run.lag import RUN_PARTS
from csam_ros.run.offline import offline_summary

BAG = Path(__file__).resolve().parents[2] / "bags" / "map_joining"
SENSOR_SUFFIXES = ("/odom", "/features", "/feature_points", "/rendezvous")


def _final_after_data_by_mcap(bag: Path) -> float:
    data_end = joined = 0
    for path in sorted(bag.glob("*.mcap")):
        with open(path, "rb") as stream:
            for _, channel, message in make_reader(stream).iter_messages():
                if channel.topic == "/csam/joined_map":
                    joined = max(joined, message.log_time)
                elif channel.topic.endswith(SENSOR_SUFFIXES):
                    data_end = max(data_end, message.log_time)
    return (joined - data_end) / 1e9


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("live")
    shutil.copytree(BAG, out / "bag")
    summary, _ = offline_summary(BAG)
    summary.write(out / "summary.json")
    return out


def test_final_map_after_the_data_as_the_mcap_reader_sees_it(run_dir: Path) -> None:
    expected = _final_after_data_by_mcap(run_dir / "bag")
    assert live.final_after_data(run_dir / "bag") == pytest.approx(expected, abs=1e-9)


def test_lines_of_a_live_run(run_dir: Path) -> None:
    lines = live.live_lines(run_dir)
    assert lines[0].startswith("lag from a local map to the joined map that uses it: mean ")
    assert any(line.startswith("merger: ") for line in lines)
    over = lines.index("over the run (local maps by arrival, solves by their report):")
    spans = lines[over + 1 : over + 1 + RUN_PARTS]
    assert len(spans) == RUN_PARTS and all(" s " in span for span in spans)
    counts = [int(span.split(" maps")[0].split()[-1]) for span in spans]
    assert sum(counts) == 52  # every local map update of bags/map_joining, in one span each
    final = next(line for line in lines if line.startswith("the final joined map "))
    assert f"{live.final_after_data(run_dir / 'bag'):.2f} s after the data" in final
    metrics = json.loads((run_dir / "metrics.json").read_text())
    rmse = metrics["landmark_error"]["rmse_m"]
    assert any(f"RMSE {rmse:.3f} m" in line for line in lines)


def test_latency_figure_beside_the_run(run_dir: Path) -> None:
    lines = live.live_lines(run_dir)
    assert f"the lags and solves over the run: {run_dir / 'latency.png'}" in lines
    assert (run_dir / "latency.png").read_bytes().startswith(b"\x89PNG")


def test_a_bag_without_a_joined_map_is_refused(tmp_path: Path) -> None:
    with BagWriter(tmp_path / "sensors") as bag:
        for message in read_bag(BAG):
            if message.topic.endswith(SENSOR_SUFFIXES):
                if message.topic not in bag.topics:
                    bag.add_topic(message.topic, message.msgtype)
                bag.write(message.topic, message.log_time_ns, message.data)
    with pytest.raises(ValueError, match="no sensor data or no joined map"):
        live.final_after_data(tmp_path / "sensors")


def test_no_yardstick_without_victoria_park(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(smoothing, "victoria_park_path", lambda: None)
    assert smoothing.victoria_park_lm_seconds() is None
