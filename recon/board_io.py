"""Folder format of calibration board captures (what ``gearscan calibrate`` reads).

::

    captures/
      board.json          {"format": "gearscan-board-captures", "version": 1,
                           "board": {"type": "checkerboard", "cols": 9, "rows": 6,
                                     "square_mm": 1.6, "margin_squares": 1.0},
                           "camera": {"width": W, "height": H, "bit_depth": 8},
                           "projector": {"width": Wp, "height": Hp},
                           "steps": N,
                           "periods_u": [20, 160, 1408],   # fringes along projector columns
                           "periods_v": [20, 160, 880],    # fringes along projector rows
                           "views": [{"name": "free_00", "turntable_angle_deg": null}, ...]}
      free_00/white.png                 board under the projector's full-white frame
      free_00/u_<period>_<n>.png        n = 0..N-1, shift 2 pi n / N, phase 2 pi u_p / period
      free_00/v_<period>_<n>.png        same with phase 2 pi v_p / period
      ...

Images are lossless PNG, 8- or 16-bit as captured. The largest period of each orientation
must cover the projector (>= its width for u, height for v) so temporal unwrapping starts
from an absolute phase. Views with ``turntable_angle_deg`` set show the board fixed on the
turntable at that encoder angle; at least three are needed to fit the axis.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from gearscan.recon.calibration import BoardCapture, Checkerboard

FORMAT = "gearscan-board-captures"
VERSION = 1


def _fname(axis: str, period: float, n: int) -> str:
    return f"{axis}_{period:g}_{n:02d}.png"


def save_captures(
    folder: str | Path,
    captures: Sequence[BoardCapture],
    board: Checkerboard,
    projector_size: tuple[int, int],
    bit_depth: int = 8,
) -> Path:
    """Write captures in the folder format above."""
    import cv2

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    if not captures:
        raise ValueError("captures: nothing to save")
    first = captures[0]
    steps = next(iter(first.fringes_u.values())).shape[0]
    meta = {
        "format": FORMAT,
        "version": VERSION,
        "board": board.to_json(),
        "camera": {"width": int(first.white.shape[1]), "height": int(first.white.shape[0]), "bit_depth": bit_depth},
        "projector": {"width": projector_size[0], "height": projector_size[1]},
        "steps": int(steps),
        "periods_u": sorted(first.fringes_u),
        "periods_v": sorted(first.fringes_v),
        "views": [],
    }
    for cap in captures:
        d = folder / cap.name
        d.mkdir(exist_ok=True)
        cv2.imwrite(str(d / "white.png"), cap.white)
        for axis, fringes in (("u", cap.fringes_u), ("v", cap.fringes_v)):
            for period, stack in fringes.items():
                for n, img in enumerate(stack):
                    cv2.imwrite(str(d / _fname(axis, period, n)), img)
        angle = None if cap.turntable_angle is None else math.degrees(cap.turntable_angle)
        meta["views"].append({"name": cap.name, "turntable_angle_deg": angle})
    (folder / "board.json").write_text(json.dumps(meta, indent=2))
    return folder


def load_captures(folder: str | Path) -> tuple[list[BoardCapture], Checkerboard, tuple[int, int], tuple[int, int]]:
    """Read a captures folder: (captures, board, camera (W, H), projector (W, H))."""

    folder = Path(folder)
    meta_path = folder / "board.json"
    if not meta_path.exists():
        raise FileNotFoundError(f"{meta_path} not found: is {folder} a board-captures folder?")
    try:
        meta = json.loads(meta_path.read_text())
    except (ValueError, OSError) as exc:
        raise ValueError(f"{meta_path}: not readable JSON ({exc})") from exc
    if not isinstance(meta, dict):
        raise ValueError(f"{meta_path}: expected a JSON object, got {type(meta).__name__}")
    try:
        return _load(folder, meta_path, meta)
    except (KeyError, TypeError, AttributeError) as exc:  # a hand-edited file: a field missing or of another type
        raise ValueError(f"{meta_path}: {type(exc).__name__} {exc} (a field missing or of the wrong type; expected the "
                         "layout gearscan.recon.board_io writes)") from exc
    except ValueError as exc:  # a value that does not read (steps 0, a board size "x"): the file named
        raise ValueError(exc if str(meta_path) in str(exc) else f"{meta_path}: {exc}") from exc


def _load(folder: Path, meta_path: Path, meta: dict) -> tuple[list[BoardCapture], Checkerboard, tuple[int, int],
                                                                tuple[int, int]]:
    import cv2

    if meta.get("format") != FORMAT:
        raise ValueError(f"{meta_path}: expected \"format\": \"{FORMAT}\", got {meta.get('format')!r}")
    for key in ("board", "camera", "projector", "steps", "periods_u", "periods_v", "views"):
        if key not in meta:
            raise ValueError(f"{meta_path}: missing key {key!r}")
    board = Checkerboard.from_json(meta["board"])
    cam = (int(meta["camera"]["width"]), int(meta["camera"]["height"]))
    proj = (int(meta["projector"]["width"]), int(meta["projector"]["height"]))
    full_scale = (1 << int(meta["camera"].get("bit_depth", 8))) - 1
    steps = int(meta["steps"])
    if steps < 3:
        raise ValueError(f"{meta_path}: steps: expected >= 3 phase steps per period, got {steps}")
    for axis in ("u", "v"):
        if not isinstance(meta[f"periods_{axis}"], list) or not meta[f"periods_{axis}"]:
            raise ValueError(f"{meta_path}: periods_{axis}: expected a non-empty list of fringe periods (projector px), "
                             f"got {meta[f'periods_{axis}']!r}")

    def read(path: Path) -> np.ndarray:
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise FileNotFoundError(f"missing or unreadable image {path}")
        if img.shape != (cam[1], cam[0]):
            raise ValueError(f"{path}: expected a {cam[0]}x{cam[1]} grayscale image, got shape {img.shape}")
        return img

    captures = []
    for view in meta["views"]:
        d = folder / view["name"]
        fringes: dict[str, dict[float, np.ndarray]] = {"u": {}, "v": {}}
        for axis in ("u", "v"):
            for period in meta[f"periods_{axis}"]:
                fringes[axis][float(period)] = np.stack([read(d / _fname(axis, float(period), n)) for n in range(steps)])
        angle = view.get("turntable_angle_deg")
        captures.append(
            BoardCapture(
                name=view["name"],
                white=read(d / "white.png"),
                fringes_u=fringes["u"],
                fringes_v=fringes["v"],
                full_scale=full_scale,
                turntable_angle=None if angle is None else math.radians(float(angle)),
            )
        )
    return captures, board, cam, proj
