"""What a run or a comparison consumes: a measurement stream, the orbital catalog, the start pose,
optional ground truth and an optional orbital image, from a ``fgslam sim`` directory, from any bag
plus a catalog CSV, or straight from the simulator."""

from __future__ import annotations

import logging
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from fgslam.errors import InputFileError
from reloc.backend import PoseEstimate, Trajectory, known_start_cov
from reloc.measurements import GroundTruthPose, RockCatalog

log = logging.getLogger(__name__)


# A bag with more messages than this is streamed from disk at every pass instead of read into
# memory once (~400 bytes a measurement in memory; a yard's bags hold 130-200 k messages, a
# kilometre traverse millions).
STREAM_ABOVE_MESSAGES = 500_000


@dataclass
class RunInputs:
    """One traverse: ``measurements`` (time-ordered; a list, or a re-iterable stream such as
    :class:`fgslam.io.bag_reader.BagSource` read anew at every pass), ``catalog``, ``initial`` pose,
    optional ``orbital_image`` (H, W, 3) uint8 with ``orbital_extent`` (xmin, xmax, ymin, ymax)
    metres in world (row 0 at ymax), optional ``rocks_true_xy`` (M, 2), and ``source`` (what it
    was read from)."""

    name: str
    measurements: Iterable
    catalog: RockCatalog
    initial: PoseEstimate
    orbital_image: np.ndarray | None = None
    orbital_extent: tuple[float, float, float, float] | None = None
    rocks_true_xy: np.ndarray | None = None
    source: dict = field(default_factory=dict)


def start_pose_from_truth(gt: GroundTruthPose) -> PoseEstimate:
    """Known start pose from the first ground-truth message, with a small covariance."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(gt.quat_xyzw).as_matrix()
    T[:3, 3] = gt.position_m
    return PoseEstimate(gt.t, T, known_start_cov())


def start_pose_from_xyyaw(t: float, x: float, y: float, yaw: float, z: float = 0.0) -> PoseEstimate:
    """Known planar start pose (m, m, rad) at ``t``."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", yaw).as_matrix()
    T[:3, 3] = [x, y, z]
    return PoseEstimate(float(t), T, known_start_cov())


def _initial_from_stream(measurements: list, where: str) -> PoseEstimate:
    for m in measurements:
        if isinstance(m, GroundTruthPose):
            return start_pose_from_truth(m)
    raise InputFileError(f"{where}: no /ground_truth message to take the start pose from; give --start X,Y,YAW")


def from_sim_run(run, name: str | None = None, orbital_gsd_m: float = 0.1) -> RunInputs:
    """Inputs straight from a :class:`sim` run (``sim.simulate(cfg)``), with its orbital image."""
    from sim.orbital_image import orbital_image

    image, extent = orbital_image(run.world, orbital_gsd_m)
    rocks = getattr(run, "rocks_true", None)
    rocks_xy = None
    if rocks is not None:
        rocks_xy = np.asarray(getattr(rocks, "xy_m", getattr(rocks, "xyz_m", rocks)))[:, :2]
    return RunInputs(
        name=name or str(getattr(run.config, "world", "sim")),
        measurements=list(run.measurements),
        catalog=run.catalog,
        initial=run.initial_pose,
        orbital_image=np.asarray(image),
        orbital_extent=tuple(float(v) for v in extent),
        rocks_true_xy=rocks_xy,
        source={"kind": "simulator", "world": str(getattr(run.config, "world", "?")),
                "seed": int(getattr(run.config, "seed", 0))},
    )


def _read_png(path: Path) -> np.ndarray:
    import matplotlib.image as mpimg

    img = mpimg.imread(str(path))
    if img.dtype != np.uint8:
        img = (np.clip(img, 0, 1) * 255).astype(np.uint8)
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    return img[:, :, :3]


def _world_extent(world_yaml: dict) -> tuple[float, float, float, float] | None:
    """Extent of the orbital image from world.yaml (several spellings accepted)."""
    for key in ("orbital_extent", "extent", "extent_m"):
        ext = world_yaml.get(key)
        if ext is not None and len(ext) == 4:
            return tuple(float(v) for v in ext)
    world = world_yaml.get("world")
    if isinstance(world, dict):
        return _world_extent(world)
    return None


def load_sim_dir(path: Path, start_xyyaw: tuple[float, float, float] | None = None) -> RunInputs:
    """Read a ``fgslam sim`` output directory: bag/, catalog.csv, world.yaml, orbital.png, rocks_true.csv."""
    import yaml

    path = Path(path)
    if not path.is_dir():
        raise InputFileError(f"{path}: not a directory (expected the output of `fgslam sim`)")
    for needed in ("bag", "catalog.csv"):
        if not (path / needed).exists():
            raise InputFileError(f"{path}: missing {needed} (expected the output of `fgslam sim`)")
    inputs = load_bag(path / "bag", path / "catalog.csv", start_xyyaw=start_xyyaw, name=path.name)
    world_yaml: dict = {}
    if (path / "world.yaml").exists():
        try:
            world_yaml = yaml.safe_load((path / "world.yaml").read_text()) or {}
        except yaml.YAMLError as exc:
            raise InputFileError(f"{path / 'world.yaml'}: not valid YAML: {exc}") from exc
    extent = _world_extent(world_yaml) if isinstance(world_yaml, dict) else None
    if (path / "orbital.png").exists() and extent is not None:
        inputs.orbital_image = _read_png(path / "orbital.png")
        inputs.orbital_extent = extent
    if (path / "rocks_true.csv").exists():
        try:
            arr = np.genfromtxt(path / "rocks_true.csv", delimiter=",", names=True)
            inputs.rocks_true_xy = np.stack([arr["x"], arr["y"]], axis=1).reshape(-1, 2)
        except (ValueError, KeyError) as exc:
            log.warning("%s: unreadable (%s); true rocks not shown", path / "rocks_true.csv", exc)
    if isinstance(world_yaml, dict):
        inputs.source.update({k: world_yaml[k] for k in ("world", "seed") if k in world_yaml and not isinstance(world_yaml[k], dict)})
    inputs.source["dir"] = str(path)
    return inputs


def load_bag(
    bag: Path, catalog_csv: Path, start_xyyaw: tuple[float, float, float] | None = None, name: str | None = None,
    stream: bool | None = None,
) -> RunInputs:
    """Read any ROS 2 bag with the fgslam topics plus an orbital catalog CSV (x,y,size,score).
    ``stream``: iterate the bag from disk at every pass (True), read it into memory once (False),
    or decide by its size (None: stream above :data:`STREAM_ABOVE_MESSAGES` messages)."""
    from fgslam.io.bag_reader import BagSource
    from fgslam.io.catalog_csv import read_catalog_csv

    bag, catalog_csv = Path(bag), Path(catalog_csv)
    if not bag.exists():
        raise InputFileError(f"{bag}: bag not found")
    if not catalog_csv.exists():
        raise InputFileError(f"{catalog_csv}: catalog not found")
    source = BagSource(bag)
    if stream is None:
        stream = sum(source.message_counts.values()) > STREAM_ABOVE_MESSAGES
    measurements = source if stream else list(source)
    if not stream and not measurements:
        raise InputFileError(f"{bag}: the bag holds no measurements")
    catalog = read_catalog_csv(catalog_csv)
    if len(catalog) < 3:
        raise InputFileError(f"{catalog_csv}: the catalog holds {len(catalog)} rocks; at least 3 are needed")
    if start_xyyaw is not None:
        t0 = source.first_stamp_s() if stream else measurements[0].t
        initial = start_pose_from_xyyaw(t0, *start_xyyaw)
    else:
        initial = _initial_from_stream(source.ground_truth() if stream else measurements, str(bag))
    return RunInputs(
        name=name or bag.stem, measurements=measurements, catalog=catalog, initial=initial,
        source={"kind": "bag", "bag": str(bag), "catalog": str(catalog_csv), "streamed": bool(stream),
                "report": str(source.report or "")},
    )


def truth_of(inputs: RunInputs) -> Trajectory | None:
    """Ground-truth trajectory of the inputs (None without /ground_truth)."""
    from fgslam.runner import ground_truth_trajectory

    ground_truth = getattr(inputs.measurements, "ground_truth", None)  # a stream reads just that topic
    poses = ground_truth() if ground_truth is not None else [m for m in inputs.measurements if isinstance(m, GroundTruthPose)]
    return ground_truth_trajectory(poses)


def stream_span_s(inputs: RunInputs) -> tuple[float, float]:
    """(first, last) measurement stamp (s) of the inputs (a stream: its bag's recorded span)."""
    span = getattr(inputs.measurements, "span_s", None)
    if span is not None:
        return span()
    return inputs.measurements[0].t, inputs.measurements[-1].t


def stream_size(inputs: RunInputs) -> str:
    """How much the inputs hold, for the console: "N measurements" (a stream: "N messages, streamed")."""
    counts = getattr(inputs.measurements, "message_counts", None)
    if counts is not None:
        return f"{sum(counts.values())} messages, streamed"
    return f"{len(inputs.measurements)} measurements"
