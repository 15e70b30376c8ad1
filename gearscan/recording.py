"""The recording format: a folder anyone can read without gearscan.

::

    recording.json        format, version, rig calibration, gear spec, pattern set, camera settings
    frames/000000.png     lossless 8- or 16-bit image as captured
    frames.jsonl          one JSON line per frame (id, timestamps, pattern index, encoder angle, exposure)
    encoder.jsonl         raw encoder samples, one JSON line each
    truth/000000.npz      twin recordings only: phase (wrapped, at that frame's pose), mask, points, ...

Writes are append-only and flushed per frame; the PNG is renamed into place before its line is
appended, so every listed frame exists. A recording cut off mid-write (SIGKILL, cable pulled)
replays up to its last complete line; a damaged line in the middle is an error naming the line.
Angles are stored in radians (``*_rad`` keys), times in nanoseconds (``*_ns``).
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from gearscan.types import EncoderSample, Frame

FORMAT = "gearscan-recording"
VERSION = 1


class RecordingError(RuntimeError):
    """A recording folder is missing, damaged or written twice."""


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
    def from_json(cls, d: dict[str, Any]) -> FrameRecord:
        return cls(
            frame_id=int(d["id"]),
            timestamp_ns=int(d["timestamp_ns"]),
            pattern_index=int(d["pattern_index"]),
            exposure_us=float(d.get("exposure_us", 0.0)),
            bit_depth=int(d.get("bit_depth", 8)),
            encoder_angle=None if d.get("encoder_angle_rad") is None else float(d["encoder_angle_rad"]),
            host_timestamp_ns=int(d.get("host_timestamp_ns", 0)),
            file=str(d["file"]),
        )


class RecordingWriter:
    """Appends frames, truth and encoder samples to a recording folder.

    Use as a context manager; ``close`` marks the recording finished. ``durable=True``
    fsyncs every frame (survives power loss, costs a few ms per frame).
    """

    @staticmethod
    def check_target(path: str | Path, overwrite: bool = False) -> None:
        """Raise :class:`RecordingError` if ``path`` already holds a recording and ``overwrite`` is off."""
        if (Path(path) / "recording.json").exists() and not overwrite:
            raise RecordingError(f"{path} already holds a recording (pass overwrite to replace it)")

    def __init__(self, path: str | Path, meta: dict[str, Any], *, overwrite: bool = False, durable: bool = False):
        self.path = Path(path)
        self.check_target(self.path, overwrite)
        (self.path / "frames").mkdir(parents=True, exist_ok=True)
        if overwrite:
            for name in ("frames.jsonl", "encoder.jsonl"):
                (self.path / name).unlink(missing_ok=True)
        self.meta = {
            "format": FORMAT,
            "version": VERSION,
            "created": _dt.datetime.now(_dt.UTC).isoformat(),
            "finished": False,
            "frame_count": 0,
            **meta,
        }
        _atomic_write_text(self.path / "recording.json", json.dumps(self.meta, indent=2))
        self._frames = open(self.path / "frames.jsonl", "a")
        self._encoder = open(self.path / "encoder.jsonl", "a")
        self._durable = durable
        self.frame_count = 0

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def write_frame(self, frame: Frame, truth: dict[str, np.ndarray] | None = None) -> FrameRecord:
        """Write the image (and truth), then append its line; flushed before returning."""
        name = f"{self.frame_count:06d}"
        rel = f"frames/{name}.png"
        tmp = self.path / "frames" / f"{name}.tmp.png"
        if not cv2.imwrite(str(tmp), frame.image):
            raise RecordingError(f"could not write {tmp} (dtype {frame.image.dtype}, shape {frame.image.shape})")
        os.replace(tmp, self.path / rel)
        if truth is not None:
            (self.path / "truth").mkdir(exist_ok=True)
            tmp_t = self.path / "truth" / f"{name}.tmp.npz"
            np.savez_compressed(tmp_t, **truth)
            os.replace(tmp_t, self.path / "truth" / f"{name}.npz")
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
        self._frames.write(json.dumps(rec.to_json()) + "\n")
        self._frames.flush()
        self._encoder.flush()
        if self._durable:
            os.fsync(self._frames.fileno())
        self.frame_count += 1
        return rec

    def write_encoder(self, sample: EncoderSample) -> None:
        """Append one raw encoder sample (flushed with the next frame)."""
        self._encoder.write(
            json.dumps(
                {
                    "seq": sample.seq,
                    "device_time_us": sample.device_time_us,
                    "count": sample.count,
                    "index": sample.index,
                    "angle_rad": sample.angle,
                    "host_time_ns": sample.host_time_ns,
                }
            )
            + "\n"
        )

    def update_meta(self, **fields: Any) -> None:
        """Atomically rewrite ``recording.json`` with extra fields."""
        self.meta.update(fields)
        _atomic_write_text(self.path / "recording.json", json.dumps(self.meta, indent=2))

    def close(self) -> None:
        if self._frames.closed:
            return
        self._frames.flush()
        self._encoder.flush()
        self._frames.close()
        self._encoder.close()
        self.update_meta(finished=True, frame_count=self.frame_count)


def _read_jsonl(path: Path) -> list[dict[str, Any]]:
    """Complete lines of a JSONL file; a cut-off last line is dropped with a warning."""
    if not path.exists():
        return []
    data = path.read_bytes()
    lines = data.split(b"\n")
    tail = lines.pop()  # empty if the file ends with a newline
    out = []
    for n, raw in enumerate(lines, start=1):
        if not raw.strip():
            continue
        try:
            out.append(json.loads(raw))
        except json.JSONDecodeError as exc:
            raise RecordingError(f"{path}:{n}: damaged line ({exc.msg}): {raw[:80]!r}") from exc
    if tail.strip():
        warnings.warn(
            f"{path}:{len(lines) + 1}: incomplete last line ignored (recording was interrupted)", stacklevel=3
        )
    return out


class RecordingReader:
    """Reads a recording folder, tolerating an interrupted tail."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        meta_path = self.path / "recording.json"
        if not meta_path.exists():
            raise RecordingError(f"{self.path} is not a recording: {meta_path.name} is missing")
        try:
            self.meta: dict[str, Any] = json.loads(meta_path.read_text())
        except json.JSONDecodeError as exc:
            raise RecordingError(f"{meta_path}:{exc.lineno}: invalid JSON ({exc.msg})") from exc
        if self.meta.get("format") != FORMAT:
            raise RecordingError(f"{meta_path}: format is {self.meta.get('format')!r}, expected {FORMAT!r}")
        if self.meta.get("version") != VERSION:
            raise RecordingError(f"{meta_path}: version {self.meta.get('version')!r} unsupported (expected {VERSION})")
        frames_path = self.path / "frames.jsonl"
        self.records: list[FrameRecord] = []
        for n, d in enumerate(_read_jsonl(frames_path), start=1):
            try:
                rec = FrameRecord.from_json(d)
            except (KeyError, TypeError, ValueError) as exc:
                raise RecordingError(f"{frames_path}:{n}: missing or invalid field {exc}") from exc
            if not (self.path / rec.file).exists():
                raise RecordingError(f"{frames_path}:{n}: frame file {self.path / rec.file} is missing")
            self.records.append(rec)

    def __len__(self) -> int:
        return len(self.records)

    @property
    def finished(self) -> bool:
        return bool(self.meta.get("finished", False))

    @property
    def rig(self):
        from gearscan.rig import Rig

        if "rig" not in self.meta:
            raise RecordingError(f"{self.path}/recording.json has no rig calibration")
        return Rig.from_json(self.meta["rig"], f"{self.path}/recording.json: rig")

    @property
    def gear(self):
        from gearscan.twin.gear import GearSpec

        return GearSpec(**self.meta["gear"]) if self.meta.get("gear") else None

    @property
    def patterns(self):
        from gearscan.projector.patterns import PatternSet

        return PatternSet.from_json(self.meta["patterns"])

    def frame(self, i: int) -> Frame:
        rec = self.records[i]
        img = cv2.imread(str(self.path / rec.file), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise RecordingError(f"{self.path / rec.file}: unreadable image (frames.jsonl line {i + 1})")
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
        for i in range(len(self.records)):
            yield self.frame(i)

    def has_truth(self) -> bool:
        return (self.path / "truth").is_dir()

    def truth(self, i: int) -> dict[str, np.ndarray]:
        """Ground truth of frame ``i`` (twin recordings): phase, mask, points, ..."""
        path = self.path / "truth" / f"{Path(self.records[i].file).stem}.npz"
        if not path.exists():
            raise RecordingError(f"{path}: no truth for frame {i}")
        with np.load(path) as z:
            return {k: z[k] for k in z.files}

    def encoder_samples(self) -> list[EncoderSample]:
        path = self.path / "encoder.jsonl"
        out = []
        for n, d in enumerate(_read_jsonl(path), start=1):
            try:
                out.append(
                    EncoderSample(
                        seq=int(d["seq"]),
                        device_time_us=int(d["device_time_us"]),
                        count=int(d["count"]),
                        index=bool(d["index"]),
                        angle=float(d["angle_rad"]),
                        host_time_ns=int(d.get("host_time_ns", 0)),
                    )
                )
            except (KeyError, TypeError, ValueError) as exc:
                raise RecordingError(f"{path}:{n}: missing or invalid field {exc}") from exc
        return out
