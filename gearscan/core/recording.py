"""The recording format: a folder anyone can read without gearscan.

::

    recording.json        format, version, rig calibration, gear spec, pattern set, camera settings
    frames/000000.png     lossless 8- or 16-bit image as captured
    frames.jsonl          one JSON line per frame (id, timestamps, pattern index, encoder angle, exposure)
    encoder.jsonl         raw encoder samples, one JSON line each
    truth/000000.npz      twin recordings only: phase (wrapped, at that frame's pose), mask, points, ...

Writes are append-only and flushed per frame; the PNG is renamed into place before its line is
appended, so every listed frame exists. A recording cut off mid-write (SIGKILL, cable pulled)
replays up to its last complete line; it may leave a ``frames/NNNNNN.tmp.png`` that no line
names: not data, ignored by the reader and listed by ``gearscan check`` as safe to delete.
A write that fails (disk full, file size limit, I/O error) stops the writer with a
:class:`RecordingError` naming the cause; it cuts the index files back to the last complete
frame, removes the half-written file and, where the disk still takes the small header, marks
the recording finished with ``stopped`` saying why: it replays up to its last complete frame.
Angles are stored in radians (``*_rad`` keys), times in nanoseconds (``*_ns``).

``recording.json`` also says what every frame is (``frame_format``: dtype, width, height, bit
depth, set by the first frame) and how the camera's frame counter wraps (``camera.frame_ids``:
modulus and whether 0 is skipped; inferred from the ids when absent).

Damage is skipped, not fatal: a line that is not JSON, lacks a key or has an unknown one, or
has a field out of range (ids and times are non-negative integers, angles finite and within
``MAX_ANGLE_RAD``, NaN and infinity refused); a line out of place (a recording holds whole
bursts: line n has pattern ``(n-1) % len(patterns)``, ids increase, by one within a burst); a
finished recording whose index files hold another number of lines than ``recording.json``'s
``frame_count`` / ``encoder_count`` (lines lost or added); a frame file that is missing,
outside the folder, truncated, fails its CRC or has another format than the recording's. Each
is reported once as a :class:`Damage` naming file and line, and the rest of the recording is
read. Only a damaged ``recording.json`` is an error. What no reader can see is a number changed
into another valid one (a calibration digit, an angle): the format has no checksum.
"""

from __future__ import annotations

import datetime as _dt
import errno
import json
import logging
import math
import os
import shutil
import struct
import threading
import warnings
import zipfile
import zlib
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn, TypeVar

import cv2
import numpy as np

from gearscan.core.frame_ids import FrameIdUnwrapper, FrameIdWrap
from gearscan.core.patterns import BURST_ORDERS, next_offsets
from gearscan.core.types import (
    ENCODER_COUNT_MAX,
    ENCODER_SEQ_MODULUS,
    ENCODER_TIME_US_MAX,
    EncoderSample,
    Frame,
)

log = logging.getLogger(__name__)
_T = TypeVar("_T")

FORMAT = "gearscan-recording"
VERSION = 1

#: What a reader can find damaged (:class:`Damage.kind`).
DAMAGE_KINDS = (
    "index_line",  # frames.jsonl line that is not valid JSON or has a field out of range
    "encoder_line",  # encoder.jsonl line likewise
    "missing_frame",  # frames.jsonl lists a file that is not there
    "path_escape",  # frames.jsonl lists a file outside the recording folder
    "unreadable_frame",  # the PNG is truncated, fails its CRC or does not decode
    "frame_format",  # dtype, bit depth, channels or size differ from the recording's
    "header",  # a section of recording.json (rig, patterns, gear) is invalid (found by check)
)

_INT63 = (1 << 63) - 1
#: Largest |encoder angle| a frame may carry: float64 still resolves 0.1 urad there (1.6e8 turns).
MAX_ANGLE_RAD = 1e9
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


class RecordingError(RuntimeError):
    """A recording folder is missing, damaged or written twice."""


@dataclass(frozen=True, slots=True)
class Damage:
    """One damaged piece of a recording: ``file`` (relative to the recording), 1-based ``line``
    of the index that names it (None for a whole file), ``kind`` (:data:`DAMAGE_KINDS`) and what
    was found against what was expected."""

    kind: str
    file: str
    line: int | None
    what: str

    def __str__(self) -> str:
        where = self.file if self.line is None else f"{self.file}:{self.line}"
        return f"{where}: {self.what}"

    def to_json(self) -> dict[str, Any]:
        return {"kind": self.kind, "file": self.file, "line": self.line, "what": self.what}


class FrameDamaged(RecordingError):
    """A listed frame cannot be used; ``damage`` says where and why. Replay skips the frame."""

    def __init__(self, damage: Damage) -> None:
        super().__init__(str(damage))
        self.damage = damage


@dataclass(frozen=True, slots=True)
class FrameFormat:
    """What every frame of one recording is: dtype, size and significant bits."""

    dtype: str  # "uint8" or "uint16"
    width: int
    height: int
    bit_depth: int

    @classmethod
    def of(cls, image: np.ndarray, bit_depth: int) -> FrameFormat:
        return cls(str(image.dtype), int(image.shape[1]), int(image.shape[0]), int(bit_depth))

    def describe(self) -> str:
        return f"{self.width}x{self.height} {self.dtype} ({self.bit_depth}-bit)"

    def to_json(self) -> dict[str, Any]:
        return {"dtype": self.dtype, "width": self.width, "height": self.height, "bit_depth": self.bit_depth}

    @classmethod
    def from_json(cls, d: Any) -> FrameFormat:
        if not isinstance(d, dict):
            raise ValueError(f"expected {{dtype, width, height, bit_depth}}, got {d!r:.80}")
        dtype = d.get("dtype")
        if dtype not in ("uint8", "uint16"):
            raise ValueError(f"dtype must be 'uint8' or 'uint16', got {dtype!r:.40}")
        return cls(dtype, _int_field(d, "width", 1, 1 << 16), _int_field(d, "height", 1, 1 << 16),
                   _int_field(d, "bit_depth", 1, 16))


def _int_field(d: dict[str, Any], key: str, lo: int, hi: int, default: int | None = None) -> int:
    """``d[key]`` as an int in ``[lo, hi]``; ValueError naming the key, the range and the value."""
    if key not in d and default is not None:
        return default
    v = d.get(key)
    if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
        raise ValueError(f"{key}: expected an integer in [{lo}, {hi}], got {v!r:.40}")
    return v


def _float_field(d: dict[str, Any], key: str, lo: float, hi: float, default: float | None = None) -> float:
    """``d[key]`` as a finite number in ``[lo, hi]`` (NaN, infinities and strings are refused)."""
    if key not in d and default is not None:
        return default
    v = d.get(key)
    if isinstance(v, bool) or not isinstance(v, int | float) or not (lo <= v <= hi) or not math.isfinite(v):
        raise ValueError(f"{key}: expected a finite number in [{lo:g}, {hi:g}], got {v!r:.40}")
    return float(v)


_FRAME_KEYS = ("id", "timestamp_ns", "host_timestamp_ns", "pattern_index", "encoder_angle_rad", "exposure_us",
               "bit_depth", "file")
_ENCODER_KEYS = ("seq", "device_time_us", "count", "index", "angle_rad", "host_time_ns")


def _check_keys(d: Any, known: tuple[str, ...], required: tuple[str, ...]) -> None:
    """A line is an object with the writer's keys: a missing or unknown key means a damaged name."""
    if not isinstance(d, dict):
        raise ValueError(f"expected a JSON object, got {type(d).__name__}")
    missing = [k for k in required if k not in d]
    unknown = [k for k in d if k not in known]
    if missing or unknown:
        raise ValueError(f"keys: missing {missing}, unknown {[k[:40] for k in unknown]} (expected {list(known)})")


def _is_count(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v >= 0


def _atomic_write_text(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w") as fh:
        fh.write(text)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


@dataclass(frozen=True, slots=True)
class FrameRecord:
    """One line of ``frames.jsonl``."""

    frame_id: int
    timestamp_ns: int
    pattern_index: int
    exposure_us: float
    bit_depth: int
    encoder_angle: float | None
    host_timestamp_ns: int
    file: str

    def to_json(self) -> dict[str, Any]:
        return {
            "id": self.frame_id,
            "timestamp_ns": self.timestamp_ns,
            "host_timestamp_ns": self.host_timestamp_ns,
            "pattern_index": self.pattern_index,
            "encoder_angle_rad": self.encoder_angle,
            "exposure_us": self.exposure_us,
            "bit_depth": self.bit_depth,
            "file": self.file,
        }

    @classmethod
    def from_json(cls, d: Any) -> FrameRecord:
        """Parse and range-check one line; ValueError names the field, its range and the value."""
        _check_keys(d, _FRAME_KEYS, required=("id", "timestamp_ns", "pattern_index", "encoder_angle_rad", "file"))
        angle = d.get("encoder_angle_rad")
        file = d.get("file")
        if not isinstance(file, str) or not file:
            raise ValueError(f"file: expected a relative path, got {file!r:.60}")
        return cls(
            frame_id=_int_field(d, "id", 0, (1 << 64) - 1),
            timestamp_ns=_int_field(d, "timestamp_ns", 0, _INT63),
            pattern_index=_int_field(d, "pattern_index", 0, 255),
            exposure_us=_float_field(d, "exposure_us", 0.0, 1e9, default=0.0),
            bit_depth=_int_field(d, "bit_depth", 1, 16, default=8),
            encoder_angle=None if angle is None else _float_field(d, "encoder_angle_rad", -MAX_ANGLE_RAD, MAX_ANGLE_RAD),
            host_timestamp_ns=_int_field(d, "host_timestamp_ns", 0, _INT63, default=0),
            file=file,
        )


def encoder_sample_from_json(d: Any) -> EncoderSample:
    """Parse and range-check one ``encoder.jsonl`` line (ranges of :class:`EncoderSample`)."""
    _check_keys(d, _ENCODER_KEYS, required=_ENCODER_KEYS[:5])
    index = d.get("index")
    if not isinstance(index, bool):
        raise ValueError(f"index: expected true or false, got {index!r:.40}")
    return EncoderSample(
        seq=_int_field(d, "seq", 0, ENCODER_SEQ_MODULUS - 1),
        device_time_us=_int_field(d, "device_time_us", 0, ENCODER_TIME_US_MAX),
        count=_int_field(d, "count", -ENCODER_COUNT_MAX, ENCODER_COUNT_MAX),
        index=index,
        angle=_float_field(d, "angle_rad", -math.inf, math.inf),
        host_time_ns=_int_field(d, "host_time_ns", 0, _INT63, default=0),
    )


def png_format(data: bytes) -> tuple[FrameFormat | None, str]:
    """Check a PNG's structure without decoding its pixels: signature, every chunk's length and
    CRC, IHDR first and IEND last. Returns the format its IHDR declares (grey images only) and
    ``""``, or ``(None, what is wrong)``."""
    if data[:8] != _PNG_SIGNATURE:
        return None, "not a PNG file (signature missing)" if data else "empty file"
    pos, header = 8, None
    while True:
        if pos + 12 > len(data):
            return None, f"PNG truncated at byte {len(data)} (no IEND chunk)"
        length, ctype = struct.unpack_from(">I4s", data, pos)
        end = pos + 8 + length
        if end + 4 > len(data):
            return None, f"PNG truncated at byte {len(data)} inside chunk {ctype!r} starting at byte {pos}"
        if zlib.crc32(memoryview(data)[pos + 4:end]) != struct.unpack_from(">I", data, end)[0]:
            return None, f"PNG chunk {ctype!r} at byte {pos}: CRC mismatch (bytes changed)"
        if header is None:
            if ctype != b"IHDR" or length != 13:
                return None, "PNG does not start with its IHDR chunk"
            width, height, bits, color = struct.unpack_from(">IIBB", data, pos + 8)
            header = (width, height, bits, color)
        if ctype == b"IEND":
            break
        pos = end + 4
    width, height, bits, color = header
    if color != 0 or bits not in (8, 16):
        return None, f"PNG is colour type {color} with {bits}-bit samples, expected 8- or 16-bit grey"
    return FrameFormat("uint8" if bits == 8 else "uint16", width, height, bits), ""


def _line_damage_kind(name: str) -> str:
    """The damage kind of a bad line in index file ``name``."""
    return "encoder_line" if name == "encoder.jsonl" else "index_line"


def _jsonl_lines(path: Path) -> Iterator[tuple[int, Any]]:
    """``(line number, parsed JSON or Damage)`` for each complete line of a JSONL file.

    Invalid UTF-8, invalid JSON, nesting too deep to parse and an unreadable file are
    :class:`Damage`; a cut-off last line (an interrupted write) is skipped with a warning.
    """
    if not path.exists():
        return
    kind = _line_damage_kind(path.name)
    n = 0
    try:
        with open(path, "rb") as fh:
            for raw in fh:
                n += 1
                if not raw.endswith(b"\n"):
                    if raw.strip():
                        warnings.warn(f"{path}:{n}: incomplete last line ignored (recording was interrupted)",
                                      stacklevel=4)
                    return
                if not raw.strip():
                    continue
                try:
                    value = json.loads(raw.rstrip(b"\r\n"))
                except (ValueError, RecursionError) as exc:  # JSONDecodeError, UnicodeDecodeError are ValueErrors
                    if (merged := _split_objects(raw)) is not None:  # a lost newline: each record kept, in order
                        log.warning("%s:%d: %d records on one line (a newline was lost): read apart", path, n,
                                    len(merged))
                        for value in merged:
                            yield n, value
                        continue
                    what = exc.msg if isinstance(exc, json.JSONDecodeError) else type(exc).__name__
                    value = Damage(kind, path.name, n, f"not a JSON line ({what}): {raw.rstrip()[:60]!r}")
                yield n, value
    except OSError as exc:  # a directory in its place, no permission, an I/O error
        yield n + 1, Damage(kind, path.name, n + 1 if n else None, f"cannot read past here ({exc.strerror or exc})")


def _split_objects(raw: bytes) -> list[dict] | None:
    """The JSON objects of one line that holds several back to back (``{...} {...}``: a newline lost or turned into
    another byte), or None where the line is not exactly that."""
    try:
        text = raw.decode("utf-8", errors="surrogateescape").strip()  # the lost newline may be any byte
        decoder, i, out = json.JSONDecoder(), 0, []
        while i < len(text):
            obj, i = decoder.raw_decode(text, i)
            if not isinstance(obj, dict):
                return None
            out.append(obj)
            gap = text.find("{", i) if i < len(text) else len(text)
            if gap < 0 or gap - i > 4:  # a newline turned into a few other bytes at most: else not two records
                return None
            i = gap
    except (ValueError, RecursionError):
        return None
    return out if len(out) > 1 else None


class RecordingWriter:
    """Appends frames, truth and encoder samples to a recording folder.

    Use as a context manager; ``close`` marks the recording finished. ``durable=True``
    fsyncs every frame (survives power loss, costs a few ms per frame).
    """

    @staticmethod
    def check_target(path: str | Path, overwrite: bool = False) -> None:
        """Raise :class:`RecordingError` if ``path`` already holds a recording, or what is left of one (its index, its
        encoder log, a frame the writer would overwrite: a recording whose header was lost), and ``overwrite`` is
        off; or if ``path`` cannot hold one (a file, a folder that cannot be made)."""
        path = Path(path)
        if path.exists() and not path.is_dir():
            raise RecordingError(f"{path}: not a folder (a recording is written into a folder)")
        if overwrite:
            return
        if (path / "recording.json").exists():
            raise RecordingError(f"{path} already holds a recording (--overwrite replaces it)")
        left = RecordingWriter.remains(path)
        if left:
            raise RecordingError(f"{path} holds part of a recording without its recording.json ({', '.join(left)}): "
                                 "writing there would mix the two; choose another folder, or --overwrite to replace it")

    @staticmethod
    def remains(path: Path) -> list[str]:
        """The pieces of a recording in ``path`` (its header, index, encoder log, a frame the writer would name): what
        ``overwrite`` replaces and what, without it, refuses the folder."""
        return [n for n in ("recording.json", "frames.jsonl", "encoder.jsonl", "frames/000000.png")
                if (Path(path) / n).exists()]

    @staticmethod
    def remove(path: Path) -> None:
        """Delete the recording in ``path`` whole; files that are not part of it are kept.

        The header goes first and ``frames.jsonl`` last, so a crash midway leaves no recording
        (rather than one mixing old and new parts) that is still recognised as one to remove.
        """
        (path / "recording.json").unlink(missing_ok=True)
        for name in ("frames", "truth"):
            if (path / name).is_dir() and not (path / name).is_symlink():
                shutil.rmtree(path / name)
            else:
                (path / name).unlink(missing_ok=True)
        for name in ("encoder.jsonl", "recording.json.tmp", "frames.jsonl"):
            (path / name).unlink(missing_ok=True)

    def __init__(self, path: str | Path, meta: dict[str, Any], *, overwrite: bool = False, durable: bool = False):
        self.path = Path(path)
        self.check_target(self.path, overwrite)
        self.meta = {
            "format": FORMAT,
            "version": VERSION,
            "created": _dt.datetime.now(_dt.UTC).isoformat(),
            "finished": False,
            "frame_count": 0,
            **meta,
        }
        try:  # a folder that cannot be made or written (a read-only disk, /proc): said before any frame is taken
            # an old truth/ or frame left behind would be read as part of the new recording: with overwrite the old
            # recording goes whole, or what is left of one; a folder holding none of it (other files) is not emptied
            if overwrite and self.remains(self.path):
                self.remove(self.path)
            (self.path / "frames").mkdir(parents=True, exist_ok=True)
            _atomic_write_text(self.path / "recording.json", json.dumps(self.meta, indent=2))
            self._frames = open(self.path / "frames.jsonl", "a")
            self._encoder = open(self.path / "encoder.jsonl", "a")
        except OSError as exc:
            raise RecordingError(f"{self.path}: cannot write a recording there ({exc.strerror or exc})") from exc
        self._durable = durable
        self.frame_count = 0
        self.encoder_count = 0
        self.format: FrameFormat | None = None
        #: why writing stopped (a failed write), None while it works
        self.stopped: str | None = None
        # bytes of each index file and encoder lines known to be on disk (after the last good flush)
        self._frames_end = (self.path / "frames.jsonl").stat().st_size
        self._encoder_end = (self.path / "encoder.jsonl").stat().st_size
        self._encoder_written = self._encoder_end  # bytes handed to the encoder file so far
        self._encoder_flushed_count = 0

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def write_frame(self, frame: Frame, truth: dict[str, np.ndarray] | None = None) -> FrameRecord:
        """Write the image (and truth), then append its line; flushed before returning.

        Every frame must have the first frame's dtype, size and bit depth (stored in
        ``recording.json`` as ``frame_format``, against which readers check each frame)."""
        fmt = FrameFormat.of(frame.image, frame.bit_depth) if frame.image.ndim == 2 else None
        if fmt is None or fmt.dtype not in ("uint8", "uint16"):
            raise RecordingError(f"{self.path}: frame {frame.frame_id}: expected an (H, W) uint8 or uint16 image, "
                                 f"got {frame.image.dtype} of shape {frame.image.shape}")
        first = self.format is None
        if first:
            self.format = fmt
        elif fmt != self.format:
            raise RecordingError(f"{self.path}: frame {frame.frame_id} is {fmt.describe()}, the recording holds "
                                 f"{self.format.describe()}")
        if self.stopped is not None:
            raise RecordingError(f"{self.path}: writing stopped earlier ({self.stopped})")
        name = f"{self.frame_count:06d}"
        rel = f"frames/{name}.png"
        ok, png = cv2.imencode(".png", frame.image)
        if not ok:
            raise RecordingError(f"could not encode frame {frame.frame_id} as PNG (dtype {frame.image.dtype}, "
                                 f"shape {frame.image.shape})")
        try:
            if first:
                self.update_meta(frame_format=fmt.to_json())
            self._write_file(self.path / rel, png.tobytes())
            if truth is not None:
                (self.path / "truth").mkdir(exist_ok=True)
                tmp_t = self.path / "truth" / f"{name}.tmp.npz"
                np.savez_compressed(tmp_t, **truth)
                os.replace(tmp_t, self.path / "truth" / f"{name}.npz")
            rec = self._append_line(frame, rel)
        except OSError as exc:
            self._stop_writing(exc, f"frame {self.frame_count} ({rel})")
        self.frame_count += 1
        return rec

    def _write_file(self, path: Path, data: bytes) -> None:
        """``data`` into ``path`` through a temporary name, so a listed file is always whole."""
        tmp = path.with_name(path.stem + ".tmp" + path.suffix)
        with open(tmp, "wb") as fh:
            fh.write(data)
            if self._durable:
                fh.flush()
                os.fsync(fh.fileno())
        os.replace(tmp, path)

    def _append_line(self, frame: Frame, rel: str) -> FrameRecord:
        rec = FrameRecord(
            frame_id=frame.frame_id,
            timestamp_ns=frame.timestamp_ns,
            pattern_index=frame.pattern_index,
            exposure_us=frame.exposure_us,
            bit_depth=frame.bit_depth,
            encoder_angle=frame.encoder_angle,
            host_timestamp_ns=frame.host_timestamp_ns,
            file=rel,
        )
        line = json.dumps(rec.to_json()) + "\n"  # ASCII: characters are bytes
        self._frames.write(line)
        self._frames.flush()
        self._encoder.flush()
        if self._durable:
            os.fsync(self._frames.fileno())
        self._frames_end += len(line)
        self._encoder_end, self._encoder_flushed_count = self._encoder_written, self.encoder_count
        return rec

    def _stop_writing(self, exc: OSError, what: str) -> NoReturn:
        """A write failed: cut the index files back to what is whole on disk, remove temporary
        files, mark the recording finished if the disk still takes its header, and raise."""
        cause = {errno.ENOSPC: "disk full", errno.EFBIG: "file size limit reached",
                 errno.EDQUOT: "disk quota exceeded"}.get(exc.errno or 0, exc.strerror or type(exc).__name__)
        self.stopped = f"{cause} ({exc.strerror or exc}) while writing {what}"
        for fh in (self._frames, self._encoder):
            try:
                fh.close()  # may fail again flushing what is buffered: cut below
            except OSError:
                pass
        for name, end in (("frames.jsonl", self._frames_end), ("encoder.jsonl", self._encoder_end)):
            try:
                os.truncate(self.path / name, end)
            except OSError:
                pass
        for sub in ("frames", "truth"):
            for tmp in (self.path / sub).glob("*.tmp.*") if (self.path / sub).is_dir() else ():
                tmp.unlink(missing_ok=True)
        self.encoder_count = self._encoder_flushed_count
        try:
            self.update_meta(finished=True, frame_count=self.frame_count, encoder_count=self.encoder_count,
                             stopped=self.stopped)
        except OSError:  # not even the header fits: it stays unfinished, which replays the same way
            (self.path / "recording.json.tmp").unlink(missing_ok=True)
        raise RecordingError(
            f"{self.path}: recording stopped: {self.stopped}. It holds {self.frame_count} complete frames and "
            f"replays up to the last of them; free space (or raise the limit) before recording again"
        ) from exc

    def write_encoder(self, sample: EncoderSample) -> None:
        """Append one raw encoder sample (flushed with the next frame)."""
        if self.stopped is not None:
            return  # the frame that failed raised already; its samples have no frame to go with
        self.encoder_count += 1
        line = json.dumps(
            {
                "seq": sample.seq,
                "device_time_us": sample.device_time_us,
                "count": sample.count,
                "index": sample.index,
                "angle_rad": sample.angle,
                "host_time_ns": sample.host_time_ns,
            }
        ) + "\n"
        self._encoder_written += len(line)
        try:
            self._encoder.write(line)
        except OSError as exc:
            self._stop_writing(exc, "encoder.jsonl")

    def update_meta(self, **fields: Any) -> None:
        """Atomically rewrite ``recording.json`` with extra fields (after a stopped write: if the
        disk takes it, else the header stays as the stop left it)."""
        self.meta.update(fields)
        try:
            _atomic_write_text(self.path / "recording.json", json.dumps(self.meta, indent=2))
        except OSError:
            (self.path / "recording.json.tmp").unlink(missing_ok=True)
            if self.stopped is None:
                raise

    def close(self) -> None:
        if self._frames.closed:
            return
        self._frames.flush()
        self._encoder.flush()
        self._frames.close()
        self._encoder.close()
        self.update_meta(finished=True, frame_count=self.frame_count, encoder_count=self.encoder_count)


class RecordingReader:
    """Reads a recording folder, tolerating an interrupted tail and skipping damage.

    A damaged line of ``frames.jsonl`` or ``encoder.jsonl``, a frame file that is missing,
    outside the folder, unreadable or not of the recording's format is not data: it is left
    out, logged once as a warning naming file and line, and listed in :attr:`damage`. Frames
    are checked when opened (index, file presence) and when read (:meth:`frame` raises
    :class:`FrameDamaged`). A damaged ``recording.json`` is a :class:`RecordingError`: without
    it nothing else can be interpreted.

    ``warn=False`` keeps the warnings quiet (``gearscan check`` prints the list itself).
    """

    def __init__(self, path: str | Path, *, warn: bool = True):
        self.path = Path(path)
        self.warn = warn
        self.damage: list[Damage] = []
        self._seen: set[tuple[str, str, int | None]] = set()
        self._lock = threading.Lock()
        self.meta = self._read_meta()
        camera = self.meta.get("camera") if isinstance(self.meta.get("camera"), dict) else {}
        try:
            declared = self.meta.get("frame_format")
            if declared is not None:
                self.format: FrameFormat | None = FrameFormat.from_json(declared)
            elif all(k in camera for k in ("width", "height", "bit_depth")):  # twin recordings before frame_format
                bits = _int_field(camera, "bit_depth", 1, 16)
                self.format = FrameFormat("uint8" if bits <= 8 else "uint16", _int_field(camera, "width", 1, 1 << 16),
                                          _int_field(camera, "height", 1, 1 << 16), bits)
            else:
                self.format = None  # taken from the first intact frame
        except ValueError as exc:
            raise RecordingError(f"{self.path / 'recording.json'}: frame_format: {exc}") from exc
        cycle = len(self.patterns) if "patterns" in self.meta else None
        self.records: list[FrameRecord] = []
        self.lines: list[int] = []  # frames.jsonl line of each record (for messages)
        # each record's place among frames.jsonl's records, damaged ones included and blank lines not: what its burst
        # position follows (a blank line, or two records on one line, must not shift every later burst)
        self.slots: list[int] = []
        self._read_index(cycle)
        # the recording's bit depth: declared, else what most frames say (recordings before frame_format)
        self._bits = self.format.bit_depth if self.format else (
            Counter(r.bit_depth for r in self.records).most_common(1)[0][0] if self.records else 8)
        for rec, n in zip(self.records, self.lines, strict=True):
            if rec.bit_depth != self._bits:
                self.report(Damage("frame_format", rec.file, n, f"bit_depth {rec.bit_depth} in a {self._bits}-bit recording"))
        self._keep([rec.bit_depth == self._bits for rec in self.records])
        try:
            wrap = FrameIdWrap.from_json(camera["frame_ids"]) if "frame_ids" in camera else None
        except ValueError as exc:
            raise RecordingError(f"{self.path / 'recording.json'}: camera.frame_ids: {exc}") from exc
        #: how the recorded camera's frame counter wraps (stored by the recorder, else inferred)
        self.frame_id_wrap = wrap or FrameIdWrap.detect([r.frame_id for r in self.records])
        #: frame ids extended past the counter's wraps: unique and increasing (one per record)
        self.extended_ids: list[int] = []
        self._check_order(cycle)

    def _read_index(self, cycle: int | None) -> None:
        """Parse ``frames.jsonl`` into :attr:`records`, reporting bad lines and frame files."""
        root = self.path.resolve()
        for n, slot, rec in self._valid_lines("frames.jsonl", FrameRecord.from_json, "frame_count"):
            if self._frame_file_damage(rec, n, root) is None:
                self.records.append(rec)
                self.lines.append(n)
                self.slots.append(slot)

    def _valid_lines(self, name: str, parse: Callable[[Any], _T], count_key: str) -> Iterator[tuple[int, int, _T]]:
        """``(line number, record slot, parse(record))`` for each record of index file ``name`` that parses (the slot:
        its place among the file's records, counting damaged ones); the others are reported, and so is a record
        count that differs from the finished recording's."""
        lines = 0
        for slot, (n, d) in enumerate(_jsonl_lines(self.path / name)):
            lines += 1
            if isinstance(d, Damage):
                self.report(d)
                continue
            try:
                value = parse(d)
            except ValueError as exc:
                self.report(Damage(_line_damage_kind(name), name, n, str(exc)))
                continue
            yield n, slot, value
        self._check_count(name, count_key, lines)

    def _keep(self, keep: list[bool]) -> None:
        self.records = [r for r, k in zip(self.records, keep, strict=True) if k]
        self.lines = [n for n, k in zip(self.lines, keep, strict=True) if k]
        self.slots = [n for n, k in zip(self.slots, keep, strict=True) if k]

    def _check_order(self, cycle: int | None) -> None:
        """A recording holds whole bursts in capture order (the recorder writes only complete
        bursts, frame after frame): the record in slot k (its place among the index's records, blank lines
        not counted) holds pattern ``k % cycle`` (three-frame bursts: 0, 1, 2
        or 0, 2, 1, as an alternating sequence shows them), ids increase, and
        within a burst they increase by one. A line that breaks this has a wrong number in it,
        which the assembler would otherwise turn into an unexplained lost burst."""
        unwrap, keep, prev = FrameIdUnwrapper(self.frame_id_wrap), [], None  # prev: (line, extended id, slot)
        angles = any(r.encoder_angle is not None for r in self.records)
        groups = cycle is not None and self.patterns.coarse_period_px is not None  # fine and coarse 3-frame bursts
        if groups:
            cycle = 3
        group = 0  # the pattern group (fine 0, coarse 1) of the burst the line belongs to
        seen: list[int] = []  # the burst's patterns so far, within its group
        for rec, n, slot in zip(self.records, self.lines, self.slots, strict=True):
            ext = unwrap(rec.frame_id)
            why = ""
            pos = slot % 3
            where = f"line {n}" if n == slot + 1 else f"line {n} (record {slot + 1}: blank or merged lines before it)"
            if groups and pos == 0:
                group = rec.pattern_index // 3
            if cycle == 3 or groups:  # three-frame bursts in either of the BURST_ORDERS
                seen = seen[:pos] if pos else []
                seen += BURST_ORDERS[0][len(seen):pos]  # a damaged line before: read as the forward order
                allowed = next_offsets(seen)
                if rec.pattern_index % 3 in allowed:
                    seen.append(rec.pattern_index % 3)
            if angles and rec.encoder_angle is None:
                why = "encoder_angle_rad is null where the recording's other frames have an angle"
            elif groups and not (rec.pattern_index < 6 and rec.pattern_index // 3 == group
                                 and rec.pattern_index % 3 in allowed):
                why = (f"pattern_index {rec.pattern_index} where {where} of a recording of whole three-frame "
                       f"fine (0-2) and coarse (3-5) bursts holds pattern "
                       f"{' or '.join(str(3 * group + a) for a in allowed)}")
            elif not groups and cycle == 3 and rec.pattern_index not in allowed:
                why = (f"pattern_index {rec.pattern_index} where {where} of a recording of whole "
                       f"3-frame bursts holds pattern {' or '.join(map(str, allowed))}")
            elif not groups and cycle is not None and cycle != 3 and rec.pattern_index != slot % cycle:
                why = (f"pattern_index {rec.pattern_index} where {where} of a recording of whole "
                       f"{cycle}-frame bursts holds pattern {slot % cycle}")
            elif prev is not None and ext <= prev[1]:
                why = f"frame id {rec.frame_id} does not come after the id on line {prev[0]}"
            elif (cycle is not None and prev is not None and prev[2] == slot - 1 and slot // cycle == (slot - 1) // cycle
                  and ext != prev[1] + 1):
                why = f"frame id {rec.frame_id} is {ext - prev[1]} after the id on line {prev[0]}, within a burst it is 1"
            if why:
                self.report(Damage("index_line", "frames.jsonl", n, why))
            else:
                prev = (n, ext, slot)
                self.extended_ids.append(ext)
            keep.append(not why)
        self._keep(keep)

    # -- damage ---------------------------------------------------------------------------
    def report(self, damage: Damage) -> None:
        """Record ``damage`` once (a second report of the same file, line and kind is ignored)."""
        key = (damage.kind, damage.file, damage.line)
        with self._lock:
            if key in self._seen:
                return
            self._seen.add(key)
            self.damage.append(damage)
        if self.warn:
            log.warning("damaged recording %s: %s (skipped)", self.path, damage)

    def damage_summary(self) -> dict[str, Any]:
        """Counts by kind and the list of damage, for metrics files."""
        with self._lock:
            items = list(self.damage)
        return {"count": len(items), "by_kind": dict(Counter(d.kind for d in items)),
                "items": [d.to_json() for d in items]}

    def _frame_file_damage(self, rec: FrameRecord, line: int, root: Path) -> Damage | None:
        target = (root / rec.file).resolve()
        if not target.is_relative_to(root):
            d = Damage("path_escape", "frames.jsonl", line, f"file {rec.file!r} points outside the recording folder")
        elif not target.is_file():
            d = Damage("missing_frame", rec.file, line, "frame file is missing")
        else:
            return None
        self.report(d)
        return d

    def _check_count(self, name: str, key: str, lines: int) -> None:
        """A finished recording says how many lines its index files hold: fewer means the file was
        cut (whole lines lost, which no parser can see), more means lines were added."""
        expected = self.meta.get(key)
        if self.finished and _is_count(expected) and expected != lines:
            self.report(Damage(_line_damage_kind(name), name, None,
                               f"{lines} complete lines where the finished recording wrote {expected} "
                               f"(recording.json {key}): lines were lost or added"))

    # -- header ---------------------------------------------------------------------------
    def _read_meta(self) -> dict[str, Any]:
        meta_path = self.path / "recording.json"
        if not meta_path.exists():
            raise RecordingError(f"{self.path} is not a recording: {meta_path.name} is missing")
        try:
            meta = json.loads(meta_path.read_bytes())
        except json.JSONDecodeError as exc:
            raise RecordingError(f"{meta_path}:{exc.lineno}: invalid JSON ({exc.msg})") from exc
        except (ValueError, RecursionError, OSError) as exc:
            raise RecordingError(f"{meta_path}: unreadable ({type(exc).__name__}: {exc})") from exc
        if not isinstance(meta, dict):
            raise RecordingError(f"{meta_path}: expected a JSON object, got {type(meta).__name__}")
        if meta.get("format") != FORMAT:
            raise RecordingError(f"{meta_path}: format is {meta.get('format')!r:.60}, expected {FORMAT!r}")
        if meta.get("version") != VERSION:
            raise RecordingError(f"{meta_path}: version {meta.get('version')!r:.60} unsupported (expected {VERSION})")
        return meta

    def _header(self, key: str, parse: Any) -> Any:
        """``parse(meta[key])`` with every failure as a RecordingError naming recording.json and the key."""
        try:
            return parse(self.meta[key])
        except KeyError as exc:
            raise RecordingError(f"{self.path / 'recording.json'}: no {key!r} section") from exc
        except (ValueError, TypeError, AttributeError, OverflowError) as exc:  # RigError, PatternError, pydantic
            raise RecordingError(f"{self.path / 'recording.json'}: {key}: {exc}") from exc

    def __len__(self) -> int:
        return len(self.records)

    @property
    def finished(self) -> bool:
        return bool(self.meta.get("finished", False))

    @property
    def rig(self):
        """The rig calibration; its camera must have the frames' size (else triangulation is wrong)."""
        from gearscan.core.rig import Rig

        rig = self._header("rig", lambda d: Rig.from_json(d, f"{self.path}/recording.json: rig"))
        return self.check_rig(rig, str(self.path / "recording.json"))

    def check_rig(self, rig, source: str):
        """``rig`` if its camera has the frames' size, else a RecordingError naming ``source``."""
        fmt = self.format
        if fmt is not None and (rig.camera.width, rig.camera.height) != (fmt.width, fmt.height):
            raise RecordingError(f"{source}: rig camera is {rig.camera.width}x{rig.camera.height}, the frames of "
                                 f"{self.path} are {fmt.width}x{fmt.height}")
        return rig

    @property
    def gear(self):
        from gearscan.core.gear import GearSpec

        return self._header("gear", lambda d: GearSpec(**d)) if self.meta.get("gear") else None

    @property
    def patterns(self):
        from gearscan.core.patterns import PatternSet

        return self._header("patterns", PatternSet.from_json)

    # -- frames ---------------------------------------------------------------------------
    def _check_format(self, i: int, fmt: FrameFormat) -> None:
        rec = self.records[i]
        with self._lock:
            if self.format is None:  # old recordings: the first intact frame sets the format
                self.format = FrameFormat(fmt.dtype, fmt.width, fmt.height, self._bits)
            expected = self.format
        want_dtype = "uint8" if rec.bit_depth <= 8 else "uint16"
        if fmt.dtype != want_dtype or (fmt.width, fmt.height) != (expected.width, expected.height):
            self._damaged(Damage("frame_format", rec.file, self.lines[i],
                                 f"{fmt.width}x{fmt.height} {fmt.dtype} where the recording holds {expected.describe()}"))

    def _damaged(self, damage: Damage) -> NoReturn:
        self.report(damage)
        raise FrameDamaged(damage)

    def frame(self, i: int) -> Frame:
        """Frame ``i``; raises :class:`FrameDamaged` (reported once) when its file is not usable."""
        rec = self.records[i]
        try:
            data = (self.path / rec.file).read_bytes()
        except OSError as exc:
            self._damaged(Damage("missing_frame", rec.file, self.lines[i], f"cannot read ({exc.strerror})"))
        fmt, why = png_format(data)
        if fmt is None:
            self._damaged(Damage("unreadable_frame", rec.file, self.lines[i], why))
        self._check_format(i, fmt)
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        if img is None or img.ndim != 2:
            self._damaged(Damage("unreadable_frame", rec.file, self.lines[i], "PNG data does not decode"))
        return Frame(
            image=img,
            frame_id=rec.frame_id,
            timestamp_ns=rec.timestamp_ns,
            pattern_index=rec.pattern_index,
            exposure_us=rec.exposure_us,
            bit_depth=rec.bit_depth,
            host_timestamp_ns=rec.host_timestamp_ns,
            encoder_angle=rec.encoder_angle,
        )

    def frames(self) -> Iterator[Frame]:
        """Every usable frame in order (damaged ones are reported and skipped)."""
        for i in range(len(self.records)):
            try:
                yield self.frame(i)
            except FrameDamaged:
                continue

    def has_truth(self) -> bool:
        return (self.path / "truth").is_dir()

    def truth(self, i: int) -> dict[str, np.ndarray]:
        """Ground truth of frame ``i`` (twin recordings): phase, mask, points, ..."""
        path = self.path / "truth" / f"{Path(self.records[i].file).stem}.npz"
        if not path.exists():
            raise RecordingError(f"{path}: no truth for frame {i}")
        try:
            with np.load(path) as z:
                return {k: z[k] for k in z.files}
        except (OSError, ValueError, EOFError, zlib.error, zipfile.BadZipFile) as exc:
            raise RecordingError(f"{path}: damaged truth file ({type(exc).__name__}: {exc})") from exc

    # -- encoder --------------------------------------------------------------------------
    def encoder_samples(self) -> list[EncoderSample]:
        """Valid samples of ``encoder.jsonl``; damaged lines are reported and skipped."""
        # ~10 us a line on a slow host: 6 s for 10 minutes of a 1 kHz encoder
        return [sample for _, _, sample in self._valid_lines("encoder.jsonl", encoder_sample_from_json, "encoder_count")]

    # -- whole-recording check ---------------------------------------------------------------
    def check(self) -> list[str]:
        """Find all damage without decoding an image: the header sections, every listed frame's
        PNG structure and format, every encoder line. Returns notes that are not damage
        (stray temporary files of an interrupted write, an unfinished recording)."""
        for key in ("rig", "patterns", "gear"):
            if key in self.meta:
                try:
                    getattr(self, key)
                except RecordingError as exc:
                    self.report(Damage("header", "recording.json", None, f"{key}: {exc.__cause__ or exc}"))
        for i, rec in enumerate(self.records):
            try:
                fmt, why = png_format((self.path / rec.file).read_bytes())
                if fmt is None:
                    self._damaged(Damage("unreadable_frame", rec.file, self.lines[i], why))
                self._check_format(i, fmt)
            except FrameDamaged:
                continue
            except OSError as exc:
                self.report(Damage("missing_frame", rec.file, self.lines[i], f"cannot read ({exc.strerror})"))
        self.encoder_samples()
        notes = [f"{p.relative_to(self.path)}: temporary file of an interrupted write, not part of the recording "
                 "(safe to delete)" for sub in ("frames", "truth") if (self.path / sub).is_dir()
                 for p in sorted((self.path / sub).glob("*.tmp.*"))]
        if not self.finished:
            notes.append("recording.json: not marked finished (interrupted recording: replays up to its last complete frame)")
        return notes
