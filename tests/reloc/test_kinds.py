"""The landmark-kind registry, and an unregistered kind refused everywhere it could turn up: the
sort order, the bag writer and reader, the EKF's history replay, the smoother's keys."""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np
import pytest

from reloc.errors import RelocError
from reloc.kinds import (
    ROCKS,
    KindLayerError,
    LandmarkKind,
    UnknownKindError,
    all_kinds,
    kind_code,
    kind_named,
    kind_of,
    kind_of_symbol,
    registered,
)
from reloc.measurements import RockObservations, sort_key


@dataclasses.dataclass(frozen=True)
class Odd:
    t: float
    xyz_base_m: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 3)))

    def __len__(self) -> int:
        return 0


def test_rocks_are_registered_with_every_layer():
    assert kind_named("rocks") is ROCKS and ROCKS in all_kinds()
    assert kind_of(RockObservations) is ROCKS and kind_of_symbol("l") is ROCKS
    for layer in ("measurement", "bag", "ekf", "smoother", "relocalizer", "catalog", "rerun"):
        assert ROCKS.has(layer) and ROCKS.layer(layer) is not None


def test_registration_checks_name_rank_and_symbol():
    with pytest.raises(KindLayerError, match="rank"):
        LandmarkKind("x1", Odd, rank=2, symbol="q")
    for bad in ("x", "c", "Q", "qq", "1"):
        with pytest.raises(KindLayerError, match="symbol"):
            LandmarkKind("x1", Odd, rank=9, symbol=bad)
    with pytest.raises(KindLayerError, match="identifier"):
        LandmarkKind("two words", Odd, rank=9, symbol="q")
    with pytest.raises(KindLayerError, match="already registered"), registered(LandmarkKind("rocks", Odd, rank=9, symbol="q")):
        pass
    with pytest.raises(KindLayerError, match="rank 4 is taken by 'rocks'"), registered(LandmarkKind("odd", Odd, rank=4, symbol="q")):
        pass
    with pytest.raises(KindLayerError, match="symbol 'l' is taken by 'rocks'"), registered(LandmarkKind("odd", Odd, rank=9, symbol="l")):
        pass


def test_a_kind_is_known_only_while_registered_and_keeps_its_code():
    odd = LandmarkKind("odd", Odd, rank=9, symbol="q")
    with registered(odd):
        assert kind_of(Odd(1.0)) is odd and kind_of_symbol("q") is odd
        code = kind_code("odd")
        assert sort_key(Odd(1.0)) == (1.0, 9)
        with pytest.raises(KindLayerError, match="'odd' has no ekf layer"):
            odd.layer("ekf")
    with pytest.raises(UnknownKindError, match="Odd is not the observation of any registered landmark kind"):
        kind_of(Odd(1.0))
    with registered(odd):
        assert kind_code("odd") == code != kind_code("rocks")


def test_a_layer_that_does_not_import_is_named():
    odd = LandmarkKind("odd", Odd, rank=9, symbol="q", ekf="no_such_module:Thing")
    with registered(odd), pytest.raises(KindLayerError, match="ekf layer 'no_such_module:Thing' does not import"):
        kind_named("odd").layer("ekf")


def test_sort_key_and_the_bag_writer_refuse_an_unknown_type(tmp_path):
    from sim.bag_writer import BagWriteError, write_bag

    with pytest.raises(UnknownKindError, match="Odd"):
        sort_key(Odd(0.0))
    with pytest.raises(BagWriteError, match="cannot write Odd .* registered landmark kind"):
        write_bag(tmp_path / "bag", [Odd(0.0)])


def test_the_bag_reader_refuses_unknown_kinds(tmp_path):
    from fgslam.errors import BagError
    from fgslam.io.bag_reader import read_bag
    from reloc.bag_spec import TopicNames

    with pytest.raises(BagError, match="no landmark kind 'lava_tubes' is registered"):
        read_bag(tmp_path / "nothing", kinds=["lava_tubes"])
    with pytest.raises(BagError, match="no landmark kind 'lava_tubes' is registered"):
        read_bag(tmp_path / "nothing", topics=TopicNames(kinds={"lava_tubes": "/lava_tubes"}))


def test_the_ekf_replay_refuses_an_unknown_history_entry():
    from ekf import EkfSlam
    from ekf.errors import EkfError
    from ekf.history import Entry
    from reloc.backend import PoseEstimate
    from reloc.measurements import GlobalFix
    from reloc.odometry import OdometryStep

    ekf = EkfSlam(PoseEstimate(0.0, np.eye(4), np.eye(6) * 1e-4))
    R = np.eye(3)
    for k in range(30):
        ekf.predict(OdometryStep(0.1 * k, 0.1 * (k + 1), 0.1, 0.0, R, R, np.zeros(3)))
        if k == 5:
            ekf._hist.log.append(Entry("mystery", 0.6, object()))  # not a step, frame or fix
    with pytest.raises(EkfError, match="history entry of unknown kind 'mystery'"):
        ekf.apply_fix(GlobalFix(0.3, 3.0, 0.03, 0.0, 0.0, np.eye(3) * 0.01))


def test_the_smoother_refuses_keys_of_no_kind():
    from fgslam.errors import SmootherError
    from fgslam.smoother import Isam2Smoother
    from reloc.backend import PoseEstimate

    sm = Isam2Smoother(PoseEstimate(0.0, np.eye(4), np.eye(6) * 1e-4))
    key = gtsam.symbol("q", 0)
    values = gtsam.Values()
    values.insert(key, np.zeros(3))
    with pytest.raises(SmootherError, match="key symbol 'q' is no variable of the smoother"):
        sm.solver.update(gtsam.NonlinearFactorGraph(), values)
    with pytest.raises(SmootherError, match="belongs to no landmark kind"):
        sm.kinds.for_key(key)
    assert issubclass(UnknownKindError, RelocError)
