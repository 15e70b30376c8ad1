"""Render a twin recording: three-step bursts of a rotating gear, with truth per frame.

The result is an ordinary recording (gearscan.core.recording) that the replay camera and
``gearscan replay`` read like a captured one; it also holds ``truth/NNNNNN.npz``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np

from gearscan.core.gear import GearSpec
from gearscan.core.patterns import DEFAULT_PERIOD_PX, PatternSet
from gearscan.core.recording import RecordingWriter
from gearscan.core.rig import Rig, default_rig
from gearscan.core.types import EncoderSample, Frame
from gearscan.twin.defects import GearDefects
from gearscan.twin.motion import frame_angles
from gearscan.twin.render import Optics, TwinRenderer

ENCODER_COUNTS_PER_REV = 1 << 17
ENCODER_RATE_HZ = 1000


def render_recording(
    out: str | Path,
    *,
    rig: Rig | None = None,
    gear: GearSpec | None = None,
    defects: GearDefects | None = None,
    optics: Optics | None = None,
    motion: str = "uniform:0.6",
    bursts: int = 4,
    period_px: float = DEFAULT_PERIOD_PX,
    start_deg: float = 0.0,
    frame_interval_ms: float = 10.0,
    exposure_us: float = 2000.0,
    motion_blur: bool = False,
    seed: int = 0,
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
    coarse_period_px: float | None = None,
    coarse_every: int = 4,
    alternate_order: bool = False,
) -> Path:
    """Render ``bursts`` three-step bursts under ``motion`` into recording folder ``out``.

    ``gear`` is the nominal spec the recording states as its CAD; with ``defects`` the twin
    renders the as-built gear and ``recording.json`` holds the answer under ``truth``. With
    ``coarse_period_px`` a coarse three-step burst (patterns 3-5) comes first and then after every
    ``coarse_every`` bursts, as a rig sequencing them would (:meth:`PatternSet.with_coarse`). With
    ``alternate_order`` every other measuring burst shows its patterns as 0, 2, 1 (:meth:`PatternSet.cycle`).
    """
    rig = rig or default_rig()
    gear = gear or GearSpec()
    optics = optics or Optics()
    if coarse_period_px is None:
        patterns, sequence = PatternSet.three_step(period_px), [0] * bursts
    else:
        if coarse_every < 1:
            raise ValueError(f"coarse_every: expected >= 1 burst between coarse bursts, got {coarse_every}")
        patterns = PatternSet.with_coarse(period_px, coarse_period_px)
        sequence = [g for k in range(bursts) for g in ([1, 0] if k % coarse_every == 0 else [0])]
    fine_orders = ((0, 1, 2), (0, 2, 1)) if alternate_order else ((0, 1, 2),)
    fine_k = np.cumsum([g == 0 for g in sequence]) - 1  # index of each burst among the measuring ones
    pattern_index = [3 * g + n for g, k in zip(sequence, fine_k, strict=True)
                     for n in (fine_orders[k % len(fine_orders)] if g == 0 else (0, 1, 2))]
    angles = frame_angles(motion, len(sequence), start_deg)
    truth = defects.truth(gear) if defects is not None and not defects.empty else None  # validates first
    renderer = TwinRenderer(rig, gear, optics, defects=defects)
    rng = np.random.default_rng(seed)
    dt_ns = int(round(frame_interval_ms * 1e6))
    # angular velocity per frame (rad/s) for exposure blur: the step to the next frame / interval
    steps = np.diff(np.append(angles, angles[-1] + (angles[-1] - angles[-2] if len(angles) > 1 else 0)))
    rig = rig if rig.counts_per_rev else replace(rig, counts_per_rev=ENCODER_COUNTS_PER_REV)
    meta = {
        "source": "twin",
        "rig": rig.to_json(),
        "gear": gear.model_dump(),
        "patterns": patterns.to_json(),
        "camera": {
            "width": rig.camera.width,
            "height": rig.camera.height,
            "bit_depth": optics.bit_depth,
            "exposure_us": exposure_us,
            "frame_interval_ms": frame_interval_ms,
        },
        "twin": {"optics": optics.model_dump(), "motion": motion, "seed": seed, "motion_blur": motion_blur,
                 "alternate_order": alternate_order},
        "encoder": {"counts_per_rev": ENCODER_COUNTS_PER_REV, "rate_hz": ENCODER_RATE_HZ},
        **({"truth": truth} if truth else {}),
    }
    frame_times = np.arange(len(angles)) * dt_ns + int(exposure_us * 500)  # exposure midpoints
    with RecordingWriter(out, meta, overwrite=overwrite) as writer:
        # encoder: samples at 1 kHz along the piecewise-linear motion through the frame midpoints
        t_enc = np.arange(0, frame_times[-1] + dt_ns, int(1e9 / ENCODER_RATE_HZ))
        a_enc = np.interp(t_enc, frame_times, angles)
        counts = np.rint(a_enc / (2 * math.pi) * ENCODER_COUNTS_PER_REV).astype(np.int64)
        enc_iter = iter(range(len(t_enc)))
        next_enc = next(enc_iter, None)
        for i, angle in enumerate(angles):
            span = abs(steps[i]) * exposure_us * 1e3 / dt_ns if motion_blur else 0.0
            img, truth = renderer.render(float(angle), patterns, rng, indices=[pattern_index[i]], motion_span=span)
            t0 = i * dt_ns
            while next_enc is not None and t_enc[next_enc] <= t0 + dt_ns:
                k = next_enc
                writer.write_encoder(
                    EncoderSample(
                        seq=k,
                        device_time_us=int(t_enc[k] // 1000),
                        count=int(counts[k]),
                        index=False,
                        angle=float(counts[k] * 2 * math.pi / ENCODER_COUNTS_PER_REV),
                        host_time_ns=int(t_enc[k]),
                    )
                )
                next_enc = next(enc_iter, None)
            frame = Frame(
                image=img[0],
                frame_id=i,
                timestamp_ns=t0,
                pattern_index=pattern_index[i],
                exposure_us=exposure_us,
                bit_depth=optics.bit_depth,
                host_timestamp_ns=t0,
                encoder_angle=float(angle),
            )
            writer.write_frame(
                frame,
                truth={
                    "phase": truth.phase,
                    "mask": truth.mask,
                    "points": truth.points,
                    "M": truth.M,
                    "D": truth.D,
                    "depth": truth.depth,
                    "angle": np.float64(angle),
                },
            )
            if progress:
                progress(i + 1, len(angles))
    return Path(out)
