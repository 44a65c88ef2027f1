"""What a run or a comparison consumes: a measurement stream, the orbital catalogs (one per
landmark kind), the start pose, optional ground truth and an optional orbital image, from a
``fgslam sim`` directory, from any bag plus catalog files, or straight from the simulator."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from fgslam.errors import InputFileError
from reloc.backend import PoseEstimate, Trajectory, known_start_cov
from reloc.errors import RelocError
from reloc.kinds import UnknownKindError, kind_named, kinds_with
from reloc.measurements import GroundTruthPose

log = logging.getLogger(__name__)


@dataclass
class RunInputs:
    """One traverse: ``measurements`` (time-ordered), ``catalogs`` (landmark kind name -> its
    orbital catalog, e.g. ``{"rocks": RockCatalog}``), ``initial`` pose, optional
    ``orbital_image`` (H, W, 3) uint8 with ``orbital_extent`` (xmin, xmax, ymin, ymax) metres in world
    (row 0 at ymax), optional ``rocks_true_xy`` (M, 2), and ``source`` (what it was read from)."""

    name: str
    measurements: list
    catalogs: dict
    initial: PoseEstimate
    orbital_image: np.ndarray | None = None
    orbital_extent: tuple[float, float, float, float] | None = None
    rocks_true_xy: np.ndarray | None = None
    source: dict = field(default_factory=dict)

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


def load_sim_dir(path: Path, start_xyyaw: tuple[float, float, float] | None = None) -> RunInputs:
    """Read a ``fgslam sim`` output directory: bag/, catalog.csv, world.yaml, orbital.png,
    rocks_true.csv, and the catalog file of every other landmark kind present (its catalog layer)."""
    import yaml

    path = Path(path)
    if not path.is_dir():
        raise InputFileError(f"{path}: not a directory (expected the output of `fgslam sim`)")
    for needed in ("bag", "catalog.csv"):
        if not (path / needed).exists():
            raise InputFileError(f"{path}: missing {needed} (expected the output of `fgslam sim`)")
    others = {k.name: path / k.layer("catalog").file_name for k in kinds_with("catalog") if k.name != "rocks"}
    others = {name: p for name, p in others.items() if p.exists()}
    inputs = load_bag(path / "bag", path / "catalog.csv", start_xyyaw=start_xyyaw, name=path.name,
                      kind_catalogs=others)
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
    kind_catalogs: dict[str, Path] | None = None,
) -> RunInputs:
    """Read any ROS 2 bag with the fgslam topics plus an orbital rock catalog CSV (x,y,size,score)
    and, in ``kind_catalogs``, the catalog files of other landmark kinds (kind name -> path)."""
    from fgslam.io.bag_reader import read_bag
    from fgslam.io.catalog_csv import read_catalog_csv

    bag, catalog_csv = Path(bag), Path(catalog_csv)
    if not bag.exists():
        raise InputFileError(f"{bag}: bag not found")
    if not catalog_csv.exists():
        raise InputFileError(f"{catalog_csv}: catalog not found")
    stream = read_bag(bag)
    measurements = list(stream.measurements)
    if not measurements:
        raise InputFileError(f"{bag}: the bag holds no measurements")
    catalog = read_catalog_csv(catalog_csv)
    if len(catalog) < 3:
        raise InputFileError(f"{catalog_csv}: the catalog holds {len(catalog)} rocks; at least 3 are needed")
    catalogs = {"rocks": catalog}
    for kind_name, path in (kind_catalogs or {}).items():
        try:
            layer = kind_named(kind_name).layer("catalog")
        except RelocError as exc:  # an unregistered kind, or one without a catalog layer
            raise InputFileError(f"{path}: cannot read a catalog of kind {kind_name!r}: {exc}") from None
        if not Path(path).exists():
            raise InputFileError(f"{path}: {kind_name} catalog not found")
        catalogs[kind_name] = layer.read(Path(path))
    if start_xyyaw is not None:
        initial = start_pose_from_xyyaw(measurements[0].t, *start_xyyaw)
    else:
        initial = _initial_from_stream(measurements, str(bag))
    return RunInputs(
        name=name or bag.stem, measurements=measurements, catalogs=catalogs, initial=initial,
        source={"kind": "bag", "bag": str(bag), "catalog": str(catalog_csv),
                **({"kind_catalogs": {k: str(p) for k, p in kind_catalogs.items()}} if kind_catalogs else {}),
                "report": str(getattr(stream, "report", ""))},
    )


def truth_of(inputs: RunInputs) -> Trajectory | None:
    """Ground-truth trajectory of the inputs (None without /ground_truth)."""
    from fgslam.runner import ground_truth_trajectory

    return ground_truth_trajectory([m for m in inputs.measurements if isinstance(m, GroundTruthPose)])
