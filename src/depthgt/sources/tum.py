"""TUM RGB-D benchmark adapter.

A sequence folder (``rgbd_dataset_freiburg1_xyz``, ...) holds::

    rgb.txt, depth.txt     "timestamp filename" per line, "#" comments
    groundtruth.txt        "timestamp tx ty tz qx qy qz qw" (colour camera in the
                           motion-capture world: camera-to-world), optional
    rgb/*.png              640x480 colour
    depth/*.png            640x480 uint16, 5000 units per metre, 0 = invalid,
                           registered to the colour camera by the OpenNI driver

``root`` is a folder of sequence folders (or a sequence folder itself, scene ``"."``
or its name). Frames are the depth images of ``depth.txt`` in time order; ``frame_id``
is the depth timestamp as written there. A ``depth.txt`` out of time order is sorted and
an entry repeating an earlier timestamp or file is dropped, both recorded in
``problems`` (a frame set could otherwise hold one image twice); a timestamp that is
not a finite number, in any of the three lists, is a SourceError naming file and line. Each depth image is associated with the colour image
and the ground-truth pose nearest in time; an association further than ``max_dt``
seconds (default 0.02) makes the frame fail with ``FrameError("no_association")``
(the pose one only when ``require_pose``; otherwise the pose is None).

Intrinsics (TUM's published calibration of each Kinect's colour camera, to which the
depth is registered): chosen by the sequence name (``freiburg1``/``fr1`` ...),
overridable with the option ``camera`` (one of :data:`CAMERAS`) or ``intrinsics``
(3x3). A name without a camera falls back to fr1 with a warning.

Lens distortion: fr1 and fr2 images keep their lens's radial distortion (fr3's was
removed by TUM). With ``undistort`` (default True) depth and colour are undistorted
with the camera's published coefficients (:data:`DISTORTION`, or the option
``distortion``: k1, k2, p1, p2, k3 in OpenCV's order) onto the same intrinsics:
colour bilinearly, depth by its nearest source pixel so that no two depths mix. The
``ros_default`` camera (TUM's suggestion for the pre-registered depth) has none.

Poses: the motion-capture pose at each depth frame's timestamp, interpolated between
the two trajectory rows around it (linear translation, normalised linear quaternion
blend; the rows are 10 ms apart) when both are within ``max_dt``; else the nearest row
within ``max_dt``. ``interpolate_poses: false`` takes the nearest row.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import cv2
import numpy as np

from depthgt.errors import FrameError, SourceError
from depthgt.io import fit_rgb_to_depth, read_rgb
from depthgt.shapes import check_shape
from depthgt.sources._files import FileScene, list_sequences, probe_depth_size, require_root
from depthgt.sources.base import Frame, check_frame, usable_pose

__all__ = [
    "CAMERAS",
    "DISTORTION",
    "DEPTH_SCALE",
    "TumScene",
    "associate",
    "poses_from_tum",
    "open_scene",
    "list_scenes",
]

log = logging.getLogger(__name__)

#: fx, fy, cx, cy at 640x480 (TUM RGB-D "intrinsic calibration" page).
CAMERAS: dict[str, tuple[float, float, float, float]] = {
    "fr1": (517.3, 516.5, 318.6, 255.3),
    "fr2": (520.9, 521.0, 325.1, 249.7),
    "fr3": (535.4, 539.2, 320.1, 247.6),
    "ros_default": (525.0, 525.0, 319.5, 239.5),
}
#: k1, k2, p1, p2, k3 (OpenCV order) of each camera (TUM's published d0..d4); fr3's
#: images were undistorted by TUM, the ROS default set describes undistorted images.
DISTORTION: dict[str, tuple[float, float, float, float, float]] = {
    "fr1": (0.2624, -0.9531, -0.0054, 0.0026, 1.1633),
    "fr2": (0.2312, -0.7849, -0.0033, -0.0001, 0.9172),
    "fr3": (0.0, 0.0, 0.0, 0.0, 0.0),
    "ros_default": (0.0, 0.0, 0.0, 0.0, 0.0),
}
DEPTH_SCALE = 5000.0  # raw units per metre in TUM depth PNGs

_CAMERA_IN_NAME = re.compile(r"(?:freiburg|fr)([123])", re.IGNORECASE)


def _read_list(path: Path, columns: int) -> tuple[np.ndarray, np.ndarray]:
    """Rows of a TUM text file ("#" comments and blank lines skipped) as an
    (N, columns) str array, and the (N,) 1-based line number of each row."""
    if not path.is_file():
        raise SourceError(f"{path}: file not found")
    rows, numbers = [], []
    for number, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
        fields = line.split()
        if not fields or fields[0].startswith("#"):
            continue
        if len(fields) != columns:
            raise SourceError(f"{path}: line {number} has {len(fields)} fields, expected {columns}")
        rows.append(fields)
        numbers.append(number)
    return np.array(rows, dtype=str).reshape(len(rows), columns), np.array(numbers, dtype=np.int64)


def _numbers(
    col: np.ndarray, lines: np.ndarray, path: Path, what: str = "timestamp", finite: bool = True
) -> np.ndarray:
    """(N,) float64 of a column; SourceError naming the file and line of the first value
    that does not parse or (with ``finite``) is not finite: a ``nan`` timestamp would
    pair with anything. Non-finite pose values are left to the per-frame pose check."""
    try:
        values = col.astype(np.float64)
    except ValueError:
        for k, text in enumerate(col.tolist()):  # find the culprit's line for the message
            try:
                float(text)
            except ValueError:
                raise SourceError(f"{path}: line {lines[k]}: {what} {text!r} is not a number") from None
        raise
    bad = np.flatnonzero(~np.isfinite(values)) if finite else ()
    if len(bad):
        raise SourceError(
            f"{path}: line {lines[bad[0]]}: {what} {str(col[bad[0]])!r} is not finite ({len(bad)} such value(s))"
        )
    return values


def clean_list(t: np.ndarray, files: np.ndarray, lines: np.ndarray, path: Path) -> tuple[np.ndarray, list[str]]:
    """Order a TUM list by time and drop repeated entries.

    TUM lists are written in time order with one line per image; a list edited by hand
    or concatenated may be out of order or repeat an image, which would put the same
    image twice into a frame set. Entries are sorted by timestamp (stable) and an entry
    whose timestamp or file name was already listed is dropped; both are recorded.

    Args:
        t: (N,) finite timestamps (seconds); files: (N,) file names; lines: (N,) line
            numbers (for the messages).

    Returns:
        (M,) int64 positions into the list to keep, in time order; the problems found
        (one message per kind, naming the file and the first line concerned).
    """
    problems = []
    order = np.argsort(t, kind="stable")
    backwards = np.flatnonzero(np.diff(t) < 0)
    if backwards.size:
        problems.append(
            f"{path}: {backwards.size} entries out of time order (first at line {lines[backwards[0] + 1]}); "
            "sorted by timestamp"
        )
    keep, seen_t, seen_f, dropped = [], {}, {}, []
    for k in order.tolist():
        earlier = seen_t.get(t[k], seen_f.get(files[k]))
        if earlier is not None:
            dropped.append((lines[k], lines[earlier]))
            continue
        seen_t[t[k]] = seen_f[files[k]] = k
        keep.append(k)
    if dropped:
        first, of = min(dropped)
        problems.append(
            f"{path}: {len(dropped)} repeated entries dropped (same timestamp or file; first: line {first} "
            f"repeats line {of})"
        )
    return np.array(keep, dtype=np.int64), problems


def associate(t_query: np.ndarray, t_ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest reference timestamp of each query timestamp.

    Args:
        t_query: (N,) float64 seconds.
        t_ref: (M,) float64 seconds, any order.

    Returns:
        (N,) int64 index into ``t_ref`` (-1 when ``t_ref`` is empty) and (N,) float64
        absolute time difference in seconds (inf when ``t_ref`` is empty).
    """
    t_query = np.asarray(t_query, dtype=np.float64)
    if t_ref.size == 0:
        return np.full(t_query.shape, -1, np.int64), np.full(t_query.shape, np.inf)
    order = np.argsort(t_ref, kind="stable")
    ts = t_ref[order]
    right = np.clip(np.searchsorted(ts, t_query), 0, ts.size - 1)
    left = np.clip(right - 1, 0, ts.size - 1)
    take_left = np.abs(t_query - ts[left]) <= np.abs(ts[right] - t_query)
    nearest = np.where(take_left, left, right)
    return order[nearest].astype(np.int64), np.abs(ts[nearest] - t_query)


def interpolate_rows(
    t_query: np.ndarray, t_ref: np.ndarray, rows: np.ndarray, max_dt: float
) -> tuple[np.ndarray, np.ndarray]:
    """Trajectory rows ``tx ty tz qx qy qz qw`` at the query times.

    Between the two reference rows around a query time, when both are within ``max_dt``
    of it: linear translation and a normalised linear blend of the quaternions (signs
    aligned first; for rows 10 ms apart it differs from slerp by far less than the
    motion capture's noise). Elsewhere the nearest row.

    Args:
        t_query: (N,) seconds; t_ref: (M,) seconds, any order; rows: (M, 7).

    Returns:
        (N, 7) rows and (N,) the time to the farthest row used (seconds; inf when
        ``t_ref`` is empty).
    """
    nearest, dt = associate(t_query, t_ref)
    if t_ref.size < 2:
        return (rows[nearest] if t_ref.size else np.full((t_query.size, 7), np.nan)), dt
    order = np.argsort(t_ref, kind="stable")
    ts, rs = t_ref[order], rows[order]
    hi = np.clip(np.searchsorted(ts, t_query, side="right"), 1, ts.size - 1)
    lo = hi - 1
    span = ts[hi] - ts[lo]
    inside = (ts[lo] <= t_query) & (t_query <= ts[hi]) & (span > 0)
    far = np.maximum(t_query - ts[lo], ts[hi] - t_query)
    use = inside & (far <= max_dt)
    a = np.where(use, (t_query - ts[lo]) / np.where(span > 0, span, 1.0), 0.0)[:, None]
    q0, q1 = rs[lo, 3:], rs[hi, 3:]
    q1 = np.where((q0 * q1).sum(1, keepdims=True) < 0, -q1, q1)
    q = (1 - a) * q0 + a * q1
    q /= np.linalg.norm(q, axis=1, keepdims=True).clip(1e-12)
    blended = np.concatenate([(1 - a) * rs[lo, :3] + a * rs[hi, :3], q], axis=1)
    out = np.where(use[:, None], blended, rows[nearest])
    return out, np.where(use, far, dt)


def poses_from_tum(rows: np.ndarray) -> np.ndarray:
    """TUM trajectory rows ``tx ty tz qx qy qz qw`` -> camera-to-world matrices.

    Args:
        rows: (N, 7) float64.

    Returns:
        (N, 4, 4) float64; a row with a non-finite or zero quaternion gives NaN rotation.
    """
    import torch
    from kornia.geometry.conversions import quaternion_to_rotation_matrix

    rows = np.asarray(rows, dtype=np.float64)
    check_shape(rows, "N 7", "TUM pose rows")
    q_xyzw = rows[:, 3:7]
    bad = ~np.isfinite(q_xyzw).all(1) | (np.linalg.norm(np.nan_to_num(q_xyzw), axis=1) < 1e-9)
    q_wxyz = torch.from_numpy(np.nan_to_num(q_xyzw[:, [3, 0, 1, 2]]))  # kornia is real-part first
    q_wxyz[torch.from_numpy(bad)] = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    R = quaternion_to_rotation_matrix(q_wxyz).numpy()
    R[bad] = np.nan
    T = np.tile(np.eye(4), (rows.shape[0], 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = rows[:, :3]
    return T


class TumScene(FileScene):
    """One TUM RGB-D sequence (see the module docstring)."""

    has_clean_depth = False

    def __init__(
        self,
        folder: str | Path,
        name: str,
        max_dt: float = 0.02,
        camera: str | None = None,
        intrinsics: np.ndarray | None = None,
        depth_scale: float = DEPTH_SCALE,
        require_pose: bool = True,
        undistort: bool = True,
        distortion: tuple[float, ...] | None = None,
        interpolate_poses: bool = True,
    ):
        self._init_files(folder, name, depth_scale, require_pose)
        if not max_dt >= 0:
            raise SourceError(f"{self.path}: max_dt must be >= 0 seconds, got {max_dt}")
        self.max_dt = float(max_dt)
        self.intrinsics = self._intrinsics(camera, intrinsics)
        self.distortion = self._distortion(undistort, distortion)
        self._maps: tuple[np.ndarray, np.ndarray] | None = None

        depth_rows, t_depth = self._list("depth.txt", clean=True)
        rgb_rows, t_rgb = self._list("rgb.txt", clean=False)  # any order: colour is associated by nearest time
        if depth_rows.shape[0] == 0:
            raise SourceError(f"{self.path / 'depth.txt'}: no depth frames listed")
        self._depth_ids = depth_rows[:, 0]
        self._depth_files = depth_rows[:, 1]
        self._rgb_files = rgb_rows[:, 1]
        self._rgb_index, self._rgb_dt = associate(t_depth, t_rgb)

        gt_path = self.path / "groundtruth.txt"
        self.has_poses = gt_path.is_file()
        if self.has_poses:
            gt, gt_lines = _read_list(gt_path, 8)
            t_gt = _numbers(gt[:, 0], gt_lines, gt_path)
            values = np.stack(
                [_numbers(gt[:, c], gt_lines, gt_path, "pose value", finite=False) for c in range(1, 8)], axis=1
            )
            if interpolate_poses:
                rows, self._pose_dt = interpolate_rows(t_depth, t_gt, values, self.max_dt)
                self._poses = poses_from_tum(rows)
                self._pose_index = np.arange(t_depth.size)
            else:
                self._poses = poses_from_tum(values)
                self._pose_index, self._pose_dt = associate(t_depth, t_gt)
        # recorded in index.json: each frame's own reason ("no pose", "no colour image") would not
        # name the file that is absent or empty
        if not self.has_poses:
            self.problems.append(
                f"{gt_path}: not found; the frames have no poses (registration.method overfit needs none)"
            )
        if rgb_rows.shape[0] == 0:
            self.problems.append(
                f"{self.path / 'rgb.txt'}: no colour frames listed; every frame lacks its colour image"
            )
        n_rgb = int((self._rgb_dt > self.max_dt).sum())
        if n_rgb:
            log.info(
                "%s: %d of %d depth frames have no colour within %.3f s", self.path, n_rgb, t_depth.size, self.max_dt
            )
        self.image_size = self._probe_size()

    def _intrinsics(self, camera: str | None, intrinsics) -> np.ndarray:
        self.camera = None
        if intrinsics is not None:
            K = np.asarray(intrinsics, dtype=np.float64)
            if K.shape != (3, 3) or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
                raise SourceError(f"{self.path} (option intrinsics): need a finite 3x3 matrix, got {K.tolist()}")
            return K.copy()
        if camera is None:
            m = _CAMERA_IN_NAME.search(self.path.resolve().name)
            if m:
                camera = f"fr{m.group(1)}"
            else:
                log.warning("%s: sequence name names no freiburg camera, using fr1 intrinsics", self.path)
                camera = "fr1"
        if camera not in CAMERAS:
            raise SourceError(f"{self.path}: unknown TUM camera {camera!r}; known: {', '.join(CAMERAS)}")
        self.camera = camera
        fx, fy, cx, cy = CAMERAS[camera]
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    def _distortion(self, undistort: bool, distortion) -> np.ndarray | None:
        """(5,) float64 coefficients to remove, or None (nothing to undistort)."""
        if not undistort:
            return None
        if distortion is None:
            if self.camera is None:  # explicit intrinsics: no published coefficients apply
                return None
            distortion = DISTORTION[self.camera]
        d = np.asarray(distortion, dtype=np.float64).reshape(-1)
        if d.shape != (5,) or not np.isfinite(d).all():
            raise SourceError(
                f"{self.path} (option distortion): need 5 finite numbers k1, k2, p1, p2, k3, got {distortion!r}"
            )
        return None if not d.any() else d

    def _undistort(self, image: np.ndarray, nearest: bool) -> np.ndarray:
        """``image`` (H, W[, 3]) resampled onto the undistorted pinhole camera of the same
        intrinsics (OpenCV's undistortion maps, built once per scene); depth by the
        nearest source pixel so that valid and invalid depths never mix."""
        if self.distortion is None:
            return image
        if self._maps is None:
            h, w = self.image_size
            self._maps = cv2.initUndistortRectifyMap(
                self.intrinsics, self.distortion, None, self.intrinsics, (w, h), cv2.CV_32FC1
            )
        interp = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
        return cv2.remap(image, self._maps[0], self._maps[1], interp, borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    def _list(self, name: str, clean: bool) -> tuple[np.ndarray, np.ndarray]:
        """Rows of ``rgb.txt`` / ``depth.txt`` and their (N,) finite timestamps; with
        ``clean``, in time order without repeats (see :func:`clean_list`, recorded in
        ``problems``)."""
        path = self.path / name
        rows, lines = _read_list(path, 2)
        t = _numbers(rows[:, 0], lines, path)
        if not clean:
            return rows, t
        keep, problems = clean_list(t, rows[:, 1], lines, path)
        for msg in problems:
            log.warning("%s", msg)
        self.problems.extend(problems)
        return rows[keep], t[keep]

    def _probe_size(self) -> tuple[int, int]:
        return self._set_size(probe_depth_size([self.path / rel for rel in self._depth_files], self.path))

    def __len__(self) -> int:
        return int(self._depth_ids.size)

    def frame_id(self, i: int) -> str:
        return str(self._depth_ids[i])

    def read(self, i: int) -> Frame:
        """Frame at position ``i``; raises FrameError naming the file at fault."""
        if not 0 <= i < len(self):
            raise IndexError(f"{self.path}: frame position {i} out of range 0..{len(self) - 1}")
        depth_path = self.path / str(self._depth_files[i])
        where = f"{self.path} depth {self._depth_ids[i]}"
        if self._rgb_dt[i] > self.max_dt:
            raise FrameError(
                f"{depth_path}: no colour image within {self.max_dt} s (nearest {self._rgb_dt[i]:.4f} s)",
                "no_association",
            )
        need_pose = self.require_pose and self.has_poses
        T = None
        if self.has_poses:
            if self._pose_dt[i] <= self.max_dt:
                T = self._poses[self._pose_index[i]].copy()
                if not need_pose:
                    T = usable_pose(T)
            elif need_pose:
                raise FrameError(
                    f"{depth_path}: no ground-truth pose within {self.max_dt} s (nearest {self._pose_dt[i]:.4f} s)",
                    "no_association",
                )
        depth_m = self._undistort(self._read_depth(depth_path), nearest=True)
        color_path = self.path / str(self._rgb_files[self._rgb_index[i]])
        rgb = self._undistort(fit_rgb_to_depth(read_rgb(color_path), self.image_size, str(color_path)), nearest=False)
        return check_frame(Frame(rgb, depth_m, T), self.image_size, where, need_pose)


def _is_sequence(folder: Path) -> bool:
    return (folder / "depth.txt").is_file()


def _root(root: str | Path | None) -> Path:
    return require_root(root, "tum")


def list_scenes(root: str | Path | None, **options) -> list[str]:
    """Sorted sequence names under ``root`` (``[root's name]`` when root is one)."""
    return list_sequences(_root(root), _is_sequence)


def open_scene(
    root: str | Path | None,
    scene: str,
    max_dt: float = 0.02,
    camera: str | None = None,
    intrinsics: np.ndarray | None = None,
    depth_scale: float = DEPTH_SCALE,
    require_pose: bool = True,
    undistort: bool = True,
    distortion: tuple[float, ...] | None = None,
    interpolate_poses: bool = True,
) -> TumScene:
    """Open TUM sequence ``scene`` under ``root``.

    Raises:
        SourceError: root or scene not found (the message lists the known scenes),
            malformed lists, unknown camera.
    """
    path = _root(root)
    opts = dict(
        max_dt=max_dt,
        camera=camera,
        intrinsics=intrinsics,
        depth_scale=depth_scale,
        require_pose=require_pose,
        undistort=undistort,
        distortion=distortion,
        interpolate_poses=interpolate_poses,
    )
    if _is_sequence(path) and scene in (".", path.resolve().name):
        return TumScene(path, path.resolve().name, **opts)
    folder = path / scene
    if scene not in (".", "") and _is_sequence(folder):
        return TumScene(folder, scene, **opts)
    known = list_scenes(path)
    raise SourceError(f"{path}: unknown tum scene {scene!r}; known scenes: {', '.join(known) or '(none)'}")
