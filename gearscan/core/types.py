"""Dataclasses that travel between pipeline stages, frozen once made (``dataclasses.replace`` derives).

Every stage package may import this module; it depends on numpy only, so importing it
never pulls in torch, open3d, rerun or hardware libraries.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True, slots=True, repr=False)
class Frame:
    """One camera image with the metadata the burst assembler and recorder need.

    ``image`` is ``(H, W)`` in the camera's raw dtype (uint8 or uint16); ``bit_depth`` says
    how many of its bits carry signal (8, 10, 12, 16). Times are nanoseconds; the device
    timestamp is in the camera's clock, the host timestamp in ``time.monotonic_ns``.
    """

    image: np.ndarray
    frame_id: int
    timestamp_ns: int
    pattern_index: int = 0
    exposure_us: float = 0.0
    bit_depth: int = 8
    host_timestamp_ns: int = 0
    encoder_angle: float | None = None  # rad, turntable angle at exposure midpoint, if known

    @property
    def full_scale(self) -> int:
        """Largest value a pixel can take, ``2**bit_depth - 1`` (S in DESIGN.md)."""
        return (1 << self.bit_depth) - 1

    @property
    def midpoint_ns(self) -> int:
        """Device time of the middle of the exposure (timestamps mark exposure start)."""
        return self.timestamp_ns + int(round(self.exposure_us * 500.0))

    def __repr__(self) -> str:
        h, w = self.image.shape[:2]
        return (
            f"Frame(id={self.frame_id}, t={self.timestamp_ns} ns, pattern={self.pattern_index}, "
            f"{w}x{h} {self.image.dtype}/{self.bit_depth}bit, exposure={self.exposure_us:g} us)"
        )


#: Valid ranges of :class:`EncoderSample` fields, shared by the encoder line protocol and the
#: recording format so a value one accepts the other accepts too.
ENCODER_SEQ_MODULUS = 1 << 32  # seq: uint32, wraps to 0
ENCODER_TIME_US_MAX = ((1 << 63) - 1) // 1000  # device_time_us: its nanoseconds fit int64 (292 years)
ENCODER_COUNT_MAX = (1 << 63) - 1  # count: int64, |count| <= this


@dataclass(frozen=True, slots=True)
class EncoderSample:
    """One turntable encoder reading, already mapped to the host clock.

    Ranges: ``0 <= seq < ENCODER_SEQ_MODULUS``, ``0 <= device_time_us <= ENCODER_TIME_US_MAX``,
    ``|count| <= ENCODER_COUNT_MAX``; ``angle`` finite.
    """

    seq: int
    device_time_us: int
    count: int
    index: bool
    angle: float  # rad, after counts-per-rev scaling and index zeroing
    host_time_ns: int = 0


@dataclass(frozen=True, slots=True, repr=False)
class Burst:
    """Three frames with phase shifts 0, 2pi/3, 4pi/3 at increasing turntable angles.

    ``angles`` are the encoder angles (rad) at each frame's exposure midpoint; the
    burst's ground truth (and the network's target) is the phase at ``angles[0]``.
    The shifts come in that order, or reversed after the first (0, 4pi/3, 2pi/3:
    :attr:`reversed_order`): a sequence that alternates the two gives every surface point
    of a turning gear distinct fringe phases from frame to frame (``recon.track``).
    """

    frames: tuple[Frame, Frame, Frame]
    angles: tuple[float, float, float]
    index: int = 0
    group: int = 0  # 0: the measuring fringes (patterns 0-2); 1: a coarse burst (3-5), the unwrapping prior

    @property
    def images(self) -> np.ndarray:
        """The three images stacked as ``(3, H, W)`` in raw dtype."""
        return np.stack([f.image for f in self.frames])

    @property
    def full_scale(self) -> int:
        return self.frames[0].full_scale

    @property
    def offsets(self) -> tuple[int, int, int]:
        """Each frame's pattern within the burst's group, in capture order: (0, 1, 2) or (0, 2, 1)."""
        first = self.frames[0].pattern_index
        return tuple(f.pattern_index - first for f in self.frames)  # type: ignore[return-value]

    @property
    def reversed_order(self) -> bool:
        """True when the frames show the group's patterns in the order 0, 2, 1 (shifts 0, 4pi/3, 2pi/3)."""
        return self.offsets == (0, 2, 1)

    @property
    def timestamp_ns(self) -> int:
        return self.frames[0].timestamp_ns

    def __repr__(self) -> str:
        deg = ", ".join(f"{np.degrees(a):.3f}" for a in self.angles)
        ids = [f.frame_id for f in self.frames]
        return f"Burst(index={self.index}, frames={ids}, angles_deg=[{deg}])"


@dataclass(frozen=True, slots=True)
class PhaseResult:
    """Wrapped phase of one burst with its per-pixel uncertainty (all ``(H, W)`` float32).

    ``M`` and ``D`` are normalised by ``N*S/4`` (DESIGN.md), so ``hypot(M, D) = 2B/S``.
    Uncertainties are standard deviations in radians; ``sigma_model`` is zero for a
    deterministic or classical decode.
    """

    phase: np.ndarray
    M: np.ndarray
    D: np.ndarray
    sigma_model: np.ndarray
    sigma_data: np.ndarray
    sigma_total: np.ndarray
    mode: str = "deterministic"
    var_M: np.ndarray | None = None
    var_D: np.ndarray | None = None
    burst_index: int = 0
    angle: float = 0.0  # rad, turntable angle the phase refers to (first frame)

    @property
    def modulation(self) -> np.ndarray:
        """Normalised modulation ``2B/S`` per pixel."""
        return np.hypot(self.M, self.D)

    @property
    def from_network(self) -> bool:
        """Whether a network decoded it (``mode`` "deterministic" or "mc<T>"): its modulation is the network's own
        estimate, not the frames' (three-step PS, AIA, Hilbert and the twin prior read theirs off the frames)."""
        return self.mode == "deterministic" or (self.mode.startswith("mc") and self.mode[2:].isdigit())


@dataclass(frozen=True, slots=True)
class Cloud:
    """Measured 3D points with per-point uncertainty.

    ``points`` is ``(N, 3)`` float64 in the frame named by ``frame`` ("camera" or
    "world" = turntable); ``sigma`` is the depth uncertainty in mm (a burst's: the phase sigma propagated and
    scaled by edge band and motion class, ``recon.depth_sigma``, so that about 95 % of points lie within 2 sigma on
    val);
    ``pixels`` holds the ``(row, col)`` each point came from.
    """

    points: np.ndarray
    sigma: np.ndarray
    pixels: np.ndarray
    frame: str = "camera"
    burst_index: int = 0
    angle: float = 0.0
    deviation: np.ndarray | None = None  # mm, signed distance to CAD if computed
    extras: dict[str, np.ndarray] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.points.shape[0])


@dataclass(frozen=True, slots=True)
class Measurement:
    """Everything one burst produced, as it travels to the viewer and the metrics.

    ``unresolved`` marks pixels that passed the modulation and sigma tests but got no point
    (no prior there, or the surface outside the rig's unambiguous range); ``unwrap`` counts
    them by cause (``unresolved``; ``mixed``: points dropped because their pixel may blend two
    surfaces, :func:`gearscan.recon.edges.mixed_pixels`; ``unsupported``: a network's pixels whose frames show
    no fringes around them, :class:`gearscan.recon.measure.Reconstructor`), so nothing is dropped silently.
    """

    burst: Burst
    result: PhaseResult
    cloud: Cloud | None = None
    phase_abs: np.ndarray | None = None
    valid: np.ndarray | None = None
    unresolved: np.ndarray | None = None
    unwrap: dict[str, int] = field(default_factory=dict)
    mixed: np.ndarray | None = None  # pixels whose point was dropped as a blend of two surfaces
