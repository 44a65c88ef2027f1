"""What a run or a comparison consumes: a measurement stream, the orbital catalogs (one per
landmark kind), the start pose, optional ground truth and an optional orbital image, from a
``fgslam sim`` directory, from any bag plus catalog files, or straight from the simulator."""

from __future__ import annotations

import logging
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from fgslam.errors import InputFileError
from reloc.backend import PoseEstimate, Trajectory, known_start_cov
from reloc.dem import Dem
from reloc.errors import RelocError
from reloc.kinds import UnknownKindError, kind_named, kinds_with
from reloc.measurements import CmdVel, GroundTruthPose, ImuSample, WheelOdometry

log = logging.getLogger(__name__)


# A bag with more messages than this is streamed from disk at every pass instead of read into
# memory once (~400 bytes a measurement in memory; a yard's bags hold 130-200 k messages, a
# kilometre traverse millions).
STREAM_ABOVE_MESSAGES = 500_000


@dataclass
class RunInputs:
    """One traverse: ``measurements`` (time-ordered; a list, or a re-iterable stream such as
    :class:`fgslam.io.bag_reader.BagSource` read anew at every pass), ``catalogs`` (landmark kind
    name -> its orbital catalog, e.g. ``{"rocks": RockCatalog}``), ``initial`` pose, optional
    ``orbital_image`` (H, W, 3) uint8 with ``orbital_extent`` (xmin, xmax, ymin, ymax) metres in world
    (row 0 at ymax), optional ``rocks_true_xy`` (M, 2), ``source`` (what it was read from), and an
    optional orbital terrain model ``dem``."""

    name: str
    measurements: Iterable
    catalogs: dict
    initial: PoseEstimate
    orbital_image: np.ndarray | None = None
    orbital_extent: tuple[float, float, float, float] | None = None
    rocks_true_xy: np.ndarray | None = None
    source: dict = field(default_factory=dict)
    dem: Dem | None = None  # an orbital terrain model: fixes get heights from it (fgslam.terrain_height)

    def __post_init__(self) -> None:
        try:
            for name in self.catalogs:
                kind_named(name)
        except UnknownKindError as exc:
            raise InputFileError(f"{self.name}: a catalog of an unknown landmark kind: {exc}") from None

    @property
    def catalog(self):
        """The rock catalog (``catalogs["rocks"]``; None without one)."""
        return self.catalogs.get("rocks")


def start_pose_from_truth(gt: GroundTruthPose) -> PoseEstimate:
    """Known start pose from the first ground-truth message, with a small covariance."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(gt.quat_xyzw).as_matrix()
    T[:3, 3] = gt.position_m
    return PoseEstimate(gt.t, T, known_start_cov())


START_STREAM = 0x57A27  # the start draw's random stream beside the simulator's (same seed)


def start_drawn_from_prior(start: PoseEstimate, seed: int) -> PoseEstimate:
    """``start`` (the true pose) moved by one draw from its own covariance, in the convention of
    :mod:`reloc.backend` (``R_true = Exp(dtheta) R_est``, ``p_true = p_est + dp``), seeded with the
    simulator's ``seed`` on a stream of its own: the start of a Monte Carlo consistency test. A run
    started at the exact truth while claiming ``start.cov`` carries in its covariance an error it
    never has (unobservable without fixes, so it never leaves), and its NEES reads pessimistic for
    that alone."""
    from reloc.geometry import exp_so3

    d = np.random.default_rng([int(seed), START_STREAM]).multivariate_normal(np.zeros(6), start.cov)
    T = start.T_world_base.copy()
    T[:3, :3] = exp_so3(-d[3:]) @ T[:3, :3]
    T[:3, 3] = T[:3, 3] - d[:3]
    return PoseEstimate(start.t, T, start.cov)


@dataclass(frozen=True)
class StartSpec:
    """A start pose given by the user (``--start``): x, y, yaw and optionally z (m, rad), and/or
    its 1-sigma (``--start-sigma``): xy, yaw and optionally z (m, rad). None: not given."""

    xyyaw: tuple[float, float, float] | None = None
    z_m: float | None = None
    sigma_xy_m: float | None = None
    sigma_yaw_rad: float | None = None
    sigma_z_m: float | None = None

    def cov(self) -> np.ndarray:
        """(6, 6) start covariance over ``[dp_world, dtheta_world]`` (see reloc.backend)."""
        cov = known_start_cov()
        if self.sigma_xy_m is not None:
            z = self.sigma_xy_m if self.sigma_z_m is None else self.sigma_z_m
            cov[0, 0] = cov[1, 1] = self.sigma_xy_m**2
            cov[2, 2] = z**2
        if self.sigma_yaw_rad is not None:
            cov[5, 5] = self.sigma_yaw_rad**2
        return cov


def start_pose_from_xyyaw(t: float, x: float, y: float, yaw: float, z: float = 0.0,
                          roll_pitch_rad: tuple[float, float] = (0.0, 0.0), cov: np.ndarray | None = None) -> PoseEstimate:
    """Known start pose at ``t``: position (m), yaw (rad) and roll/pitch (rad, e.g. the IMU's)."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("ZYX", [yaw, roll_pitch_rad[1], roll_pitch_rad[0]]).as_matrix()
    T[:3, 3] = [x, y, z]
    return PoseEstimate(float(t), T, known_start_cov() if cov is None else cov)


def _first_of(measurements, cls: type):
    """The stream's first measurement of type ``cls`` (a bag stream reads only its topic), or None."""
    first_of = getattr(measurements, "first_of", None)
    if first_of is not None:
        return first_of(cls)
    return next((m for m in measurements if isinstance(m, cls)), None)


def _given_start(measurements: list, start: StartSpec, where: str) -> PoseEstimate:
    """The user's start pose: x, y, (z,) yaw as given, roll and pitch from the first IMU sample's
    gravity-referenced attitude (its yaw is arbitrary), at the first measurement's time."""
    imu = _first_of(measurements, ImuSample)
    roll_pitch = (0.0, 0.0)
    if imu is not None:
        _, pitch, roll = Rotation.from_quat(imu.quat_xyzw).as_euler("ZYX")
        roll_pitch = (float(roll), float(pitch))
    x, y, yaw = start.xyyaw
    z = 0.0 if start.z_m is None else start.z_m
    if start.z_m is None:
        gt = _first_of(measurements, GroundTruthPose)
        if gt is not None and abs(gt.position_m[2]) > 0.1:
            log.warning("%s: --start gives no z, so the start is at z = 0 m while the first ground truth is at "
                        "z = %.2f m: every error against it includes that offset; give --start X,Y,Z,YAW",
                        where, gt.position_m[2])
    return start_pose_from_xyyaw(next(iter(measurements)).t, x, y, yaw, z, roll_pitch, start.cov())


def _initial_from_stream(measurements: list, where: str, start: StartSpec) -> PoseEstimate:
    if start.xyyaw is not None:
        return _given_start(measurements, start, where)
    gt = _first_of(measurements, GroundTruthPose)
    if gt is not None:
        pose = start_pose_from_truth(gt)
        return PoseEstimate(pose.t, pose.T_world_base, start.cov())
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
        catalogs={"rocks": run.catalog},
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


def load_sim_dir(path: Path, start: StartSpec | None = None, topics=None, images=None,
                 image_progress=None, preread: BagRead | None = None) -> RunInputs:
    """Read a ``fgslam sim`` output directory: bag/, catalog.csv, world.yaml, orbital.png,
    rocks_true.csv, dem.tif, and the catalog file of every other landmark kind present (its catalog
    layer); refused when its manifest says it was not completely written. ``topics``, ``preread``:
    as :func:`load_bag`."""
    import yaml

    from fgslam.io.outdir import require_complete

    path = Path(path)
    if not path.is_dir():
        raise InputFileError(f"{path}: not a directory (expected the output of `fgslam sim`)")
    require_complete(path, "sim")
    for needed in ("bag", "catalog.csv"):
        if not (path / needed).exists():
            raise InputFileError(f"{path}: missing {needed} (expected the output of `fgslam sim`)")
    others = {k.name: path / k.layer("catalog").file_name for k in kinds_with("catalog") if k.name != "rocks"}
    others = {name: p for name, p in others.items() if p.exists()}
    inputs = load_bag(path / "bag", path / "catalog.csv", start=start, name=path.name, kind_catalogs=others,
                      topics=topics, images=images, image_progress=image_progress, preread=preread)
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
    if (path / DEM_FILE).exists():
        from fgslam.io.dem_tif import read_dem

        with_dem(inputs, read_dem(path / DEM_FILE), path / DEM_FILE)
    return inputs


DEM_FILE = "dem.tif"  # a simulation's orbital terrain model


def with_dem(inputs: RunInputs, dem: Dem, path: Path) -> RunInputs:
    """``inputs`` (changed in place) with the terrain model ``dem`` read from ``path``."""
    inputs.dem = dem
    inputs.source["dem"] = str(path)
    return inputs


def bag_topics(mapping: dict[str, str] | None = None):
    """:class:`reloc.bag_spec.TopicNames` of a role -> topic map (``--topic ROLE=NAME``, a
    ``topics:`` block) over the defaults; roles are TopicNames' fields and the landmark kinds with
    a bag layer. A bad map raises :class:`reloc.errors.ConfigError` listing the roles."""
    from reloc.bag_spec import topic_names

    return topic_names(mapping, tuple(k.name for k in kinds_with("bag")))


def _has_topic(bag: Path, topic: str) -> bool:
    from fgslam.io.bag_reader import _open, _resolve

    reader = _open(_resolve(Path(bag)), Path(bag))
    try:
        return topic in reader.topics and reader.topics[topic].msgcount > 0
    finally:
        reader.close()


@dataclass
class BagRead:
    """A bag's measurement source and what a run iterates: the source itself (streamed from disk
    at every pass) or its measurements read into a list (:func:`read_bag_measurements`)."""

    bag: Path
    source: object
    measurements: object
    stream: bool


def read_bag_measurements(bag: Path, topics=None, stream: bool | None = None) -> BagRead:
    """Open ``bag`` (fgslam's topics, or ``topics``) and, unless it is to be streamed (``stream``;
    None: above :data:`STREAM_ABOVE_MESSAGES` messages), read its measurements into memory."""
    from fgslam.io.bag_reader import BagSource

    return _collected(Path(bag), BagSource(bag, topics or bag_topics()), stream)


def _collected(bag: Path, source, stream: bool | None) -> BagRead:
    if stream is None:
        stream = sum(source.message_counts.values()) > STREAM_ABOVE_MESSAGES
    measurements = source if stream else list(source)
    if not stream and not measurements:
        raise InputFileError(f"{bag}: the bag holds no measurements")
    return BagRead(bag, source, measurements, bool(stream))


def load_bag(bag: Path, catalog_csv: Path, start: StartSpec | None = None, name: str | None = None,
             kind_catalogs: dict[str, Path] | None = None, stream: bool | None = None,
             topics=None, images=None, image_progress=None, preread: BagRead | None = None) -> RunInputs:
    """Read any ROS 2 bag with the fgslam topics plus an orbital rock catalog CSV (x,y,size,score)
    and, in ``kind_catalogs``, the catalog files of other landmark kinds (kind name -> path); the
    start pose is the first ground truth unless ``start`` gives one. ``stream``: iterate the bag
    from disk at every pass (True), read it into memory once (False), or decide by its size (None:
    stream above :data:`STREAM_ABOVE_MESSAGES` messages). ``topics``: the bag's
    :class:`reloc.bag_spec.TopicNames` (default: fgslam's own names). A bag without the rock
    topic but with stereo images has its rocks detected on the fly
    (:class:`fgslam.io.image_rocks.ImageRockSource`, settings ``images``, an
    :class:`~fgslam.io.image_rocks.ImageInputConfig`; ``image_progress(done, total)`` per pair).
    ``preread``: this bag already read by :func:`read_bag_measurements` (e.g. while something
    else was being written)."""
    from fgslam.io.catalog_csv import MIN_CATALOG_ROCKS, read_catalog_csv

    bag, catalog_csv = Path(bag), Path(catalog_csv)
    if not bag.exists():
        raise InputFileError(f"{bag}: bag not found")
    if not catalog_csv.exists():
        raise InputFileError(f"{catalog_csv}: catalog not found")
    from fgslam.io.image_rocks import ImageRockSource, has_images

    topics = topics or bag_topics()
    on_the_fly = False
    if preread is not None:
        if preread.bag != bag:
            raise InputFileError(f"{bag}: the measurements given were read from another bag, {preread.bag}")
        read = preread
    elif on_the_fly := (not _has_topic(bag, topics.rocks) and has_images(bag, topics)):
        log.info("%s: no %s topic; rocks are detected in its stereo images", bag, topics.rocks)
        source = ImageRockSource(bag, topics, images)
        source.detect(image_progress)
        read = _collected(bag, source, stream)
    else:
        read = read_bag_measurements(bag, topics, stream)
    source, measurements, stream = read.source, read.measurements, read.stream
    catalog = read_catalog_csv(catalog_csv)
    if len(catalog) < MIN_CATALOG_ROCKS:
        raise InputFileError(f"{catalog_csv}: the catalog holds {len(catalog)} rocks; at least {MIN_CATALOG_ROCKS} are needed")
    catalogs = {"rocks": catalog}
    for kind_name, path in (kind_catalogs or {}).items():
        try:
            layer = kind_named(kind_name).layer("catalog")
        except RelocError as exc:  # an unregistered kind, or one without a catalog layer
            raise InputFileError(f"{path}: cannot read a catalog of kind {kind_name!r}: {exc}") from None
        if not Path(path).exists():
            raise InputFileError(f"{path}: {kind_name} catalog not found")
        catalogs[kind_name] = layer.read(Path(path))
    initial = _initial_from_stream(measurements, str(bag), start or StartSpec())
    return RunInputs(
        name=name or bag.stem, measurements=measurements, catalogs=catalogs, initial=initial,
        source={"kind": "bag", "bag": str(bag), "catalog": str(catalog_csv), "streamed": bool(stream),
                **({"kind_catalogs": {k: str(p) for k, p in kind_catalogs.items()}} if kind_catalogs else {}),
                "report": str(source.report or ""), "rocks_from_images": on_the_fly,
                "topics": {"cmd_vel": topics.cmd_vel, "wheel_odom": topics.wheel_odom, "imu": topics.imu}},
    )


def truth_of(inputs: RunInputs) -> Trajectory | None:
    """Ground-truth trajectory of the inputs (None without /ground_truth)."""
    from fgslam.runner import ground_truth_trajectory

    ground_truth = getattr(inputs.measurements, "ground_truth", None)  # a stream reads just that topic
    poses = ground_truth() if ground_truth is not None else (m for m in inputs.measurements if isinstance(m, GroundTruthPose))
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


class _Stamps:
    """One motion input's stamps in one pass, in constant memory (a 24-hour bag holds millions):
    count, first and last, the largest gap and where it starts, and the time by which gaps exceed
    ``max_age_s``."""

    def __init__(self, max_age_s: float) -> None:
        self.max_age_s = max_age_s
        self.n, self.first, self.last = 0, float("nan"), float("nan")
        self.gap, self.gap_at, self.beyond_age_s = 0.0, float("nan"), 0.0

    def push(self, t: float) -> None:
        if self.n:
            d = t - self.last
            if d > self.gap:
                self.gap, self.gap_at = d, self.last
            if d > self.max_age_s:
                self.beyond_age_s += d - self.max_age_s
        else:
            self.first = t
        self.last = t
        self.n += 1

    def silent_s(self, t0: float, t1: float) -> float:
        """Time in [t0, t1] (s) with no stamp younger than ``max_age_s`` (before the first stamp,
        in the gaps, after the last)."""
        return self.beyond_age_s + max(self.first - t0, 0.0) + max(t1 - self.last - self.max_age_s, 0.0)


def _motion_stamps(measurements, max_age_s: float) -> dict[type, _Stamps]:
    """The stamps of the commands, wheel odometry and IMU samples, in one pass (a bag stream reads
    only those topics)."""
    only = getattr(measurements, "motion_only", None)
    out = {CmdVel: _Stamps(max_age_s), WheelOdometry: _Stamps(max_age_s), ImuSample: _Stamps(max_age_s)}
    for m in (only() if only is not None else measurements):
        kind = out.get(type(m))
        if kind is not None:
            kind.push(m.t)
    return out


def check_stream(inputs: RunInputs, runner):
    """The :class:`fgslam.runner.RunnerConfig` to run ``inputs`` with, checked before the run starts:
    the configured speed source must be in the stream (a bag without /cmd_vel but with
    /wheel_odom uses the wheels, with a warning, instead of standing still), and no IMU gap may
    exceed ``runner.max_imu_gap_s`` (an error naming the gap and the key, not one mid-run)."""
    import dataclasses

    where = inputs.source.get("bag") or inputs.name
    stamps = _motion_stamps(inputs.measurements, runner.max_speed_age_s)
    n = {"cmd": stamps[CmdVel].n, "wheel": stamps[WheelOdometry].n}
    names = inputs.source.get("topics") or {}
    topic = {"cmd": names.get("cmd_vel", "/cmd_vel"), "wheel": names.get("wheel_odom", "/wheel_odom")}
    want = runner.speed_source
    other = "wheel" if want == "cmd" else "cmd"
    if n[want] == 0:
        if n[other] == 0:
            raise InputFileError(f"{where}: no usable speed input: neither {topic['cmd']} nor {topic['wheel']} "
                                 "holds a valid message")
        log.warning("%s: no usable %s message: speeds come from %s (runner.speed_source: %s)",
                    where, topic[want], topic[other], other)
        runner = dataclasses.replace(runner, speed_source=other)
        inputs.source["speed_source"] = other  # recorded with the results
    imu = stamps[ImuSample]
    speed = stamps[CmdVel if runner.speed_source == "cmd" else WheelOdometry]
    if imu.n >= 2 and speed.n:  # where the speed input is older than it may be, nothing moves
        silent = speed.silent_s(imu.first, imu.last)
        if silent > 0.05 * (imu.last - imu.first):
            log.warning("%s: %s is silent for %.1f s of the %.1f s stream (gaps over runner.max_speed_age_s = %g s): "
                        "the rover is taken as stopped there; raise it if this recorder publishes speeds only "
                        "when they change", where, topic[runner.speed_source], silent, imu.last - imu.first,
                        runner.max_speed_age_s)
    if imu.n >= 2 and imu.gap > runner.max_imu_gap_s:
        raise InputFileError(
            f"{where}: the IMU stream has a gap of {imu.gap:.3f} s at t = {imu.gap_at:.3f} s, more than "
            f"runner.max_imu_gap_s = {runner.max_imu_gap_s:g} s; to bridge it, raise runner.max_imu_gap_s "
            f"in the --config file (the rover is taken as stopped where its speed input is older than "
            f"runner.max_speed_age_s = {runner.max_speed_age_s:g} s)")
    return runner
