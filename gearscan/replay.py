"""Replay a recording through decoding and into the viewer, with accuracy when truth exists."""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gearscan.recon.phase import phase_error, three_step
from gearscan.recording import RecordingReader
from gearscan.types import Burst, PhaseResult

log = logging.getLogger(__name__)


def classical_result(burst: Burst) -> PhaseResult:
    """Three-step phase shifting of a burst, with the noise-only phase sigma as data uncertainty."""
    phase, m, d = three_step(burst.images, burst.full_scale)
    mod = np.hypot(m, d)
    # sigma_phi = s_I sqrt(2/N) / B with one DN of noise: a floor, not a motion-aware estimate
    with np.errstate(divide="ignore"):
        sigma = np.where(mod > 0, (2.0 / burst.full_scale) * np.sqrt(2 / 3) / mod, np.inf).astype(np.float32)
    zero = np.zeros_like(sigma)
    return PhaseResult(phase=phase, M=m, D=d, sigma_model=zero, sigma_data=sigma, sigma_total=sigma, mode="three-step",
                       burst_index=burst.index, angle=burst.angles[0])


def recording_bursts(reader: RecordingReader) -> Iterator[tuple[Burst, int]]:
    """Consecutive frames with pattern indices 0, 1, 2 as bursts, with the first frame's index."""
    from gearscan.acquisition.bursts import BurstAssembler

    assembler = BurstAssembler()
    for i in range(len(reader)):
        burst = assembler.push(reader.frame(i))
        if burst is not None:
            yield burst, i - 2


@dataclass
class ReplayMetrics:
    bursts: int = 0
    per_burst: list[dict[str, float]] = field(default_factory=list)

    def summary(self) -> dict[str, float]:
        out: dict[str, float] = {"bursts": self.bursts}
        if self.per_burst:
            for key in self.per_burst[0]:
                if key.endswith("_rmse_rad"):
                    vals = np.array([b[key] for b in self.per_burst])
                    out[key] = float(np.sqrt(np.mean(vals**2)))
        return out


def replay(
    recording: str | Path,
    *,
    save: str | Path | None = None,
    metrics_path: str | Path | None = None,
    decode: Callable[[Burst], PhaseResult] | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> ReplayMetrics:
    """Decode every burst of ``recording``; log to rerun if ``save``; return accuracy metrics."""
    from gearscan.viewer.log import RerunLogger

    reader = RecordingReader(recording)
    decode = decode or classical_result
    logger = RerunLogger(save=save) if save else None
    if logger:
        logger.log_rig(reader.rig)
    metrics = ReplayMetrics()
    total = len(reader) // 3
    truth_ok = reader.has_truth()
    for burst, first in recording_bursts(reader):
        result = decode(burst)
        row: dict[str, float] = {"burst": burst.index, "angle_deg": float(np.degrees(burst.angles[0]))}
        err = mask = None
        if truth_ok:
            truth = reader.truth(first)
            mask = truth["mask"]
            err = np.where(mask, phase_error(result.phase, truth["phase"]), 0.0)
            row[f"{result.mode}_rmse_rad"] = float(np.sqrt(np.mean(err[mask] ** 2)))
            if result.mode != "three-step":
                base = classical_result(burst)
                row["three-step_rmse_rad"] = float(np.sqrt(np.mean(phase_error(base.phase, truth["phase"])[mask] ** 2)))
        metrics.per_burst.append(row)
        metrics.bursts += 1
        if logger:
            logger.log_burst(burst, result, mask=mask, error=err, stats={k: v for k, v in row.items() if k.endswith("rmse_rad")})
        if progress:
            progress(metrics.bursts, total)
    if logger:
        logger.close()
    if metrics_path:
        Path(metrics_path).write_text(json.dumps({"summary": metrics.summary(), "bursts": metrics.per_burst}, indent=2))
    return metrics
