"""The camera and frame messages of a bag: stereo images, CameraInfo, /tf and /tf_static, and the
orbital catalog as markers. The simulator's writer encodes with these functions and the image
front-end (``fgslam.io.image_rocks``) decodes with them, so both sides share one convention.

- Images: ``sensor_msgs/Image`` (``mono8``, ``mono16``, ``rgb8``, ``bgr8``, ``rgba8``, ``bgra8``)
  or ``sensor_msgs/CompressedImage`` (``png``, ``jpeg``; the ``image_transport`` form
  ``"mono8; png compressed mono8"`` too), decoded to (H, W) uint8 grey.
- CameraInfo: ``k``, ``d``, ``r``, ``p`` as ROS defines them; a stereo rig's baseline is
  ``-P_right[0, 3] / P_right[0, 0]``; images with distortion (``d`` non-zero) or a rectifying
  rotation (``r`` not identity) are rectified with OpenCV to the projection ``p``.
- /tf_static: ``geometry_msgs/TransformStamped`` parent -> child; :func:`resolve_transform`
  chains them (either direction) into ``T_parent_child`` of any two connected frames.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from reloc.bag_spec import BagCodecError

ENCODINGS = ("mono8", "mono16", "rgb8", "bgr8", "rgba8", "bgra8", "8UC1", "16UC1")


class ImageDecodeError(BagCodecError):
    """An image or camera message that cannot be used (encoding, size, calibration)."""


@dataclass(frozen=True)
class StereoFrame:
    """A rectified stereo pair to write (``left``, ``right``: (H, W) uint8) stamped ``t`` (s)."""

    t: float
    left: np.ndarray
    right: np.ndarray


@dataclass(frozen=True)
class CameraCalibration:
    """One camera as CameraInfo holds it: size (px), ``K`` (3, 3), ``D`` (n,), ``R`` (3, 3),
    ``P`` (3, 4), ``distortion_model``, ``frame_id``."""

    width_px: int
    height_px: int
    K: np.ndarray
    D: np.ndarray
    R: np.ndarray
    P: np.ndarray
    distortion_model: str = "plumb_bob"
    frame_id: str = ""

    @staticmethod
    def rectified(width_px: int, height_px: int, f_px: float, cx_px: float, cy_px: float,
                  tx_px_m: float = 0.0, frame_id: str = "") -> CameraCalibration:
        """A rectified pinhole camera; ``tx_px_m`` = -f * baseline for the right camera of a pair."""
        K = np.array([[f_px, 0.0, cx_px], [0.0, f_px, cy_px], [0.0, 0.0, 1.0]])
        P = np.column_stack([K, [tx_px_m, 0.0, 0.0]])
        return CameraCalibration(int(width_px), int(height_px), K, np.zeros(5), np.eye(3), P, "plumb_bob", frame_id)

    @property
    def needs_rectification(self) -> bool:
        return bool(np.any(self.D != 0.0) or not np.allclose(self.R, np.eye(3)))


def stereo_rig(left: CameraCalibration, right: CameraCalibration, baseline_m: float | None = None):
    """The rectified :class:`reloc.stereo.StereoRig` of a pair (from the projections ``P``)."""
    from reloc.stereo import StereoRig

    fx = float(left.P[0, 0])
    if not fx > 0:
        raise ImageDecodeError(f"left camera_info has no projection (P[0, 0] = {fx}): the camera is not calibrated")
    if baseline_m is None:
        baseline_m = -float(right.P[0, 3]) / float(right.P[0, 0]) if right.P[0, 0] > 0 else 0.0
        if not baseline_m > 0:
            raise ImageDecodeError(
                f"right camera_info P[0, 3] = {right.P[0, 3]} gives no positive baseline (-P[0, 3] / P[0, 0]); "
                "give images.baseline_m in the config")
    if (left.width_px, left.height_px) != (right.width_px, right.height_px):
        raise ImageDecodeError(f"left and right cameras differ in size: {left.width_px}x{left.height_px} "
                               f"vs {right.width_px}x{right.height_px}")
    return StereoRig(fx, float(left.P[0, 2]), float(left.P[1, 2]), float(baseline_m))


class Rectifier:
    """OpenCV remap of a raw image to the rectified projection of its CameraInfo (identity when
    the camera needs none)."""

    def __init__(self, cal: CameraCalibration) -> None:
        self.maps = None
        if not cal.needs_rectification:
            return
        import cv2

        size = (cal.width_px, cal.height_px)
        if cal.distortion_model == "equidistant":
            self.maps = cv2.fisheye.initUndistortRectifyMap(cal.K, cal.D[:4], cal.R, cal.P[:3, :3], size, cv2.CV_32FC1)
        elif cal.distortion_model in ("plumb_bob", "rational_polynomial", ""):
            self.maps = cv2.initUndistortRectifyMap(cal.K, cal.D, cal.R, cal.P[:3, :3], size, cv2.CV_32FC1)
        else:
            raise ImageDecodeError(f"camera_info distortion_model {cal.distortion_model!r} is not supported "
                                   "(plumb_bob, rational_polynomial, equidistant)")

    def __call__(self, img: np.ndarray) -> np.ndarray:
        if self.maps is None:
            return img
        import cv2

        return cv2.remap(img, self.maps[0], self.maps[1], cv2.INTER_LINEAR)


# -- decoding ------------------------------------------------------------------------------------

def decode_camera_info(msg) -> CameraCalibration:
    """sensor_msgs/CameraInfo -> :class:`CameraCalibration`."""
    K = np.reshape(np.asarray(msg.k, float), (3, 3))
    P = np.reshape(np.asarray(msg.p, float), (3, 4))
    R = np.reshape(np.asarray(msg.r, float), (3, 3))
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(P)) and np.all(np.isfinite(R))):
        raise ImageDecodeError("camera_info holds NaN or inf in K, R or P")
    if not np.any(R):
        R = np.eye(3)  # an all-zero R (some drivers): no rectifying rotation
    return CameraCalibration(int(msg.width), int(msg.height), K, np.asarray(msg.d, float), R, P,
                             str(msg.distortion_model), str(msg.header.frame_id))


def _to_grey(img: np.ndarray, order: str) -> np.ndarray:
    import cv2

    if img.ndim == 2:
        return img
    code = {"rgb": cv2.COLOR_RGB2GRAY, "bgr": cv2.COLOR_BGR2GRAY, "rgba": cv2.COLOR_RGBA2GRAY,
            "bgra": cv2.COLOR_BGRA2GRAY}[order]
    return cv2.cvtColor(np.ascontiguousarray(img), code)


def decode_image(msg, msgtype: str) -> np.ndarray:
    """An Image or CompressedImage message -> (H, W) uint8 grey (see module doc)."""
    import cv2

    data = np.asarray(msg.data, dtype=np.uint8)
    if msgtype.endswith("CompressedImage"):
        img = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE) if data.size else None
        if img is None:
            raise ImageDecodeError(f"compressed image (format {msg.format!r}, {data.size} bytes) cannot be decoded")
        return img
    enc, h, w, step = str(msg.encoding), int(msg.height), int(msg.width), int(msg.step)
    if enc not in ENCODINGS:
        raise ImageDecodeError(f"image encoding {enc!r} is not supported ({', '.join(ENCODINGS)})")
    channels = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4}.get(enc, 1)
    depth = 2 if enc in ("mono16", "16UC1") else 1
    if h < 1 or w < 1 or step < w * channels * depth or data.size < h * step:
        raise ImageDecodeError(f"image {w}x{h} {enc} with step {step} holds {data.size} bytes, expected {h * step}")
    rows = data[: h * step].reshape(h, step)[:, : w * channels * depth]
    if depth == 2:
        px = rows.view(">u2" if msg.is_bigendian else "<u2").reshape(h, w)
        return (px >> 8).astype(np.uint8)
    img = rows.reshape(h, w, channels) if channels > 1 else rows
    return _to_grey(img, enc.removesuffix("8")) if channels > 1 else np.ascontiguousarray(img)


def transform_matrix(tf) -> np.ndarray:
    """geometry_msgs/Transform -> (4, 4)."""
    q = np.array([tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w], float)
    if not (np.all(np.isfinite(q)) and abs(np.linalg.norm(q) - 1.0) < 1e-3):
        raise ImageDecodeError(f"transform rotation {q} is not a unit quaternion")
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(q).as_matrix()
    T[:3, 3] = [tf.translation.x, tf.translation.y, tf.translation.z]
    return T


def static_transforms(msgs: Iterable) -> dict[tuple[str, str], np.ndarray]:
    """(parent, child) -> ``T_parent_child`` of every TransformStamped in TFMessages ``msgs``."""
    out = {}
    for msg in msgs:
        for ts in msg.transforms:
            out[(str(ts.header.frame_id).lstrip("/"), str(ts.child_frame_id).lstrip("/"))] = transform_matrix(ts.transform)
    return out


def resolve_transform(edges: Mapping[tuple[str, str], np.ndarray], parent: str, child: str) -> np.ndarray:
    """``T_parent_child`` through the transform tree ``edges`` (edges used either way); raises
    :class:`ImageDecodeError` naming the frames when they are not connected."""
    graph: dict[str, list[tuple[str, np.ndarray]]] = {}
    for (a, b), T in edges.items():
        graph.setdefault(a, []).append((b, T))
        Ti = np.eye(4)
        Ti[:3, :3] = T[:3, :3].T
        Ti[:3, 3] = -T[:3, :3].T @ T[:3, 3]
        graph.setdefault(b, []).append((a, Ti))
    seen, todo = {parent: np.eye(4)}, [parent]
    while todo:
        a = todo.pop()
        for b, T in graph.get(a, []):
            if b not in seen:
                seen[b] = seen[a] @ T
                todo.append(b)
    if child not in seen:
        known = sorted(graph) or ["none"]
        raise ImageDecodeError(f"no transform from {parent!r} to {child!r} in /tf_static (frames: {', '.join(known)}); "
                               "give images.T_base_cam in the config")
    return seen[child]


# -- encoding (the simulator's writer) ------------------------------------------------------------

def quat_xyzw(R: np.ndarray) -> np.ndarray:
    return Rotation.from_matrix(np.asarray(R, float)[:3, :3]).as_quat()


def image_message(b, ns: int, frame_id: str, img: np.ndarray, fmt: str):
    """(H, W) uint8 -> Image (``fmt`` "raw": mono8) or CompressedImage (``fmt`` "png" / "jpeg")."""
    T = b.types
    img = np.ascontiguousarray(img, dtype=np.uint8)
    if fmt == "raw":
        return T["sensor_msgs/msg/Image"](header=b.header(ns, frame_id), height=img.shape[0], width=img.shape[1],
                                          encoding="mono8", is_bigendian=0, step=img.shape[1], data=img.ravel())
    import cv2

    ok, buf = cv2.imencode(".png" if fmt == "png" else ".jpg", img,
                           [cv2.IMWRITE_JPEG_QUALITY, 95] if fmt == "jpeg" else [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise ImageDecodeError(f"image cannot be encoded as {fmt}")
    return T["sensor_msgs/msg/CompressedImage"](header=b.header(ns, frame_id), format=f"mono8; {fmt} compressed mono8",
                                                data=buf.ravel())


def camera_info_message(b, ns: int, cal: CameraCalibration):
    T = b.types
    return T["sensor_msgs/msg/CameraInfo"](
        header=b.header(ns, cal.frame_id), height=cal.height_px, width=cal.width_px,
        distortion_model=cal.distortion_model, d=np.asarray(cal.D, float), k=np.asarray(cal.K, float).ravel(),
        r=np.asarray(cal.R, float).ravel(), p=np.asarray(cal.P, float).ravel(), binning_x=0, binning_y=0,
        roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))


def tf_message(b, ns: int, transforms: Iterable[tuple[str, str, np.ndarray]]):
    """TFMessage of (parent, child, T_parent_child) triples stamped ``ns``; T_parent_child a
    (4, 4) matrix or (translation, quaternion xyzw) as they are (no round trip through a matrix)."""
    T = b.types
    out = []
    for parent, child, M in transforms:
        p, q = M if isinstance(M, tuple) else (M[:3, 3], quat_xyzw(M))
        out.append(T["geometry_msgs/msg/TransformStamped"](
            header=b.header(ns, parent), child_frame_id=child,
            transform=T["geometry_msgs/msg/Transform"](translation=b.vec3(p), rotation=b.quat(q))))
    return T["tf2_msgs/msg/TFMessage"](transforms=out)


def catalog_markers(b, ns: int, frame_id: str, xy_m: np.ndarray, size_m: np.ndarray, ns_name: str = "catalog"):
    """MarkerArray of one flat cylinder per catalog entry (diameter ``size_m``) at z = 0 in ``frame_id``."""
    T = b.types
    color = T["std_msgs/msg/ColorRGBA"](r=0.9, g=0.75, b=0.43, a=0.8)
    zero = T["builtin_interfaces/msg/Duration"](sec=0, nanosec=0)
    markers = []
    for i, ((x, y), d) in enumerate(zip(np.asarray(xy_m, float), np.asarray(size_m, float))):
        markers.append(T["visualization_msgs/msg/Marker"](
            header=b.header(ns, frame_id), ns=ns_name, id=i, type=3, action=0,  # CYLINDER, ADD
            pose=b.pose((x, y, 0.0), (0.0, 0.0, 0.0, 1.0)), scale=b.vec3((max(d, 0.05), max(d, 0.05), 0.05)),
            color=color, lifetime=zero, frame_locked=False, points=[], colors=[], texture_resource="",
            texture=T["sensor_msgs/msg/CompressedImage"](header=b.header(ns, frame_id), format="", data=np.zeros(0, np.uint8)),
            uv_coordinates=[], text="", mesh_resource="",
            mesh_file=T["visualization_msgs/msg/MeshFile"](filename="", data=np.zeros(0, np.uint8)),
            mesh_use_embedded_materials=False))
    return T["visualization_msgs/msg/MarkerArray"](markers=markers)
