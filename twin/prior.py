"""The twin as a prior at run time: what the CAD says each pixel sees during a moving burst.

The encoder gives the three frames' turntable angles and the calibration + CAD give the
geometry, so the twin predicts, per pixel, how far the fringe phase moves between the frames
(the motion error of three-step PS) and how much the shading changes. Solving the three frames
with those shifts (:func:`~gearscan.recon.compensation.solve_shifted`) needs no training and no
data from the user's rig; at zero motion it *is* three-step PS, so it cannot make a still gear
worse. It holds only where the model holds: the CAD must see one smooth lit surface in every
frame's blur footprint (``clean``) and the shifts must stay apart (``gain``, the noise gain of the
solve over three-step PS). Elsewhere (moving silhouettes, shadow borders, creases) the frames
see different surfaces and the prior says so instead of guessing.

Only the phase *changes* come from the CAD, never the phase itself: a gear that deviates from
its CAD by much less than a fringe keeps its deviation (benchmarks/twin_prior_report.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from gearscan.core.gear import GearSpec
from gearscan.core.phase import THREE_STEP_SHIFTS
from gearscan.core.rig import Rig
from gearscan.core.types import PhaseResult
from gearscan.recon.compensation import solve_shifted
from gearscan.twin.render import Optics, TwinRenderer

_GAIN_THREE_STEP = math.sqrt(4.0 / 3.0)  # |rows C, S of the three-step solve's inverse|
MIN_INCIDENCE_COS = 0.08  # the twin's own mask threshold (Optics.min_incidence_cos)


@dataclass(frozen=True, slots=True)
class PriorMaps:
    """Per-pixel prediction for one burst (camera image grid)."""

    shifts: np.ndarray  # (3, H, W) rad: nominal shift + the CAD's phase change since frame 0
    ratio: np.ndarray  # (3, H, W) irradiance of frame k over frame 0 (1 where unknown)
    clean: np.ndarray  # (H, W) bool: one smooth lit CAD surface in every frame's blur footprint
    gain: np.ndarray  # (H, W) noise gain of the solve over three-step PS (inf where singular)

    def phase_change(self, nominal: np.ndarray = THREE_STEP_SHIFTS) -> np.ndarray:
        """``(2, H, W)`` rad: the CAD's fringe phase change from the first frame to the second and third."""
        return self.shifts[1:] - np.asarray(nominal, np.float64)[1:, None, None]

    def usable(self, max_gain: float = 2.0) -> np.ndarray:
        """Pixels where the prior's model holds and the solve is well conditioned."""
        return self.clean & (self.gain <= max_gain)


class TwinPrior:
    """Renders the prior maps of a rig + CAD gear for bursts at given encoder angles.

    ``camera_defocus_px`` sets how far a blur footprint reaches (the ``clean`` test); it is a
    property of the camera, not of the gear, and defaults to the twin's.
    """

    def __init__(self, rig: Rig, gear: GearSpec, period_px: float, *, camera_defocus_px: float = 0.5) -> None:
        if not period_px > 0:
            raise ValueError(f"period_px: expected > 0, got {period_px}")
        self.rig = rig
        self.gear = gear
        self.period_px = float(period_px)
        self.renderer = TwinRenderer(rig, gear, Optics(camera_defocus_px=camera_defocus_px))

    def maps(self, angles: np.ndarray | tuple[float, float, float],
             nominal: np.ndarray = THREE_STEP_SHIFTS) -> PriorMaps:
        """Prior maps for frames at turntable ``angles`` (rad, the encoder's, first frame first) whose
        patterns have the shifts ``nominal`` (a reversed burst's: ``core.phase.burst_shifts``)."""
        angles = np.asarray(angles, np.float64)
        if angles.shape != (3,) or not np.isfinite(angles).all():
            raise ValueError(f"angles: expected three finite turntable angles (rad), got {angles}")
        surfs = [self.renderer.surface(float(a)) for a in angles]
        u0, irr0 = surfs[0].u_proj, surfs[0].irradiance
        shape = u0.shape
        shifts = np.empty((3, *shape))
        ratio = np.ones((3, *shape))
        clean = np.ones(shape, bool)
        for k, s in enumerate(surfs):
            change = 2 * np.pi * (s.u_proj - u0) / self.period_px
            clean &= np.isfinite(change)
            clean &= self.renderer.clean_mask(s.lit & (s.cos_incidence >= MIN_INCIDENCE_COS), s)
            shifts[k] = nominal[k] + np.nan_to_num(change)
            with np.errstate(divide="ignore", invalid="ignore"):
                ratio[k] = np.where((irr0 > 0) & (s.irradiance > 0), s.irradiance / irr0, 1.0)
        return PriorMaps(shifts, ratio, clean, _noise_gain(shifts))

    def decode(self, frames: np.ndarray, full_scale: float, angles, *, max_gain: float = 2.0,
               read_noise_dn: float = 1.0, nominal: np.ndarray = THREE_STEP_SHIFTS,
               maps: PriorMaps | None = None) -> tuple[PhaseResult, np.ndarray]:
        """Phase of a burst solved with the prior's shifts, and where the prior is usable.

        Each frame is first divided by its predicted shading ratio (so ``A`` and ``B`` stay put),
        then the three equations are solved per pixel. ``sigma`` is the noise-only sigma of
        three-step PS times the solve's noise gain, infinite where the prior is not usable.
        ``maps``: this burst's :meth:`maps` if already rendered (the ray casts are the cost).
        """
        frames = np.asarray(frames)
        if frames.ndim != 3 or frames.shape[0] != 3:
            raise ValueError(f"frames: expected a three-step burst (3, H, W), got shape {frames.shape}")
        prior = self.maps(angles, nominal) if maps is None else maps
        if frames.shape[1:] != prior.clean.shape:
            raise ValueError(f"frames: {frames.shape[1:]} do not match the rig's camera {prior.clean.shape}")
        usable = prior.usable(max_gain)
        _, c, s = solve_shifted(frames.astype(np.float64) / np.clip(prior.ratio, 0.25, 4.0), prior.shifts)
        m, d = (2.0 / full_scale) * s, (2.0 / full_scale) * c  # N S / 4 normalisation: hypot = 2B/S
        mod = np.hypot(m, d)
        with np.errstate(divide="ignore", invalid="ignore"):
            sigma = np.where(usable & (mod > 0),
                             prior.gain * (2.0 * read_noise_dn / full_scale) * math.sqrt(2 / 3) / mod, np.inf)
        sigma = sigma.astype(np.float32)
        result = PhaseResult(
            phase=np.arctan2(m, d).astype(np.float32), M=m.astype(np.float32), D=d.astype(np.float32),
            sigma_model=np.zeros_like(sigma), sigma_data=sigma, sigma_total=sigma, mode="twin prior",
            angle=float(np.asarray(angles, np.float64)[0]),
        )
        return result, usable


def _noise_gain(shifts: np.ndarray) -> np.ndarray:
    """Noise gain of the per-pixel solve for ``(a, C, S)`` over three-step PS's (1 at nominal shifts)."""
    cos, sin = np.cos(shifts), np.sin(shifts)
    mat = np.stack([np.ones_like(cos), cos, -sin], axis=-1)  # (3, H, W, 3): row per frame
    mat = np.moveaxis(mat, 0, -2)  # (H, W, 3, 3)
    det = np.linalg.det(mat)
    ok = np.abs(det) > 1e-6
    inv = np.zeros_like(mat)
    inv[ok] = np.linalg.inv(mat[ok])
    gain = np.sqrt((inv[..., 1, :] ** 2).sum(-1) + (inv[..., 2, :] ** 2).sum(-1)) / _GAIN_THREE_STEP
    return np.where(ok, gain, np.inf)


def blend(prior: PhaseResult, usable: np.ndarray, other: PhaseResult) -> PhaseResult:
    """``prior`` where it is usable, ``other`` (the network's result) everywhere else."""
    def pick(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.where(usable, a, b).astype(np.float32)

    return PhaseResult(
        phase=pick(prior.phase, other.phase), M=pick(prior.M, other.M), D=pick(prior.D, other.D),
        sigma_model=pick(prior.sigma_model, other.sigma_model), sigma_data=pick(prior.sigma_data, other.sigma_data),
        sigma_total=pick(prior.sigma_total, other.sigma_total), mode=f"twin prior + {other.mode}",
        burst_index=other.burst_index, angle=other.angle,
    )
