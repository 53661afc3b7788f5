"""One interface for every RGB-D source, and the registry of adapters.

Every adapter opens one *scene* (a single continuous RGB-D stream) and exposes:

* ``len(scene)``: number of frames (frame positions ``0..len-1``);
* ``scene.intrinsics``: (3, 3) float64 pinhole matrix of the depth camera at
  ``scene.image_size``;
* ``scene.image_size``: ``(H, W)`` of the depth image (colour is brought to it);
* ``scene.has_poses``: whether ``read`` returns camera-to-world poses;
* ``scene.colour_matches_depth``: whether colour is taken by the depth's camera at the
  depth's instant (synthetic), so that a photometric residual is exact to the sub-pixel;
  real sensors' colour comes from another camera (7-Scenes, ScanNet) or another instant
  (TUM: 10-20 ms apart), and the registration leaves its photometric refinement term
  out there (``registration.photometric: auto``). Set by :func:`open_scene` from the
  kind's registry entry (a config source may override it), not by the adapter;
* ``scene.has_clean_depth``: whether ``read`` returns noise-free depth (synthetic);
* ``scene.frame_id(i)``: the source's own id for position ``i`` (file number,
  timestamp, ...), used in manifests;
* ``scene.read(i) -> Frame``: raises :class:`~depthgt.errors.FrameError` when the
  frame is unusable (the message names the file).

Every source kind is one entry of the registry :data:`KINDS` (:class:`SourceKind`): its
adapter module, its options and their checks, whether its poses are optional, whether a
scene may be a single file and whether its colour matches its depth. Adapter modules are
imported lazily, by the functions below, so that opening a 7-Scenes folder never imports
the ``.sens`` reader and the workflow's start-up checks import no adapter at all.

Checks that run when the workflow starts, before any data is opened (numpy only):
:func:`check_options` (the adapter options of a source) and
:func:`check_scene_identity` (no scene twice, no data under two sources or in two
splits). :func:`check_frame` and :func:`pose_problem` check every frame as it is read.
"""

from __future__ import annotations

import importlib
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np

from depthgt.errors import ConfigError, FrameError, SourceError


@dataclass(frozen=True)
class Frame:
    """One RGB-D frame at the depth camera's resolution.

    Attributes:
        rgb: (H, W, 3) uint8 colour, RGB order, registered to the depth image as well
            as the source allows.
        depth_m: (H, W) float32 depth in metres, 0 = invalid.
        T_world_cam: (4, 4) float64 camera-to-world pose, or None when the source has
            no poses.
        clean_depth_m: (H, W) float32 noise-free depth in metres (0 = no surface), only
            for sources that know it (synthetic), else None.
    """

    rgb: np.ndarray
    depth_m: np.ndarray
    T_world_cam: np.ndarray | None = None
    clean_depth_m: np.ndarray | None = None


@runtime_checkable
class Scene(Protocol):
    """A single RGB-D stream; see the module docstring for the contract."""

    name: str
    intrinsics: np.ndarray
    image_size: tuple[int, int]
    has_poses: bool
    has_clean_depth: bool
    colour_matches_depth: bool

    def __len__(self) -> int: ...

    def frame_id(self, i: int) -> str: ...

    def read(self, i: int) -> Frame: ...


def known_kinds() -> list[str]:
    """The registered source kinds, sorted."""
    return sorted(KINDS)


def source_kind(kind: str) -> SourceKind:
    """The registry entry of ``kind``.

    Raises:
        SourceError: unknown kind (the message lists the known ones).
    """
    if kind not in KINDS:
        raise SourceError(f"unknown source kind {kind!r}; known kinds: {', '.join(known_kinds())}")
    return KINDS[kind]


def _adapter(kind: str):
    """The adapter module of ``kind``, imported now (lazily: only the kinds in use)."""
    return importlib.import_module(source_kind(kind).module)


def open_scene(kind: str, root: str | None, scene: str, **options: Any) -> Scene:
    """Open scene ``scene`` of a source of kind ``kind`` under ``root``; the scene's
    ``colour_matches_depth`` is the kind's (:class:`SourceKind`; a config source
    overrides it, :func:`depthgt.jobs.common.open_source_scene`).

    Raises:
        SourceError: unknown kind, unknown scene (the message lists the known ones),
            or a scene that cannot be opened.
    """
    opened = _adapter(kind).open_scene(root, scene, **options)
    opened.colour_matches_depth = KINDS[kind].colour_matches_depth
    return opened


def list_scenes(kind: str, root: str | None, **options: Any) -> list[str]:
    """Names of the scenes a source holds, sorted."""
    return _adapter(kind).list_scenes(root, **options)


def frame_count(kind: str, root: str | None, scene: str, **options: Any) -> int:
    """Number of frame positions of a scene, from cheap metadata: what the workflow plans
    its frame sets from, without reading a frame. An adapter module may define
    ``frame_count(root, scene, **options)`` (the synthetic source: its ``n_frames``; a
    ``.sens`` file: its header); otherwise the scene is opened, which for folder sources
    lists files and parses text lists only. Frames that turn out unreadable are recorded
    by the frame-set batch jobs that read them, and targets planned beyond the frames a
    job can read are recorded as skipped there.

    Raises:
        SourceError: as :func:`open_scene`.
    """
    counter = getattr(_adapter(kind), "frame_count", None)
    if counter is not None:
        return int(counter(root, scene, **options))
    return len(open_scene(kind, root, scene, **options))


def scene_file(kind: str, root: str | None, scene: str, **options: Any) -> str | None:
    """The one file that holds a scene (ScanNet's ``.sens``), or None: a kind without
    ``single_file`` (:class:`SourceKind`), or a scene that is a folder. The workflow makes
    it an input of the scene's index, so that a change of the file re-runs it (a folder
    has too many files to list)."""
    if not source_kind(kind).single_file or root is None:
        return None
    path = _adapter(kind).scene_file(root, scene, **options)
    return None if path is None else str(path)


# ---------------------------------------------------------------- frame checks

#: Largest |R R^T - I| entry and |det R - 1| of a rigid pose. 7-Scenes' KinectFusion
#: poses, written with 8 digits, reach 1.3e-4 and 1.7e-4.
ROTATION_TOL = 1e-3
#: Largest deviation of a pose's bottom row from ``0 0 0 1``.
BOTTOM_ROW_TOL = 1e-6


def pose_problem(T: np.ndarray | None) -> tuple[str, str] | None:
    """Why ``T`` is not a usable camera-to-world pose, or None when it is.

    A usable pose is a finite (4, 4) matrix with a rotation block that is orthonormal
    with determinant +1 (within :data:`ROTATION_TOL`) and a bottom row ``0 0 0 1``
    (within :data:`BOTTOM_ROW_TOL`): a bottom row ``0 0 0 0`` makes the matrix
    singular, ``0 0 0 2`` scales every point by 1/2 once normalised.

    Returns:
        ``(reason, description)`` with reason ``"missing_pose"``, ``"nonfinite_pose"``
        or ``"invalid_pose"``; or None.
    """
    if T is None:
        return "missing_pose", "no pose"
    T = np.asarray(T)
    if T.shape != (4, 4):
        return "invalid_pose", f"pose has shape {T.shape}, expected (4, 4)"
    if not np.isfinite(T).all():
        return "nonfinite_pose", "pose is not a finite 4x4 matrix"
    T = T.astype(np.float64)
    bottom = T[3]
    if np.abs(bottom - (0.0, 0.0, 0.0, 1.0)).max() > BOTTOM_ROW_TOL:
        return "invalid_pose", f"pose's bottom row is {' '.join(f'{v:g}' for v in bottom)}, expected 0 0 0 1"
    R = T[:3, :3]
    err = float(np.abs(R @ R.T - np.eye(3)).max())
    if err > ROTATION_TOL:
        return "invalid_pose", f"pose rotation is not orthonormal (max |R R^T - I| = {err:.3g})"
    det = float(np.linalg.det(R))
    if abs(det - 1.0) > ROTATION_TOL:
        return (
            "invalid_pose",
            f"pose rotation has determinant {det:.4g}, expected +1 (a reflection is not a rigid motion)",
        )
    return None


def usable_pose(T: np.ndarray | None) -> np.ndarray | None:
    """``T`` when :func:`pose_problem` finds nothing wrong with it, else None (for
    adapters whose poses are optional: ``require_pose: false``)."""
    return T if T is not None and pose_problem(T) is None else None


def check_frame(frame: Frame, expected_hw: tuple[int, int], where: str, need_pose: bool) -> Frame:
    """Validate a frame read by an adapter; raise :class:`FrameError` naming ``where``.

    Checks shapes and dtypes, finite depth, a non-empty depth image and (when
    ``need_pose``) a usable pose (:func:`pose_problem`: finite, rigid, bottom row
    ``0 0 0 1``), so that nothing downstream inverts a singular or scaled pose.
    """
    h, w = expected_hw
    if frame.depth_m.shape != (h, w):
        raise FrameError(
            f"{where}: depth is {frame.depth_m.shape[1]}x{frame.depth_m.shape[0]}, expected {w}x{h}", "size_mismatch"
        )
    if frame.rgb.shape != (h, w, 3):
        raise FrameError(f"{where}: colour has shape {frame.rgb.shape}, expected {(h, w, 3)}", "size_mismatch")
    if not np.isfinite(frame.depth_m).all():
        raise FrameError(f"{where}: depth holds non-finite values", "nonfinite_depth")
    if not (frame.depth_m > 0).any():
        raise FrameError(f"{where}: depth image is empty (no valid pixel)", "empty_depth")
    if need_pose:
        problem = pose_problem(frame.T_world_cam)
        if problem is not None:
            raise FrameError(f"{where}: {problem[1]}", problem[0])
    return frame


# ---------------------------------------------------------------- option checks


@dataclass(frozen=True)
class OptionCheck:
    """One adapter option: ``check(value) -> bool`` and what a valid value is."""

    expects: str
    check: Callable[[Any], bool]


def _is_number(v: Any) -> bool:
    return (
        isinstance(v, (int, float, np.integer, np.floating))
        and not isinstance(v, (bool, np.bool_))
        and bool(np.isfinite(v))
    )


def _is_seq_of_numbers(v: Any, n: int) -> bool:
    return isinstance(v, (list, tuple)) and len(v) == n and all(_is_number(x) for x in v)


def _is_int(v: Any) -> bool:
    return isinstance(v, (int, np.integer)) and not isinstance(v, (bool, np.bool_))


def _intrinsics_ok(shapes: tuple[tuple[int, int], ...]) -> Callable[[Any], bool]:
    def check(v: Any) -> bool:
        try:
            K = np.asarray(v, dtype=np.float64)
        except (TypeError, ValueError):
            return False
        return K.shape in shapes and bool(np.isfinite(K).all()) and K[0, 0] > 0 and K[1, 1] > 0

    return check


_BOOL = OptionCheck("true or false", lambda v: isinstance(v, (bool, np.bool_)))
_DEPTH_SCALE = OptionCheck("a number > 0 (raw depth units per metre)", lambda v: _is_number(v) and v > 0)
_K33 = OptionCheck("a finite 3x3 matrix with positive focal lengths", _intrinsics_ok(((3, 3),)))
_K_ANY = OptionCheck(
    "a finite 3x3 (or 4x4) matrix with positive focal lengths", _intrinsics_ok(((3, 3), (4, 4), (3, 4), (4, 3)))
)


def _int_in(lo: int, hi: int) -> OptionCheck:
    return OptionCheck(f"an integer in [{lo}, {hi}]", lambda v: _is_int(v) and lo <= v <= hi)


def _number(lo: float, strict: bool) -> OptionCheck:
    return OptionCheck(
        f"a number {'>' if strict else '>='} {lo:g}", lambda v: _is_number(v) and (v > lo if strict else v >= lo)
    )


_OPTIONAL_POSITIVE = OptionCheck("null or a number > 0", lambda v: v is None or (_is_number(v) and v > 0))

#: Sensor profiles (depthgt.synth.noise.SENSOR_PROFILES) and scene families
#: (depthgt.sources.synthetic.FAMILIES) of the synthetic source.
SYNTHETIC_SENSORS = ("kinect_v1", "coarse_stereo")
SYNTHETIC_FAMILIES = ("room", "varied")

#: Fields of depthgt.synth.noise.KinectNoise (option ``noise_<field>``); a test keeps
#: this list equal to the dataclass, which is not imported here (it needs OpenCV).
SYNTHETIC_NOISE_FIELDS = (
    "baseline_m",
    "disparity_step_px",
    "sigma_disp_px",
    "sigma_disp_smooth_px",
    "sigma_disp_falloff",
    "jitter_px",
    "shadow_tol_px",
    "shadow_grow_px",
    "edge_band_px",
    "edge_rel_jump",
    "edge_drop_prob",
    "grazing_cos",
    "dark_level",
    "min_range_m",
    "max_range_m",
    "far_ramp_m",
    "blob_fraction",
    "border_right_px",
    "round_mm",
)
#: Default of the synthetic ``seed`` option (part of a synthetic scene's identity).
SYNTHETIC_DEFAULT_SEED = 0


@dataclass(frozen=True)
class SourceKind:
    """One source kind of the registry :data:`KINDS`: everything the project knows of it.

    Attributes:
        module: the adapter module, imported lazily (when a scene of the kind is listed,
            counted or opened): ``open_scene(root, scene, **options) -> Scene`` and
            ``list_scenes(root, **options) -> list[str]``; optionally
            ``frame_count(root, scene, **options)`` (planning from cheap metadata, see
            :func:`frame_count`) and, with ``single_file``, ``scene_file(root, scene,
            **options)``.
        options: option name -> :class:`OptionCheck` of every option ``open_scene``
            takes, checked when the workflow starts (:func:`check_options`, numpy only:
            the module is not imported); None: not checked before the adapter opens a
            scene.
        poses_optional: the source's poses may be missing or unusable (option
            ``require_pose``): a job whose registration needs no poses opens it with
            ``require_pose: false`` (:func:`depthgt.jobs.common.open_source_scene`).
        single_file: a scene may be one file (:func:`scene_file`).
        colour_matches_depth: colour is taken by the depth's camera at the depth's
            instant (``Scene.colour_matches_depth``; decides ``registration.photometric:
            auto``); a source's ``colour_matches_depth: true|false`` in the config
            overrides it for data that says otherwise (e.g. synthetic data exported in
            ScanNet's layout).
        has_truth: its scenes know the noise-free depth (``Scene.has_clean_depth``:
            synthetic data), which the evaluation scores against; a kind without it is a
            real recording: the workflow builds its scenes the independent references of
            Table 2 (``depthgt.gt.references``) and their RDE GT whatever their split.
    """

    module: str
    options: Mapping[str, OptionCheck] | None
    poses_optional: bool = False
    single_file: bool = False
    colour_matches_depth: bool = False
    has_truth: bool = False

    def __post_init__(self):
        if self.poses_optional and "require_pose" not in (self.options or {}):
            raise ValueError(f"source kind of {self.module}: poses_optional needs the option require_pose")


# The registry: kind -> its entry. Options mirror what each adapter accepts (tests keep
# the names equal to the adapters' signatures); image sizes are bounded so that one
# synthetic frame cannot exhaust memory. Adding a kind = its module + its entry
# (docs/development.md); a kind defined outside depthgt is added by register().
KINDS: dict[str, SourceKind] = {
    "scannet": SourceKind(
        "depthgt.sources.scannet",
        {"depth_scale": _DEPTH_SCALE, "require_pose": _BOOL, "intrinsics": _K_ANY},
        poses_optional=True,
        single_file=True,
    ),  # colour: another camera, calibrated apart
    "sevenscenes": SourceKind(
        "depthgt.sources.sevenscenes",
        {"depth_scale": _DEPTH_SCALE, "require_pose": _BOOL, "intrinsics": _K33},
        poses_optional=True,
    ),  # colour: another camera, not registered to depth
    "tum": SourceKind(
        "depthgt.sources.tum",
        {
            "max_dt": _number(0.0, strict=False),
            "camera": OptionCheck(
                "one of fr1, fr2, fr3, ros_default", lambda v: v in ("fr1", "fr2", "fr3", "ros_default")
            ),
            "intrinsics": _K33,
            "depth_scale": _DEPTH_SCALE,
            "require_pose": _BOOL,
            "undistort": _BOOL,
            "distortion": OptionCheck("5 finite numbers k1, k2, p1, p2, k3", lambda v: _is_seq_of_numbers(v, 5)),
            "interpolate_poses": _BOOL,
        },
        poses_optional=True,
    ),  # colour: 10-20 ms from the depth's instant
    "synthetic": SourceKind(
        "depthgt.sources.synthetic",
        {
            "seed": _int_in(0, 2**63 - 1),
            "n_frames": _int_in(1, 1_000_000),
            "n_scenes": _int_in(1, 1_000_000),
            "width": _int_in(32, 4096),
            "height": _int_in(32, 4096),
            "fx": _OPTIONAL_POSITIVE,
            "fy": _OPTIONAL_POSITIVE,
            "cx": _OPTIONAL_POSITIVE,
            "cy": _OPTIONAL_POSITIVE,
            "noise": _BOOL,
            "rgb_noise": _number(0.0, strict=False),
            "step_mm": _number(0.0, strict=True),
            "sweep_m": _number(0.0, strict=False),
            # names mirror depthgt.synth.noise.SENSOR_PROFILES and synthetic.FAMILIES (a test keeps them equal)
            "sensor": OptionCheck("one of kinect_v1, coarse_stereo", lambda v: v in SYNTHETIC_SENSORS),
            "family": OptionCheck("one of room, varied", lambda v: v in SYNTHETIC_FAMILIES),
            **{
                f"noise_{name}": OptionCheck(
                    "a number >= 0 (or true/false for round_mm)",
                    lambda v: isinstance(v, (bool, np.bool_)) or (_is_number(v) and v >= 0),
                )
                for name in SYNTHETIC_NOISE_FIELDS
            },
        },
        colour_matches_depth=True,
        has_truth=True,
    ),  # rendered from the depth's camera at its instant, with its noise-free depth
}


def register(kind: str, entry: SourceKind) -> None:
    """Add (or replace) a source kind, e.g. an adapter that lives outside depthgt."""
    if not isinstance(entry, SourceKind):
        raise TypeError(f"register({kind!r}, ...): a SourceKind, got {type(entry).__name__}")
    KINDS[kind] = entry


def option_names(kind: str) -> list[str] | None:
    """Sorted names of the options of ``kind``, or None when they are not declared."""
    options = source_kind(kind).options
    return sorted(options) if options is not None else None


def check_options(kind: str, options: Mapping[str, Any] | None, where: str = "options") -> None:
    """Check a source's adapter options without opening any data (numpy only).

    Args:
        kind: the source kind.
        options: the source's ``options`` mapping (None: no options).
        where: how the options are named in errors, e.g. ``"config key sources[syn].options"``.

    Raises:
        ConfigError: unknown kind, options that are not a mapping, an unknown option
            (the message lists the known ones) or an invalid value (the message names
            the key, the value and what is expected).
    """
    try:
        entry = source_kind(kind)
    except SourceError as exc:
        raise ConfigError(f"{where}: {exc}") from exc
    if options is None:
        return
    if not isinstance(options, Mapping):
        raise ConfigError(f"{where}: must be a mapping of option names to values, got {type(options).__name__}")
    spec = entry.options
    if spec is None:
        return
    for key, value in options.items():
        if key not in spec:
            raise ConfigError(f"{where}.{key}: unknown {kind} option; known options: {', '.join(sorted(spec))}")
        if not spec[key].check(value):
            raise ConfigError(f"{where}.{key}: must be {spec[key].expects}, got {value!r}")


# ---------------------------------------------------------------- scene identity

_ROOM = re.compile(r"^room_(\d+)$")


def scene_data_key(kind: str, root: str | Path | None, scene: str, options: Mapping[str, Any] | None = None) -> tuple:
    """What identifies the data of a scene, so that two config entries naming the same
    data can be told apart from two entries naming different data (no data is read).

    * synthetic: the room (``room_NNN``'s number) and the ``seed`` option, which fix
      the room's geometry and textures (other options change the camera path or the
      noise, not the room);
    * file-based kinds: the resolved path of the scene's folder or ``.sens`` file
      (symbolic links and relative roots resolved), whatever the kind, or of ``root``
      itself when it is a sequence named ``"."`` or after its folder.
    """
    options = options or {}
    if kind == "synthetic":
        m = _ROOM.match(str(scene))
        return ("synthetic", options.get("seed", SYNTHETIC_DEFAULT_SEED), int(m.group(1)) if m else str(scene))
    if root is None:
        return (kind, None, str(scene))
    base = Path(root).expanduser().resolve()
    if scene not in (".", ""):
        for candidate in (base / scene, base / f"{scene}.sens"):
            if candidate.exists():
                return ("files", str(candidate.resolve()))
    if scene in (".", "", base.name):
        return ("files", str(base))
    return ("files", str(base / scene))


def check_scene_identity(sources: Sequence[Mapping[str, Any]], scenes: Mapping[str, Sequence[str]]) -> None:
    """Refuse a configuration that would build the same data twice.

    Args:
        sources: the config's source entries (``name``, ``kind``, ``root``, ``split``,
            ``options``).
        scenes: source name -> the scene names it resolves to (after ``scenes: all``).

    Raises:
        ConfigError: listing every problem: a scene listed twice in a source (every row
            of the dataset would be doubled), the same data (:func:`scene_data_key`)
            under two sources (counted twice), and above all the same data in two
            splits (identical GT in train and test).
    """
    problems: list[str] = []
    seen: dict[tuple, tuple[str, str, str]] = {}  # key -> (source name, scene, split)
    for src in sources:
        name, kind, split = src["name"], src["kind"], src.get("split", "auto")
        for scene in scenes.get(name, ()):
            key = scene_data_key(kind, src.get("root"), scene, src.get("options"))
            if key not in seen:
                seen[key] = (name, scene, split)
                continue
            other, other_scene, other_split = seen[key]
            what = f"scene {scene!r}" if other_scene == scene else f"scenes {other_scene!r} and {scene!r}"
            if other == name:
                twice = "is listed twice" if other_scene == scene else "are the same data"
                problems.append(
                    f"sources {name!r}: {what} {twice} ({_describe(key)}); every frame set would be built "
                    f"and counted twice"
                )
            elif other_split != split or "auto" in (split, other_split):
                # ``auto`` splits by blocks drawn per source: the copies land in different splits
                problems.append(
                    f"sources {other!r} (split: {other_split}) and {name!r} (split: {split}) hold the same "
                    f"data, {what} ({_describe(key)}): identical ground truth would end up in two splits"
                )
            else:
                problems.append(
                    f"sources {other!r} and {name!r} (both split: {split}) hold the same data, {what} "
                    f"({_describe(key)}): its frame sets would be counted twice"
                )
    if problems:
        raise ConfigError("config sources: " + "; ".join(problems))


def _describe(key: tuple) -> str:
    if key[0] == "synthetic":
        return f"synthetic room {key[2]} with seed {key[1]}"
    if key[0] == "files":
        return key[1]
    return f"{key[0]} scene {key[2]}"
