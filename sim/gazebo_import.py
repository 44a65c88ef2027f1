"""Import a Gazebo model (``model.sdf``) as a :class:`~sim.world.World`.

The heightmap (GeoTIFF with heights in metres, or an 8/16-bit PNG scaled to ``<size>`` z) covers
``<size>`` x/y centred on ``<pos>``; image row 0 is the +y edge and column 0 the -x edge. Rock
meshes are the Wavefront OBJ files of ``<mesh>`` visuals whose file name contains ``rock``; each
connected component of such a mesh is one rock. Poses of the model, the link and the visual
(``x y z roll pitch yaw``) are applied to the mesh vertices.
"""

from __future__ import annotations

import logging
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial.transform import Rotation

from sim.errors import WorldImportError
from sim.rocks import Rocks
from sim.terrain import Heightmap

log = logging.getLogger(__name__)


def _floats(elem: ET.Element | None, n: int, what: str, default: list[float] | None = None) -> np.ndarray:
    if elem is None or not (elem.text or "").strip():
        if default is None:
            raise WorldImportError(f"missing <{what}>")
        return np.array(default, dtype=float)
    try:
        vals = [float(x) for x in elem.text.split()]
    except ValueError as exc:
        raise WorldImportError(f"<{what}> is not numeric: {elem.text!r}") from exc
    if len(vals) != n:
        raise WorldImportError(f"<{what}> needs {n} numbers, got {len(vals)}: {elem.text!r}")
    return np.array(vals)


def pose_matrix(pose6: np.ndarray) -> np.ndarray:
    """SDF pose ``x y z roll pitch yaw`` (m, rad, extrinsic XYZ) -> T (4, 4)."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", pose6[3:]).as_matrix()
    T[:3, 3] = pose6[:3]
    return T


def _resolve_uri(uri: str, model_dir: Path) -> Path:
    uri = uri.strip()
    if uri.startswith("model://"):
        parts = uri[len("model://"):].split("/", 1)
        return model_dir / (parts[1] if len(parts) > 1 else "")
    if uri.startswith("file://"):
        return Path(uri[len("file://"):])
    return model_dir / uri


def load_heightmap(path: Path, size_m: np.ndarray, pos_m: np.ndarray) -> Heightmap:
    """Heightmap image -> :class:`Heightmap` in the world frame (see the module doc for conventions)."""
    if not path.is_file():
        raise WorldImportError(f"heightmap file not found: {path}")
    suffix = path.suffix.lower()
    try:
        if suffix in (".tif", ".tiff"):
            import tifffile

            img = np.asarray(tifffile.imread(path))
        else:
            import cv2

            img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if img is None:
                raise WorldImportError(f"heightmap {path} could not be decoded as an image")
    except WorldImportError:
        raise
    except Exception as exc:
        raise WorldImportError(f"heightmap {path} could not be read: {exc}") from exc
    if img.ndim == 3:
        img = img[..., 0]
    if img.ndim != 2 or min(img.shape) < 2:
        raise WorldImportError(f"heightmap {path} must be a 2D image, got shape {img.shape}")
    if np.issubdtype(img.dtype, np.integer):
        z = img.astype(float) / float(np.iinfo(img.dtype).max) * size_m[2]
    else:
        z = img.astype(float)
    if not np.all(np.isfinite(z)):
        raise WorldImportError(f"heightmap {path} contains NaN or inf")
    z = z[::-1, :] + pos_m[2]  # image row 0 is the +y edge; Heightmap row 0 is ymin
    hx, hy = size_m[0] / 2, size_m[1] / 2
    return Heightmap(z, (pos_m[0] - hx, pos_m[0] + hx, pos_m[1] - hy, pos_m[1] + hy))


def read_obj(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) and triangles (T, 3) of a Wavefront OBJ (polygons fan-triangulated)."""
    if not path.is_file():
        raise WorldImportError(f"mesh file not found: {path}")
    verts, tris = [], []
    with open(path, encoding="utf-8", errors="replace") as fh:
        for lineno, line in enumerate(fh, 1):
            if line.startswith("v "):
                try:
                    verts.append([float(x) for x in line.split()[1:4]])
                except ValueError as exc:
                    raise WorldImportError(f"{path}:{lineno}: bad vertex {line.strip()!r}") from exc
            elif line.startswith("f "):
                try:
                    idx = [int(tok.split("/")[0]) for tok in line.split()[1:]]
                except ValueError as exc:
                    raise WorldImportError(f"{path}:{lineno}: bad face {line.strip()!r}") from exc
                idx = [i - 1 if i > 0 else len(verts) + i for i in idx]
                tris += [[idx[0], idx[k], idx[k + 1]] for k in range(1, len(idx) - 1)]
    v = np.array(verts, dtype=float).reshape(-1, 3)
    t = np.array(tris, dtype=np.int64).reshape(-1, 3)
    if len(v) == 0 or len(t) == 0:
        raise WorldImportError(f"mesh {path} has no vertices or faces")
    if t.min() < 0 or t.max() >= len(v):
        raise WorldImportError(f"mesh {path} has a face index outside its {len(v)} vertices")
    return v, t


def split_components(v: np.ndarray, t: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Split a mesh into its connected components (shared vertices), each re-indexed."""
    n = len(v)
    rows = np.concatenate([t[:, 0], t[:, 1], t[:, 2]])
    cols = np.concatenate([t[:, 1], t[:, 2], t[:, 0]])
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    tri_label = label[t[:, 0]]
    out = []
    for lab in np.unique(tri_label):
        tk = t[tri_label == lab]
        used, inv = np.unique(tk, return_inverse=True)
        out.append((v[used], inv.reshape(-1, 3)))
    return out


def import_gazebo_world(model_dir: Path, name: str | None = None):
    """A :class:`~sim.world.World` from a Gazebo model directory holding ``model.sdf``."""
    from sim.world import World

    model_dir = Path(model_dir)
    sdf = model_dir / "model.sdf"
    if not sdf.is_file():
        raise WorldImportError(f"no model.sdf in {model_dir}")
    try:
        root = ET.parse(sdf).getroot()
    except ET.ParseError as exc:
        raise WorldImportError(f"{sdf} is not valid XML: {exc}") from exc
    model = root.find("model")
    if model is None:
        raise WorldImportError(f"{sdf} has no <model>")
    T_world_model = pose_matrix(_floats(model.find("pose"), 6, "model/pose", [0.0] * 6))

    terrain = None
    meshes: list[tuple[np.ndarray, np.ndarray]] = []
    seen: set[str] = set()
    for link in model.findall("link"):
        T_model_link = pose_matrix(_floats(link.find("pose"), 6, "link/pose", [0.0] * 6))
        for elem in list(link.findall("collision")) + list(link.findall("visual")):
            geom = elem.find("geometry")
            if geom is None:
                continue
            hm = geom.find("heightmap")
            if hm is not None and terrain is None:
                uri = hm.findtext("uri")
                if not uri:
                    raise WorldImportError(f"{sdf}: <heightmap> without <uri>")
                size = _floats(hm.find("size"), 3, "heightmap/size")
                pos = _floats(hm.find("pos"), 3, "heightmap/pos", [0.0] * 3)
                pos = (T_world_model @ T_model_link @ np.append(pos, 1.0))[:3]
                terrain = load_heightmap(_resolve_uri(uri, model_dir), size, pos)
            mesh = geom.find("mesh")
            if mesh is None or elem.tag != "visual":
                continue
            uri = (mesh.findtext("uri") or "").strip()
            if "rock" not in Path(uri).name.lower() or uri in seen:
                continue
            seen.add(uri)
            path = _resolve_uri(uri, model_dir)
            if not path.is_file():
                log.warning("rock mesh %s referenced by %s is missing; skipped", path, sdf)
                continue
            T = T_world_model @ T_model_link @ pose_matrix(_floats(elem.find("pose"), 6, "visual/pose", [0.0] * 6))
            v, t = read_obj(path)
            v = v @ T[:3, :3].T + T[:3, 3]
            meshes += split_components(v, t)
    if terrain is None:
        raise WorldImportError(f"{sdf} has no <heightmap> geometry")
    rocks = Rocks.from_meshes(meshes)
    log.info("imported %s: %d rocks from %d mesh files", model_dir, len(rocks), len(seen))
    return World(name=name or model.get("name", model_dir.name), terrain=terrain, rocks=rocks,
                 preset=None, source=str(model_dir))
