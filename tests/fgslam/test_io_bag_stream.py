"""The streamed bag reader: the same stream as in memory, late messages, memory bounded by the
reorder window, and a streamed run equal to an in-memory one."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from fgslam.errors import BagError
from fgslam.io import BagReaderConfig
from fgslam.io.bag_decode import same_measurement
from fgslam.io.bag_reader import BagSource, read_bag
from fgslam.io.synthetic import SyntheticStreamConfig, synthetic_stream
from reloc.measurements import GroundTruthPose, ImuSample
from sim.bag_writer import write_bag


def _bag(tmp_path, duration_s: float, name: str = "bag", seed: int = 4):
    stream = synthetic_stream(SyntheticStreamConfig(duration_s=duration_s, rocks_per_frame=5.0),
                              np.random.default_rng(seed))
    write_bag(tmp_path / name, stream)
    return tmp_path / name, stream


def test_source_streams_what_read_bag_holds_and_can_be_iterated_again(tmp_path):
    bag, stream = _bag(tmp_path, 6.0)
    src = BagSource(bag)
    assert src.report is None
    first, second = list(src), list(src)
    held = read_bag(bag).measurements
    assert len(first) == len(second) == len(held) == len(stream)
    assert all(same_measurement(a, b) and same_measurement(b, c) for a, b, c in zip(first, second, held))
    assert src.report.topics["/imu"].n_kept == sum(isinstance(m, ImuSample) for m in stream)
    gt = src.ground_truth()
    assert [m.t for m in gt] == [m.t for m in stream if isinstance(m, GroundTruthPose)]
    assert src.first_stamp_s() == stream[0].t
    t0, t1 = src.span_s()
    assert t0 == pytest.approx(stream[0].t, abs=1e-6) and t1 == pytest.approx(stream[-1].t, abs=1e-6)


def _imu_bag(tmp_path, stamps_ns: list[int], log_ns: list[int]):
    """A bag of IMU samples (gyro z = their index) with the given header stamps and log times, and
    one command and one empty rock frame so that it is a valid fgslam bag."""
    from rosbags.rosbag2 import Writer

    from reloc.bag_spec import typestore
    from test_io_bag import _header, _imu, _twist

    ts = typestore()
    T = ts.types
    with Writer(tmp_path / "bag", version=8) as w:
        ci = w.add_connection("/imu", "sensor_msgs/msg/Imu", typestore=ts)
        cc = w.add_connection("/cmd_vel", "geometry_msgs/msg/Twist", typestore=ts)
        cr = w.add_connection("/rocks", "vision_msgs/msg/Detection3DArray", typestore=ts)
        w.write(cc, log_ns[0], ts.serialize_cdr(_twist(0.1, 0.0), "geometry_msgs/msg/Twist"))
        rocks = T["vision_msgs/msg/Detection3DArray"](header=_header(stamps_ns[0], "base_link"), detections=[])
        w.write(cr, log_ns[0], ts.serialize_cdr(rocks, "vision_msgs/msg/Detection3DArray"))
        for k, (s, lg) in enumerate(zip(stamps_ns, log_ns)):
            w.write(ci, lg, ts.serialize_cdr(_imu(s, gyro_z=float(k)), "sensor_msgs/msg/Imu"))
    return tmp_path / "bag"


def test_a_message_later_than_the_reorder_window_is_dropped_and_counted(tmp_path):
    s = 1_000_000_000
    # 50 samples 0.1 s apart, recorded in order, but sample 40 carries the stamp of 1.0 s: it
    # arrives 3 s after later-stamped ones
    stamps = [s + 100_000_000 * k for k in range(50)]
    stamps[40] = s + 1_000_000_000 + 50_000_000
    logs = [s + 100_000_000 * k for k in range(50)]
    bag = _imu_bag(tmp_path, stamps, logs)
    wide = read_bag(bag, config=BagReaderConfig(reorder_window_s=5.0))  # inside the window: sorted
    imu = [m for m in wide.measurements if isinstance(m, ImuSample)]
    assert len(imu) == 50 and wide.report.topics["/imu"].n_reordered == 1
    assert [m.t for m in imu] == sorted(m.t for m in imu)
    assert imu[11].gyro_radps[2] == 40.0  # put back at its stamp
    narrow = read_bag(bag, config=BagReaderConfig(reorder_window_s=1.0))
    rep = narrow.report.topics["/imu"]
    assert rep.n_late == 1 and rep.n_kept == 49 and 40.0 not in [m.gyro_radps[2] for m in narrow.measurements
                                                                   if isinstance(m, ImuSample)]
    assert any("reorder window" in line for line in narrow.report.repairs)
    with pytest.raises(BagError, match="out of order"):
        read_bag(bag, config=BagReaderConfig(reorder_window_s=1.0), repair=False)
    with pytest.raises(BagError, match="reorder_window_s"):
        BagReaderConfig(reorder_window_s=float("nan"))


def _peak_bytes(bag) -> int:
    src = BagSource(bag, config=BagReaderConfig(reorder_window_s=1.0))
    tracemalloc.start()
    n = 0
    for _ in src:
        n += 1
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return peak


def test_streaming_memory_does_not_grow_with_the_traverse(tmp_path):
    short, _ = _bag(tmp_path, 40.0, "short")
    long, _ = _bag(tmp_path, 160.0, "long")
    p_short, p_long = _peak_bytes(short), _peak_bytes(long)
    # 4x the messages; the stream holds blocks and the reorder window, not the traverse
    assert p_long < 1.5 * p_short, (p_short, p_long)
    in_memory = tracemalloc.start() or len(read_bag(long).measurements)
    _, held = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert in_memory and p_long < held  # and holding grows with the traverse, streaming does not


def test_a_streamed_run_equals_the_in_memory_run(tmp_path):
    from fgslam.backends.registry import make_backend
    from fgslam.inputs import load_bag, truth_of
    from fgslam.io.catalog_csv import write_catalog_csv
    from fgslam.runner import run_backend
    from reloc.measurements import RockCatalog

    bag, stream = _bag(tmp_path, 8.0)
    cat = tmp_path / "catalog.csv"
    write_catalog_csv(cat, RockCatalog(np.array([[0.0, 0.0], [5.0, 1.0], [2.0, 7.0]]), np.ones(3), np.ones(3)))
    held, streamed = load_bag(bag, cat, stream=False), load_bag(bag, cat, stream=True)
    assert isinstance(streamed.measurements, BagSource) and isinstance(held.measurements, list)
    assert streamed.initial.t == held.initial.t and np.array_equal(streamed.initial.T_world_base, held.initial.T_world_base)
    a = run_backend(make_backend("ekf", held.initial), held.measurements)
    b = run_backend(make_backend("ekf", streamed.initial), streamed.measurements)
    assert np.array_equal(a.final.T_world_base, b.final.T_world_base)
    assert np.array_equal(truth_of(held).T_world_base, truth_of(streamed).T_world_base)
