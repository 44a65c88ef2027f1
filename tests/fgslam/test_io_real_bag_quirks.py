"""Habits of real ROS 2 bags recorded by other software (found in public bags, e.g. amber's
soccer_goal recording): per-message zstd compression, known only from metadata.yaml, read as the
bare storage file; ROS 1-style type names (``sensor_msgs/Image``), with and without type hashes.
Both the image path (``fgslam detect``, :class:`StereoBag`) and the run's reader (:class:`BagSource`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import Writer
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode, StoragePlugin

from fgslam.cli import main
from fgslam.errors import BagError
from fgslam.io import read_bag
from fgslam.io.bag_decode import same_measurement
from fgslam.io.bag_reader import BagSource
from fgslam.io.image_rocks import ImageInputConfig, StereoBag
from fgslam.io.synthetic import SyntheticStreamConfig, synthetic_stream
from reloc.bag_spec import ros2_msgtype, typestore
from reloc.measurements import ImuSample
from sim.bag_writer import write_bag

CAM = {"left_image": "/cam/left/image_raw", "right_image": "/cam/right/image_raw",
       "left_info": "/cam/left/camera_info", "right_info": "/cam/right/camera_info"}
CAM_ARGS = [a for role, topic in CAM.items() for a in ("--topic", f"{role}={topic}")]
T_BASE_CAM = [0, 0, 1, 0, -1, 0, 0, 0, 0, -1, 0, 1.0, 0, 0, 0, 1]  # optical frame on a 1 m mast


def test_ros2_msgtype_normalises_ros1_style_names_only():
    assert ros2_msgtype("sensor_msgs/Image") == "sensor_msgs/msg/Image"
    for name in ("sensor_msgs/msg/Image", "std_srvs/srv/Empty", "Image", "/Image", "a/b/c/d"):
        assert ros2_msgtype(name) == name


# --- bags as other recorders write them -------------------------------------------------------


def _stereo_bag(path: Path) -> Path:
    """Two stereo pairs (textured 320x240 mono8 images) with CameraInfo (f=200 px, 0.12 m
    baseline), written with rosbags' Writer."""
    ts = typestore()
    T = ts.types
    rng = np.random.default_rng(0)
    w, h, f = 320, 240, 200.0

    def header(ns, frame):
        return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9),
                                        frame_id=frame)

    def info(ns, frame, tx):
        return T["sensor_msgs/msg/CameraInfo"](
            header=header(ns, frame), height=h, width=w, distortion_model="plumb_bob", d=np.zeros(5),
            k=np.array([f, 0, w / 2, 0, f, h / 2, 0, 0, 1.0]), r=np.eye(3).ravel(),
            p=np.array([f, 0, w / 2, tx, 0, f, h / 2, 0, 0, 0, 1, 0.0]), binning_x=0, binning_y=0,
            roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))

    with Writer(path, version=8, storage_plugin=StoragePlugin.MCAP) as wr:
        conns = {t: wr.add_connection(t, "sensor_msgs/msg/CameraInfo" if "info" in r else "sensor_msgs/msg/Image",
                                      typestore=ts) for r, t in CAM.items()}
        for k in range(2):
            ns = 8 * 10**9 + k * 33_000_000
            pixels = rng.integers(0, 256, (h, w), dtype=np.uint8)
            for side, tx in (("left", 0.0), ("right", -0.12 * f)):
                frame = f"cam_{side}_optical"
                img = T["sensor_msgs/msg/Image"](header=header(ns, frame), height=h, width=w, encoding="mono8",
                                                 is_bigendian=0, step=w, data=pixels.ravel())
                wr.write(conns[CAM[f"{side}_image"]], ns, ts.serialize_cdr(img, "sensor_msgs/msg/Image"))
                wr.write(conns[CAM[f"{side}_info"]], ns,
                         ts.serialize_cdr(info(ns, frame, tx), "sensor_msgs/msg/CameraInfo"))
    return path


def _rewrite(src: Path, dst: Path, *, message_zstd: bool = False, ros1_names: bool = False,
             hashes: bool = True, edit=None, storage: StoragePlugin = StoragePlugin.MCAP) -> Path:
    """``src`` written again message by message, as another recorder would: per-message zstd
    compression (rosbag2's ``--compression-mode message``), ROS 1-style type names, the type
    hashes dropped from metadata.yaml (as in bags of rosbag2 before Iron); ``edit(topic, k, raw)``
    may replace the k-th message of a topic."""
    counts: dict[str, int] = {}
    with AnyReader([src]) as reader:
        wr = Writer(dst, version=8, storage_plugin=storage)
        if message_zstd:
            wr.set_compression(CompressionMode.MESSAGE, CompressionFormat.ZSTD)
        with wr:
            conns = {c.id: wr.add_connection(c.topic, c.msgtype.replace("/msg/", "/") if ros1_names else c.msgtype,
                                             msgdef=c.msgdef.data, rihs01=c.digest) for c in reader.connections}
            for c, t, raw in reader.messages():
                k = counts[c.topic] = counts.get(c.topic, 0) + 1
                wr.write(conns[c.id], t, edit(c.topic, k, raw) if edit else raw)
    if not hashes:
        meta = dst / "metadata.yaml"
        doc = yaml.safe_load(meta.read_text())
        for entry in doc["rosbag2_bagfile_information"]["topics_with_message_count"]:
            entry["topic_metadata"].pop("type_description_hash", None)
        meta.write_text(yaml.safe_dump(doc))
    return dst


def _storage(bag: Path) -> Path:
    (file,) = [*bag.glob("*.mcap"), *bag.glob("*.db3")]
    return file


@pytest.fixture(scope="module")
def motion(tmp_path_factory):
    """A motion bag of the kind `fgslam run` reads (fgslam's writer) and its stream."""
    root = tmp_path_factory.mktemp("motion")
    stream = synthetic_stream(SyntheticStreamConfig(duration_s=3.0, rocks_per_frame=5.0), np.random.default_rng(5))
    write_bag(root / "bag", stream)
    (root / "catalog.csv").write_text("x,y,size,score\n0,0,1,1\n5,0,1,1\n0,5,1,1\n5,5,1,1\n")
    return root, read_bag(root / "bag").measurements


@pytest.fixture(scope="module")
def stereo(tmp_path_factory):
    root = tmp_path_factory.mktemp("stereo")
    (root / "images.yaml").write_text(yaml.safe_dump({"images": {"T_base_cam": T_BASE_CAM}}))
    return root, _stereo_bag(root / "plain")


def _same(a: list, b: list) -> bool:
    return len(a) == len(b) and all(same_measurement(x, y) for x, y in zip(a, b))


def _stereo_pairs(bag: Path) -> list:
    sb = StereoBag(bag, _topics(), ImageInputConfig(T_base_cam=tuple(T_BASE_CAM)))
    return list(sb.pairs())


def _topics():
    from fgslam.inputs import bag_topics

    return bag_topics(CAM)


# --- per-message compression ----------------------------------------------------------------


def test_message_compressed_image_bag_read_bare_is_an_error_naming_bag_and_topic(stereo, tmp_path, capsys):
    root, plain = stereo
    bag = _rewrite(plain, tmp_path / "msgzstd", message_zstd=True)
    cfg = ["--config", str(root / "images.yaml")]
    assert main(["detect", str(_storage(bag)), "--out", str(tmp_path / "bare_out"), *CAM_ARGS, *cfg]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert f"bag {_storage(bag)}: topic /cam/left/camera_info: a message cannot be decoded" in err
    assert "zstd-compressed" in err and "per-message compression" in err and "as its directory" in err
    assert not (tmp_path / "bare_out").exists()
    # the directory, with metadata.yaml, says how the messages are compressed: it reads
    assert main(["detect", str(bag), "--out", str(tmp_path / "out"), *CAM_ARGS, *cfg]) == 0
    assert "2 stereo pairs" in capsys.readouterr().err
    for (na, la, ra), (nb, lb, rb) in zip(_stereo_pairs(bag), _stereo_pairs(plain), strict=True):
        assert na == nb and np.array_equal(la, lb) and np.array_equal(ra, rb)


@pytest.mark.parametrize("storage", [StoragePlugin.MCAP, StoragePlugin.SQLITE3])
def test_message_compressed_motion_bag_read_bare_is_an_error_naming_bag_and_topic(motion, tmp_path, capsys,
                                                                                  storage):
    root, held = motion
    bag = _rewrite(root / "bag", tmp_path / "msgzstd", message_zstd=True, storage=storage)
    assert _same(read_bag(bag).measurements, held)  # the directory form reads alike
    bare = _storage(bag)
    with pytest.raises(BagError, match=r"topic /\w+: a message cannot be decoded .*zstd-compressed") as exc:
        BagSource(bare)  # refused when made, before any pass
    assert f"bag {bare}:" in str(exc.value) and "as its directory, with metadata.yaml" in str(exc.value)
    args = ["run", "--bag", str(bare), "--catalog", str(root / "catalog.csv"), "--backend", "ekf",
            "--out", str(tmp_path / "run")]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and f"fgslam: error: bag {bare}: topic /" in err
    assert "per-message compression" in err


@pytest.mark.parametrize("bad", ["zstd frame", "truncated", "bad encapsulation"])
def test_an_undecodable_message_mid_stream_is_a_bag_error(motion, tmp_path, bad):
    """The vectorised decoder takes a block only when every message has the plain CDR layout;
    a bad message sends its block to the per-message decoder, which names it."""
    root, _ = motion
    n_imu = sum(isinstance(m, ImuSample) for m in read_bag(root / "bag").measurements)
    k_bad = n_imu // 2

    def edit(topic, k, raw):
        if topic != "/imu" or k != k_bad:
            return raw
        raw = bytes(raw)
        return {"zstd frame": b"\x28\xb5\x2f\xfd" + raw[4:], "truncated": raw[: len(raw) // 2],
                "bad encapsulation": b"\x00\x42\x00\x00" + raw[4:]}[bad]

    bag = _rewrite(root / "bag", tmp_path / "bad", edit=edit)
    source = BagSource(bag)  # the first messages decode
    with pytest.raises(BagError, match=rf"bag {bag}: topic /imu: message {k_bad} cannot be deserialized"):
        list(source)


# --- ROS 1-style type names ---------------------------------------------------------------------


@pytest.mark.parametrize("form", ["directory", "bare file"])
def test_ros1_style_type_names_read_as_ros2_names(motion, stereo, tmp_path, form):
    root, held = motion
    bag = _rewrite(root / "bag", tmp_path / "ros1", ros1_names=True, hashes=False)
    path = bag if form == "directory" else _storage(bag)
    got = read_bag(path)
    assert _same(got.measurements, held)
    assert got.report.topics["/imu"].msgtype == "sensor_msgs/msg/Imu"  # the vectorised decoders' key
    _, plain = stereo
    image_bag = _rewrite(plain, tmp_path / "ros1_images", ros1_names=True, hashes=False)
    image_path = image_bag if form == "directory" else _storage(image_bag)
    pairs, expected = _stereo_pairs(image_path), _stereo_pairs(plain)
    assert len(pairs) == len(expected) == 2
    for (na, la, ra), (nb, lb, rb) in zip(pairs, expected):
        assert na == nb and np.array_equal(la, lb) and np.array_equal(ra, rb)


def test_ros1_style_names_with_type_hashes_are_named_as_the_problem(motion, stereo, tmp_path, capsys):
    """rosbags cannot match a type hash recorded for a ROS 1-style name (AnyReader.open fails
    with a KeyError): the error says so, and how to read the bag anyway."""
    root, held = motion
    bag = _rewrite(root / "bag", tmp_path / "ros1", ros1_names=True)
    with pytest.raises(BagError, match=r"ROS 1-style name .* type hash") as exc:
        read_bag(bag)
    assert "not a valid or a truncated bag" not in str(exc.value)
    assert str(_storage(bag)) in str(exc.value)
    assert _same(read_bag(_storage(bag)).measurements, held)  # the storage file alone, as the error says
    sroot, plain = stereo
    image_bag = _rewrite(plain, tmp_path / "ros1_images", ros1_names=True)
    assert main(["detect", str(image_bag), "--out", str(tmp_path / "out"), *CAM_ARGS,
                 "--config", str(sroot / "images.yaml")]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert f"fgslam: error: bag {image_bag} cannot be opened: its message type 'sensor_msgs/" in err
    # as the error says: without the hashes in metadata.yaml the directory reads
    meta = image_bag / "metadata.yaml"
    meta.write_text("\n".join(line for line in meta.read_text().splitlines()
                              if "type_description_hash" not in line and "RIHS01_" not in line))
    assert len(_stereo_pairs(image_bag)) == 2


@pytest.mark.parametrize("ros1_names", [False, True])
def test_detect_writes_its_bag_from_connections_without_type_hashes(stereo, tmp_path, capsys, ros1_names):
    """A bare storage file (its connections carry no definitions' hashes) and ROS 1-style names
    without hashes: `fgslam detect` writes the bag with rocks (the types under their ROS 2 names),
    readable by rosbags with every message of the input."""
    from rosbags.highlevel import AnyReader

    from reloc.bag_spec import typestore

    root, plain = stereo
    bag = _rewrite(plain, tmp_path / "in", ros1_names=ros1_names, hashes=False) if ros1_names else plain
    out = tmp_path / "out"
    assert main(["detect", str(_storage(bag)), "--out", str(out), *CAM_ARGS,
                 "--config", str(root / "images.yaml")]) == 0, capsys.readouterr().err
    with AnyReader([_storage(plain)], default_typestore=typestore()) as src, \
            AnyReader([out], default_typestore=typestore()) as got:
        assert {t: i.msgcount for t, i in src.topics.items()}.items() <= \
            {t: i.msgcount for t, i in got.topics.items()}.items()
        assert got.topics["/rocks"].msgcount == 2
        assert {i.msgtype for i in got.topics.values()} <= set(typestore().fielddefs)
