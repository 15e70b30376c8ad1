"""Damaged ``predict`` inputs: exit 2 with a message naming the file, never a traceback (seeded, small)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from gearscan.cli import app
from gearscan.mocks.fuzz import BAD_NUMBERS, HOSTILE_BYTES, OPS, mutate

FRAMES = np.random.default_rng(0).integers(0, 256, (3, 32, 40), dtype=np.uint8)


def _predict(path: Path, tmp_path: Path):
    result = CliRunner().invoke(app, ["predict", str(path), "-o", str(tmp_path / "out.npz")])
    exc = result.exception
    assert exc is None or isinstance(exc, SystemExit), f"traceback: {exc!r}"
    return result


def _npz_bytes(tmp_path: Path, **arrays) -> bytes:
    np.savez(tmp_path / "src.npz", **arrays)
    return (tmp_path / "src.npz").read_bytes()


def _flip_data(b: bytes) -> bytes:  # a bit in the pixels: the zip CRC must catch it
    return b[:-400] + bytes([b[-400] ^ 1]) + b[-399:]


DAMAGE = {
    "truncated": lambda b: b[: len(b) // 2],
    "bit flip in the pixels": _flip_data,
    "npy header": lambda b: b.replace(b"'descr'", b"'dexcr'", 1),
    "not a zip": lambda b: b"garbage" * 20,
    "empty": lambda b: b"",
}
BAD_ARRAYS = {
    "float frames with NaN": {"frames": np.full((3, 32, 40), np.nan, np.float32)},
    "wrong shape": {"frames": FRAMES[:2]},
    "empty frames": {"frames": FRAMES[:, :0]},
    "bit_depth -1": {"frames": FRAMES, "bit_depth": np.asarray(-1)},
    "full_scale inf": {"frames": FRAMES, "full_scale": np.asarray(np.inf)},
    "angles NaN": {"frames": FRAMES, "angles": np.asarray([np.nan, 0.0, 0.1])},
}


@pytest.mark.parametrize("what", DAMAGE)
def test_a_damaged_npz_is_a_clean_error_naming_the_file(tmp_path, what):
    path = tmp_path / "burst.npz"
    path.write_bytes(DAMAGE[what](_npz_bytes(tmp_path, frames=FRAMES)))
    result = _predict(path, tmp_path)
    assert result.exit_code == 2 and "burst.npz" in result.output, result.output


@pytest.mark.parametrize("what", BAD_ARRAYS)
def test_out_of_range_arrays_are_refused_naming_the_file(tmp_path, what):
    path = tmp_path / "burst.npz"
    np.savez(path, **BAD_ARRAYS[what])
    result = _predict(path, tmp_path)
    assert result.exit_code == 2 and "burst.npz" in result.output, result.output


def test_seeded_byte_mutations_never_give_a_traceback(tmp_path):
    """30 mutations (1-3 edits each, the recording fuzz's operators): exit 2 naming the file, or exit 0."""
    rng = np.random.default_rng(1)
    base = _npz_bytes(tmp_path, frames=FRAMES)
    payloads = [*HOSTILE_BYTES, *BAD_NUMBERS]
    path = tmp_path / "burst.npz"
    for _ in range(30):
        data = base
        for _ in range(int(rng.integers(1, 4))):
            data = mutate(data, OPS[rng.integers(len(OPS))], int(rng.integers(0, 10_000)),
                          payloads[rng.integers(len(payloads))])
        path.write_bytes(data)
        result = _predict(path, tmp_path)
        assert result.exit_code == 0 or (result.exit_code == 2 and "burst.npz" in result.output), result.output
