"""Seeded fuzzing of the source readers, for the test suite and bench/fuzz_readers.py.

Cases are mutants of valid inputs (a ``.sens`` file; the JPEG colour, PNG colour and
PNG depth files of a 7-Scenes sequence) plus crafted cases (absurd image headers, a
zlib bomb, a lowered frame count, truncated and wrongly typed images, degenerate
poses). Each case opens its scene through :func:`depthgt.sources.base.open_scene` and
reads every frame, as the frame-set batches do. An outcome is one of:

* ``ok``: every frame read and valid;
* ``frame_errors``: some frames raised :class:`~depthgt.errors.FrameError` (a recorded
  skip, counted per reason);
* ``source_error``: the scene raised a project error when opened (the run stops with
  its message);
* ``exception``, ``timeout``, ``worker_died``: anything else: a failure.

Frames are *lost without a recorded reason* when a scene opens with fewer frames than
its input holds and records no problem (``scene.problems``).

Cases run in a worker process (``python tests/fuzz_harness.py --worker ...``) whose
address space is capped (``RLIMIT_AS``: its size after start-up plus ``cap_mib``), so an
allocation beyond the cap fails as ``MemoryError``/``cv2.error`` (an ``exception``
outcome) instead of exhausting the machine; the peak resident memory of each case is
measured by resetting the kernel's high-water mark (``/proc/self/clear_refs``) before it
and reading ``VmHWM`` after it. A worker that dies (a crash in native code) is recorded
as ``worker_died`` for its case and restarted on the next one.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import zlib
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from sens_writer import write_sens  # noqa: E402

N_SENS_FRAMES = 6
N_SEQ_FRAMES = 3
COLOR_HW = (96, 128)
DEPTH_HW = (48, 64)
K_DEPTH = np.array([[58.0, 0.0, 31.5], [0.0, 58.0, 23.5], [0.0, 0.0, 1.0]])
MUTANT_KINDS = ("sens", "jpeg", "png", "depth_png")
_SEQ_TARGET = {"jpeg": "frame-000001.color.jpg", "png": "frame-000001.color.png", "depth_png": "frame-000001.depth.png"}


# ------------------------------------------------------------------ valid inputs


def _colour(k: int) -> np.ndarray:
    """(H, W, 3) uint8: smooth gradients plus texture (JPEG data of realistic density)."""
    h, w = COLOR_HW
    y, x = np.mgrid[0:h, 0:w]
    rng = np.random.default_rng(k)
    tex = rng.integers(0, 40, (h, w, 1))
    img = (
        np.concatenate(
            [
                120 + 80 * np.sin(x / 9 + k)[..., None],
                100 + 60 * np.cos(y / 7)[..., None],
                60 + 0.5 * (x + y)[..., None],
            ],
            axis=2,
        )
        + tex
    )
    return np.clip(img, 0, 255).astype(np.uint8)


def _depth(k: int) -> np.ndarray:
    h, w = DEPTH_HW
    y, x = np.mgrid[0:h, 0:w]
    d = (1500 + 10 * x + 5 * y + 20 * k).astype(np.uint16)
    d[:4, :6] = 0
    return d


def _pose(k: int) -> np.ndarray:
    a = 0.05 * k
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]
    T[:3, 3] = (0.02 * k, 0.1, 1.0)
    return T


def write_base_sens(path: Path, poses: list[np.ndarray] | None = None, **kw) -> Path:
    """A valid 6-frame ``.sens`` (JPEG colour 128x96, zlib depth 64x48, 3 IMU records)."""
    n = N_SENS_FRAMES
    K_color = K_DEPTH * np.array([[2, 1, 2], [1, 2, 2], [1, 1, 1]])
    kw.setdefault("imu_frames", 3)
    return write_sens(
        path,
        [_colour(k) for k in range(n)],
        [_depth(k) for k in range(n)],
        poses or [_pose(k) for k in range(n)],
        K_color,
        K_DEPTH,
        **kw,
    )


def write_base_sequence(folder: Path, color_ext: str) -> Path:
    """A valid 7-Scenes sequence of 3 frames with ``color_ext`` colour."""
    folder.mkdir(parents=True, exist_ok=True)
    for k in range(N_SEQ_FRAMES):
        rgb = cv2.resize(_colour(k), DEPTH_HW[::-1], interpolation=cv2.INTER_AREA)
        assert cv2.imwrite(str(folder / f"frame-{k:06d}.color.{color_ext}"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        assert cv2.imwrite(str(folder / f"frame-{k:06d}.depth.png"), _depth(k))
        np.savetxt(folder / f"frame-{k:06d}.pose.txt", _pose(k))
    np.savetxt(folder / "camera-intrinsics.txt", K_DEPTH)
    return folder


def sens_fields(path: Path) -> list[tuple[int, int]]:
    """(offset, size) of the integer fields of a ``.sens`` file that steer its parsing:
    name length, compressions, sizes, frame count, and each frame's payload sizes."""
    from depthgt.sources.sens import SensFile, read_header

    h = read_header(path)
    name_end = 12 + len(h.sensor_name.encode())
    tail = name_end + 4 * 64
    fields = [(4, 8)] + [(tail + 4 * k, 4) for k in range(8)] + [(tail + 32, 8)]
    sens = SensFile(path)
    for start in (sens.color_offsets - 96).tolist():
        fields += [(start + 64 + 16, 8), (start + 64 + 24, 8), (start + 12 * 4, 4), (start + 15 * 4, 4)]
    return fields


# ------------------------------------------------------------------ mutations

_INTERESTING = (
    0,
    1,
    2,
    0x7F,
    0xFF,
    0x7FFF,
    0xFFFF,
    0x7FFFFFFF,
    0x80000000,
    0xFFFFFFFF,
    1 << 32,
    1 << 62,
    1 << 63,
    (1 << 64) - 1,
)


def mutate(data: bytes, rng: np.random.Generator, fields: list[tuple[int, int]] | None = None) -> bytes:
    """One to three random mutations of ``data``: bit flips, random bytes, an integer
    field set to an edge value, truncation, deletion, duplication or insertion of a
    chunk. ``fields``: (offset, size) of little-endian integer fields to favour."""
    buf = bytearray(data)
    for _ in range(int(rng.integers(1, 4))):
        n = len(buf)
        if n == 0:
            break
        op = int(rng.integers(0, 8))
        # favour the first bytes (headers), where a mutation changes how the rest is read
        pos = int(rng.integers(0, min(n, 512))) if rng.random() < 0.4 else int(rng.integers(0, n))
        if op == 0:
            for _ in range(int(rng.integers(1, 9))):
                p = int(rng.integers(0, n))
                buf[p] ^= 1 << int(rng.integers(0, 8))
        elif op == 1:
            k = int(rng.integers(1, 17))
            buf[pos : pos + k] = rng.integers(0, 256, min(k, n - pos), dtype=np.uint8).tobytes()
        elif op == 2 and fields:
            off, size = fields[int(rng.integers(0, len(fields)))]
            if off + size <= n:
                old = int.from_bytes(buf[off : off + size], "little")
                choices = [*_INTERESTING, old + 1, max(old - 1, 0), old * 2, old // 2, int(rng.integers(0, 1 << 31))]
                value = choices[int(rng.integers(0, len(choices)))] % (1 << (8 * size))
                buf[off : off + size] = value.to_bytes(size, "little")
        elif op == 3:
            del buf[int(rng.integers(0, n)) :]
        elif op == 4:
            del buf[pos : pos + int(rng.integers(1, 257))]
        elif op == 5:
            k = int(rng.integers(1, 257))
            buf[pos:pos] = buf[pos : pos + k]
        elif op == 6:
            buf[pos:pos] = rng.integers(0, 256, int(rng.integers(1, 33)), dtype=np.uint8).tobytes()
        else:
            p = int(rng.integers(0, n))
            buf[p] = int(rng.choice([0x00, 0xFF, 0x7F, 0x80]))
    return bytes(buf)


def fix_png_crcs(data: bytes) -> bytes:
    """Recompute the CRC of every chunk whose length still fits, so that a mutant gets
    past libpng's checksum test into the header fields and the compressed data."""
    buf = bytearray(data)
    pos = 8
    while pos + 12 <= len(buf):
        length = int.from_bytes(buf[pos : pos + 4], "big")
        end = pos + 8 + length
        if end + 4 > len(buf):
            break
        buf[end : end + 4] = zlib.crc32(bytes(buf[pos + 4 : end])).to_bytes(4, "big")
        pos = end + 4
    return bytes(buf)


# ------------------------------------------------------------------ crafted cases


def jpeg_with_size(data: bytes, w: int, h: int) -> bytes:
    """A JPEG whose start-of-frame declares ``w`` x ``h`` (nothing else changed)."""
    buf = bytearray(data)
    m = re.search(rb"\xff[\xc0-\xc2]", bytes(buf))
    assert m is not None, "no SOF marker"
    i = m.start()
    buf[i + 5 : i + 7] = h.to_bytes(2, "big")
    buf[i + 7 : i + 9] = w.to_bytes(2, "big")
    return bytes(buf)


def png_with_size(data: bytes, w: int, h: int) -> bytes:
    """A PNG whose IHDR declares ``w`` x ``h`` (CRC recomputed, so the header is valid)."""
    buf = bytearray(data)
    assert buf[12:16] == b"IHDR"
    buf[16:20] = w.to_bytes(4, "big")
    buf[20:24] = h.to_bytes(4, "big")
    buf[29:33] = zlib.crc32(bytes(buf[12:29])).to_bytes(4, "big")
    return bytes(buf)


def zlib_bomb(n_bytes: int) -> bytes:
    """zlib stream of ``n_bytes`` zeros, compressed chunk by chunk (never held whole)."""
    comp = zlib.compressobj(9)
    chunk = bytes(1 << 20)
    parts = [comp.compress(chunk[: min(len(chunk), n_bytes - k)]) for k in range(0, n_bytes, len(chunk))]
    return b"".join(parts) + comp.flush()


def _encode(img: np.ndarray, ext: str) -> bytes:
    ok, buf = cv2.imencode(ext, img)
    assert ok
    return buf.tobytes()


CRAFTED_SENS = (
    "sens_empty_colour_payload",
    "sens_jpeg_declares_60000x60000",
    "sens_jpeg_declares_40000x26000",
    "sens_jpeg_declares_16000x16000",
    "sens_jpeg_declares_8000x6000",
    "sens_jpeg_declares_256x192",
    "sens_jpeg_truncated_half",
    "sens_png16_colour",
    "sens_rgba_colour",
    "sens_png_truncated_half",
    "sens_tiff_colour",
    "sens_png_in_jpeg_file",
    "sens_grey_colour",
    "sens_lowered_frame_count",
    "sens_frame_count_2^64-1",
    "sens_no_imu_block",
    "sens_garbage_after_frames",
    "sens_colour_size_2^63",
    "sens_name_length_2^60",
    "sens_header_colour_60000x60000",
    "sens_pose_bottom_row_0000",
    "sens_pose_bottom_row_0002",
    "sens_pose_reflection",
    "sens_zlib_bomb",
)


def crafted_sens_kwargs(name: str, param: int = 0) -> dict:
    """Keyword arguments of :func:`write_base_sens` for crafted case ``name`` (a
    ``patch`` entry names an edit of the written file); ``param``: the bomb's size."""
    rgb = _colour(2)
    bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
    jpg = _encode(bgr, ".jpg")

    def colour_of_frame_2(payload: bytes, fmt: str = "jpeg") -> dict:
        ext = {"jpeg": ".jpg", "png": ".png"}[fmt]
        return {
            "color_compression": fmt,
            "color_payloads": [
                payload if k == 2 else _encode(cv2.cvtColor(_colour(k), cv2.COLOR_RGB2BGR), ext)
                for k in range(N_SENS_FRAMES)
            ],
        }

    def pose_of_frame_3(edit) -> dict:
        poses = [_pose(k) for k in range(N_SENS_FRAMES)]
        edit(poses[3])
        return {"poses": poses}

    if name == "sens_zlib_bomb":  # param: inflated size in bytes
        depths = [zlib.compress(_depth(k).astype("<u2").tobytes()) for k in range(N_SENS_FRAMES)]
        depths[1] = zlib_bomb(param)
        return {"depth_payloads": depths}
    m = re.match(r"sens_jpeg_declares_(\d+)x(\d+)$", name)
    if m:
        return colour_of_frame_2(jpeg_with_size(jpg, int(m.group(1)), int(m.group(2))))
    table = {
        "sens_empty_colour_payload": lambda: colour_of_frame_2(b""),
        "sens_jpeg_truncated_half": lambda: colour_of_frame_2(jpg[: len(jpg) // 2]),
        "sens_png16_colour": lambda: colour_of_frame_2(_encode(bgr.astype(np.uint16) * 257, ".png"), "png"),
        "sens_rgba_colour": lambda: colour_of_frame_2(_encode(np.dstack([bgr, bgr[..., :1]]), ".png"), "png"),
        "sens_png_truncated_half": lambda: colour_of_frame_2(_encode(bgr, ".png")[:3000], "png"),
        "sens_tiff_colour": lambda: colour_of_frame_2(_encode(bgr, ".tiff")),
        "sens_png_in_jpeg_file": lambda: colour_of_frame_2(_encode(bgr, ".png")),
        "sens_grey_colour": lambda: colour_of_frame_2(_encode(bgr[..., 0], ".jpg")),  # 8-bit grey: accepted
        "sens_lowered_frame_count": lambda: {"num_frames": N_SENS_FRAMES - 2},
        "sens_frame_count_2^64-1": lambda: {"num_frames": (1 << 64) - 1},
        "sens_no_imu_block": lambda: {"imu_frames": None},
        "sens_garbage_after_frames": lambda: {"patch": "append_garbage"},
        "sens_colour_size_2^63": lambda: {"patch": "colour_size_huge"},
        "sens_name_length_2^60": lambda: {"patch": "name_length_huge"},
        "sens_header_colour_60000x60000": lambda: {"patch": "header_colour_size"},
        "sens_pose_bottom_row_0000": lambda: pose_of_frame_3(lambda T: T.__setitem__(3, (0, 0, 0, 0))),
        "sens_pose_bottom_row_0002": lambda: pose_of_frame_3(lambda T: T.__setitem__(3, (0, 0, 0, 2))),
        "sens_pose_reflection": lambda: pose_of_frame_3(lambda T: T.__setitem__((slice(0, 3), 0), -T[:3, 0])),
    }
    return table[name]()


def _patch_sens(path: Path, how: str) -> None:
    from depthgt.sources.sens import SensFile, read_header

    data = bytearray(path.read_bytes())
    h = read_header(path)
    tail = 12 + len(h.sensor_name.encode()) + 4 * 64
    if how == "append_garbage":
        data += bytes(range(256)) * 3
    elif how == "colour_size_huge":
        start = int(SensFile(path).color_offsets[2]) - 96
        data[start + 80 : start + 88] = (1 << 63).to_bytes(8, "little")
    elif how == "name_length_huge":
        data[4:12] = (1 << 60).to_bytes(8, "little")
    elif how == "header_colour_size":
        data[tail + 8 : tail + 16] = struct.pack("<II", 60000, 60000)
    path.write_bytes(bytes(data))


def crafted_image_cases() -> dict[str, tuple[str, bytes]]:
    """name -> (file of frame 1 of a 7-Scenes sequence it replaces, its bytes)."""
    rgb = cv2.resize(_colour(1), DEPTH_HW[::-1], interpolation=cv2.INTER_AREA)
    bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
    jpg, png, dpng = _encode(bgr, ".jpg"), _encode(bgr, ".png"), _encode(_depth(1), ".png")
    return {
        "jpeg_declares_60000x60000": ("jpeg", jpeg_with_size(jpg, 60000, 60000)),
        "jpeg_declares_40000x26000": ("jpeg", jpeg_with_size(jpg, 40000, 26000)),
        "jpeg_declares_16000x16000": ("jpeg", jpeg_with_size(jpg, 16000, 16000)),
        "jpeg_declares_8000x6000": ("jpeg", jpeg_with_size(jpg, 8000, 6000)),
        "jpeg_truncated_half": ("jpeg", jpg[: len(jpg) // 2]),
        "jpeg_empty_file": ("jpeg", b""),
        "png_declares_60000x60000": ("png", png_with_size(png, 60000, 60000)),
        "png_truncated_half": ("png", png[: len(png) // 2]),
        "png16_colour": ("png", _encode(bgr.astype(np.uint16) * 257, ".png")),
        "rgba_colour": ("png", _encode(np.dstack([bgr, bgr[..., :1]]), ".png")),
        "tiff_colour_named_png": ("png", _encode(bgr, ".tiff")),
        "depth_png_declares_60000x60000": ("depth_png", png_with_size(dpng, 60000, 60000)),
        "depth_png_declares_16000x16000": ("depth_png", png_with_size(dpng, 16000, 16000)),
        "depth_png_truncated_half": ("depth_png", dpng[: len(dpng) // 2]),
        "depth_png_8bit": ("depth_png", _encode(_depth(1).astype(np.uint8), ".png")),
        "depth_png_other_size": (
            "depth_png",
            _encode(cv2.resize(_depth(1), (32, 24), interpolation=cv2.INTER_NEAREST), ".png"),
        ),
        "depth_jpeg_named_png": ("depth_png", jpg),
    }


# ------------------------------------------------------------------ one case


@dataclass(frozen=True)
class Case:
    """``kind``: a mutant kind (:data:`MUTANT_KINDS`) with ``index``; ``"crafted"`` with
    ``name`` (and ``param``, the inflated size of a zlib bomb); ``"control"``: allocate
    ``param`` bytes (checks that the memory cap works)."""

    kind: str
    index: int = 0
    name: str = ""
    seed: int = 0
    param: int = 0

    @property
    def label(self) -> str:
        if self.kind == "control":
            return self.name
        if self.kind != "crafted":
            return f"{self.kind}#{self.index}"
        return f"{self.name}_{self.param >> 20}MiB" if self.param else self.name


def _materialise(case: Case, base: Path, work: Path) -> tuple[str, Path, str, int]:
    """Write the case's input under ``work``; (source kind, root, scene, frames it holds)."""
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    if case.kind == "sens" or (case.kind == "crafted" and case.name.startswith("sens_")):
        target = work / "scene.sens"
        if case.kind == "sens":
            rng = np.random.default_rng([case.seed, 0, case.index])
            fields = json.loads((base / "sens_fields.json").read_text())
            target.write_bytes(mutate((base / "base.sens").read_bytes(), rng, [tuple(f) for f in fields]))
        else:
            kw = crafted_sens_kwargs(case.name, case.param)
            patch = kw.pop("patch", None)
            write_base_sens(target, **kw)
            if patch:
                _patch_sens(target, patch)
        return "scannet", work, "scene", N_SENS_FRAMES
    which, data = None, None
    if case.kind == "crafted":
        which, data = crafted_image_cases()[case.name]
    else:
        which = case.kind
        rng = np.random.default_rng([case.seed, 1 + MUTANT_KINDS.index(which), case.index])
        data = mutate((base / f"seq_{'png' if which == 'png' else 'jpg'}" / _SEQ_TARGET[which]).read_bytes(), rng)
        if which != "jpeg" and rng.random() < 0.5:
            data = fix_png_crcs(data)
    seq = work / "seq"
    shutil.copytree(base / f"seq_{'png' if which == 'png' else 'jpg'}", seq)
    (seq / _SEQ_TARGET[which]).write_bytes(data)
    return "sevenscenes", seq, ".", N_SEQ_FRAMES


class _Timeout(Exception):
    pass


def _alarm(signum, frame):
    raise _Timeout()


def _status_kib(key: str) -> int:
    m = re.search(rf"^{key}:\s+(\d+) kB", Path("/proc/self/status").read_text(), re.M)
    return int(m.group(1)) if m else 0


def _reset_peak() -> bool:
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def run_case(case: Case, base: Path, work: Path, timeout_s: int = 30) -> dict:
    """Open the case's scene and read every frame; the outcome record (module docstring)."""
    from depthgt.errors import DepthGTError, FrameError
    from depthgt.sources.base import check_frame, open_scene

    out = {
        "case": case.label,
        "kind": case.kind,
        "frames_ok": 0,
        "frame_errors": {},
        "outcome": "ok",
        "message": "",
        "lost_unrecorded": 0,
        "problems": 0,
    }
    if case.kind == "control":  # checks the harness itself: an allocation beyond the cap must fail
        kind, root, name, n_true = "control", None, case.name, 0
    else:
        kind, root, name, n_true = _materialise(case, base, work)
    resettable = _reset_peak()
    rss0 = _status_kib("VmRSS")
    signal.signal(signal.SIGALRM, _alarm)
    signal.alarm(timeout_s)
    errors: Counter[str] = Counter()
    try:
        try:
            if kind == "control":
                np.ones(case.param, dtype=np.uint8)
            scene = open_scene(kind, root, name)
        except DepthGTError as exc:
            out.update(outcome="source_error", message=str(exc)[:300])
        else:
            for i in range(len(scene)):
                try:
                    check_frame(scene.read(i), scene.image_size, f"{case.label} frame {i}", need_pose=True)
                    out["frames_ok"] += 1
                except FrameError as exc:
                    errors[exc.reason] += 1
                    out["message"] = out["message"] or str(exc)[:300]
            problems = list(getattr(scene, "problems", []))
            out["problems"] = len(problems)
            lost = n_true - len(scene)
            out["lost_unrecorded"] = max(0, lost) if not problems else 0
            if errors:
                out["outcome"] = "frame_errors"
            if problems and not out["message"]:
                out["message"] = problems[0][:300]
    except _Timeout:
        out.update(outcome="timeout", message=f"no result within {timeout_s} s")
    except Exception as exc:  # the point of the harness: anything that is not a project error
        out.update(outcome="exception", message=f"{type(exc).__module__}.{type(exc).__name__}: {str(exc)[:300]}")
    finally:
        signal.alarm(0)
    out["frame_errors"] = dict(errors)
    out["peak_mib"] = round(max(0, _status_kib("VmHWM") - rss0) / 1024, 2) if resettable else None
    return out


# ------------------------------------------------------------------ worker and driver


def prepare_base(base: Path) -> None:
    """The valid inputs the mutants derive from."""
    base.mkdir(parents=True, exist_ok=True)
    write_base_sens(base / "base.sens")
    (base / "sens_fields.json").write_text(json.dumps(sens_fields(base / "base.sens")))
    write_base_sequence(base / "seq_jpg", "jpg")
    write_base_sequence(base / "seq_png", "png")


def _worker(args) -> None:
    cv2.setNumThreads(1)
    base, work = Path(args.base), Path(args.work)
    cases = [Case(**c) for c in json.loads(Path(args.cases).read_text())][args.start :]
    limit = _status_kib("VmSize") * 1024 + args.cap_mib * (1 << 20)
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    with open(args.out, "a", encoding="utf-8") as out:
        for case in cases:
            out.write(json.dumps(run_case(case, base, work, args.timeout)) + "\n")
            out.flush()


def run_fuzz(cases: list[Case], cap_mib: int = 512, timeout_s: int = 30, tmp: Path | None = None) -> list[dict]:
    """Run ``cases`` in capped worker processes; one outcome record per case, in order."""
    own = tmp is None
    tmp = Path(tempfile.mkdtemp(prefix="fuzz_")) if own else tmp
    try:
        prepare_base(tmp / "base")
        (tmp / "cases.json").write_text(json.dumps([c.__dict__ for c in cases]))
        results_path = tmp / "results.jsonl"
        results_path.write_text("")
        env = dict(os.environ, MALLOC_ARENA_MAX="2", OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
        done = 0
        while done < len(cases):
            cmd = [
                sys.executable,
                str(Path(__file__).resolve()),
                "--worker",
                "--base",
                str(tmp / "base"),
                "--work",
                str(tmp / "work"),
                "--cases",
                str(tmp / "cases.json"),
                "--start",
                str(done),
                "--out",
                str(results_path),
                "--cap-mib",
                str(cap_mib),
                "--timeout",
                str(timeout_s),
            ]
            proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
            lines = results_path.read_text().splitlines()
            done = len(lines)
            if done < len(cases) and proc.returncode != 0:
                rec = {
                    "case": cases[done].label,
                    "kind": cases[done].kind,
                    "outcome": "worker_died",
                    "message": f"exit {proc.returncode}: {proc.stderr[-300:]}",
                    "frames_ok": 0,
                    "frame_errors": {},
                    "lost_unrecorded": 0,
                    "problems": 0,
                    "peak_mib": None,
                }
                with results_path.open("a") as f:
                    f.write(json.dumps(rec) + "\n")
                done += 1
            elif done < len(cases):
                raise RuntimeError(f"fuzz worker stopped after {done} of {len(cases)} cases: {proc.stderr[-2000:]}")
        return [json.loads(line) for line in results_path.read_text().splitlines()]
    finally:
        if own:
            shutil.rmtree(tmp, ignore_errors=True)


def summarise(records: list[dict]) -> dict:
    """Outcome counts, frame-error reasons, failures, peak memory and unrecorded losses."""
    peaks = [r["peak_mib"] for r in records if r.get("peak_mib") is not None]
    worst = max(records, key=lambda r: r.get("peak_mib") or 0.0) if records else None
    return {
        "cases": len(records),
        "outcomes": dict(Counter(r["outcome"] for r in records)),
        "frame_error_reasons": dict(sum((Counter(r["frame_errors"]) for r in records), Counter())),
        "failures": [r for r in records if r["outcome"] in ("exception", "timeout", "worker_died")],
        "peak_mib_max": max(peaks) if peaks else None,
        "peak_case": worst["case"] if worst else None,
        "cases_over_512_mib": sum(p > 512 for p in peaks),
        "frames_lost_unrecorded": sum(r["lost_unrecorded"] for r in records),
        "cases_with_recorded_problems": sum(r["problems"] > 0 for r in records),
    }


def mutant_cases(counts: dict[str, int], seed: int) -> list[Case]:
    return [Case(kind, index=i, seed=seed) for kind, n in counts.items() for i in range(n)]


def crafted_cases(bomb_bytes: tuple[int, ...]) -> list[Case]:
    """Every crafted case; one zlib bomb per size in ``bomb_bytes``."""
    cases = [Case("crafted", name=n) for n in CRAFTED_SENS if n != "sens_zlib_bomb"]
    cases += [Case("crafted", name="sens_zlib_bomb", param=n) for n in bomb_bytes]
    return cases + [Case("crafted", name=n) for n in crafted_image_cases()]


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--worker", action="store_true")
    ap.add_argument("--base")
    ap.add_argument("--work")
    ap.add_argument("--cases")
    ap.add_argument("--start", type=int, default=0)
    ap.add_argument("--out")
    ap.add_argument("--cap-mib", type=int, default=512)
    ap.add_argument("--timeout", type=int, default=30)
    _args = ap.parse_args()
    if not _args.worker:
        ap.error("run through run_fuzz() or bench/fuzz_readers.py")
    _worker(_args)
