"""Accuracy evaluation on twin scenes: phase RMSE, calibration (ECE) and cloud error vs CAD.

A *scene* is a rig + optics + gear + fringe period (from a rendered dataset's index, so the
validation scenes are exactly the unseen ones). A *motion* is the pair of frame-to-frame
rotation steps of a three-step burst (degrees). Methods map raw frames to a
:class:`PhaseResult`, so three-step PS, the network (deterministic or MC) and its peers are
scored the same way.
"""

from __future__ import annotations

import copy
import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gearscan.core.gear import GearSpec
from gearscan.core.patterns import PatternSet
from gearscan.core.phase import phase_error
from gearscan.core.rig import Rig
from gearscan.core.types import PhaseResult
from gearscan.twin.render import Optics, Truth, TwinRenderer

# frame-to-frame steps (deg): the paper's motions, a static reference and the §3.7 intervals
PAPER_MOTIONS = {"uniform 0.6/0.6": (0.6, 0.6), "non-uniform 0.1/1.6": (0.1, 1.6)}
STATIC = {"static": (0.0, 0.0)}
# the paper's motions with the turntable turning the other way
REVERSED = {"reversed uniform 0.6/0.6": (-0.6, -0.6), "reversed non-uniform 0.1/1.6": (-0.1, -1.6)}
GENERALISATION = {
    "uniform 0.5": (0.5, 0.5), "uniform 1": (1.0, 1.0), "uniform 2": (2.0, 2.0),
    "0.5+1": (0.5, 1.0), "1+2": (1.0, 2.0), "2+3": (2.0, 3.0),
}

Method = Callable[..., PhaseResult]  # (frames (3, H, W), full_scale, angles (3,) rad) -> PhaseResult


@dataclass
class Scene:
    name: str
    rig: Rig
    optics: Optics
    gear: GearSpec
    period_px: float
    _renderer: TwinRenderer | None = field(default=None, repr=False)
    _cad: tuple | None = field(default=None, repr=False)

    @property
    def renderer(self) -> TwinRenderer:
        if self._renderer is None:
            self._renderer = TwinRenderer(self.rig, self.gear, self.optics)
        return self._renderer

    @property
    def cad(self) -> tuple:
        """(Reconstructor, RaycastingScene of the CAD gear), built once per scene."""
        if self._cad is None:
            import open3d as o3d

            from gearscan.recon.measure import Reconstructor

            scene = o3d.t.geometry.RaycastingScene()
            scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(self.gear.mesh()))
            self._cad = (Reconstructor.for_gear(self.rig, self.period_px, self.gear), scene)
        return self._cad


def scenes_from_dataset(root: str | Path, limit: int | None = None) -> list[Scene]:
    """One scene per gear of a rendered twin dataset (its rig, optics, gear and period)."""
    index = json.loads((Path(root) / "index.json").read_text())
    seen: dict[int, Scene] = {}
    for e in index["entries"]:
        g = e["gear_index"]
        if g in seen:
            continue
        seen[g] = Scene(
            name=f"{Path(root).name}/gear{g} z={e['gear']['teeth']}",
            rig=Rig.from_json(e["rig"]), optics=Optics(**e["optics"]), gear=GearSpec(**e["gear"]),
            period_px=float(e["period_px"]),
        )
    return list(seen.values())[:limit]


def builtin_scenes(size: int = 256, seed: int = 25) -> list[Scene]:
    """Scenes needing no rendered dataset: the default rig and a randomised rig, gear z=25."""
    from gearscan.core.rig import default_rig
    from gearscan.twin.randomize import random_scene

    gear = GearSpec(teeth=25)
    rig = default_rig(size, size, working_radius=gear.pitch_radius)
    rnd = random_scene(np.random.default_rng(seed), gear, size, size)
    return [Scene("default rig z=25", rig, Optics(), gear, 40.0),
            Scene("random rig z=25", rnd[0], rnd[1], rnd[2], rnd[3])]


@dataclass
class BurstCase:
    """One rendered three-step burst with the truth at its first frame."""

    scene: Scene
    motion: str
    frames: np.ndarray  # (3, H, W) raw
    truth: Truth
    angles_deg: tuple[float, float, float]
    last_phase_abs: np.ndarray | None = None  # the truth's absolute phase at the third frame's pose

    def fringe_phase_change(self) -> np.ndarray:
        """``|phi_3 - phi_1|`` (rad) per pixel: how far the fringe phase seen at a camera pixel moves
        from frame 1 to frame 3, the physical cause of three-step PS's motion error (NaN where either
        frame does not see the lit surface, or unknown)."""
        if self.last_phase_abs is None:
            return np.full(self.truth.mask.shape, np.nan)
        return np.abs(self.last_phase_abs - self.truth.phase_abs)

    @property
    def full_scale(self) -> float:
        return float(self.scene.optics.full_scale)

    @property
    def angles_rad(self) -> np.ndarray:
        """The frames' turntable angles as the encoder reports them."""
        return np.radians(np.asarray(self.angles_deg, dtype=np.float64))


def render_cases(scene: Scene, motions: dict[str, tuple[float, float]], per_motion: int, seed: int = 0) -> list[BurstCase]:
    """``per_motion`` bursts per motion at random start angles within one tooth pitch."""
    rng = np.random.default_rng(seed)
    ps = PatternSet.three_step(scene.period_px)
    cases = []
    pitch = 360.0 / scene.gear.teeth
    for name, (d1, d2) in motions.items():
        for _ in range(per_motion):
            a0 = float(rng.uniform(0, pitch))
            angles = (a0, a0 + d1, a0 + d1 + d2)
            frames, truths = scene.renderer.render_sequence([math.radians(a) for a in angles], ps, [0, 1, 2], rng)
            cases.append(BurstCase(scene, name, frames, truths[0], angles, truths[2].phase_abs.astype(np.float32)))
    return cases


def classical_method(frames: np.ndarray, full_scale: float, angles: np.ndarray | None = None) -> PhaseResult:
    from gearscan.core.phase import classical_result
    from gearscan.core.types import Burst, Frame

    fr = tuple(Frame(f, i, 0, i, bit_depth=int(full_scale).bit_length()) for i, f in enumerate(frames))
    return classical_result(Burst(fr, (0.0, 0.0, 0.0)))


def network_method(predictor, mc: int = 0) -> Method:
    """``predictor`` as a method; ``network_support`` on it: the model's own fringe-support tests (the clouds'
    keep test, :func:`cloud_accuracy`)."""
    def run(frames: np.ndarray, full_scale: float, angles: np.ndarray | None = None) -> PhaseResult:
        return predictor.predict(frames, mc, full_scale=full_scale, angles=angles)

    run.network_support = getattr(predictor, "network_support", None)
    from gearscan.recon.depth_sigma import run_depth_sigma_scales

    # the clouds' sigma scales as the app picks them: the model's own (its JSON), else in MC mode the product's MC table
    run.depth_sigma_scales = run_depth_sigma_scales(getattr(predictor, "depth_sigma_scales", None), network=True, mc=mc)
    return run


@dataclass
class Score:
    method: str
    motion: str
    rmse_rad: float
    ece: float | None
    seconds_per_burst: float
    bursts: int
    cloud_rms_mm: float | None = None  # accuracy: distance of each point to the true surface point
    coverage: float | None = None  # share of the truth mask that got a point
    # the clouds' sigma against their depth error along each pixel's ray: median |error| / sigma (0.67 for a right
    # Gaussian sigma) and the share beyond 2 sigma (4.6 %); None without clouds
    cloud_z_median: float | None = None
    cloud_beyond_2sigma: float | None = None


def score(methods: dict[str, Method], cases: list[BurstCase], *, clouds: bool = False) -> list[Score]:
    """Pooled phase RMSE (valid pixels), ECE (30 bins, eps 0.03 rad) and time, per method and motion."""
    from gearscan.inference.uncertainty import reliability

    out = []
    motions = list(dict.fromkeys(c.motion for c in cases))
    for mname, method in methods.items():
        for motion in motions:
            sel = [c for c in cases if c.motion == motion]
            errs, sigmas, secs, cloud_sq, cloud_n, covered, truth_px, zs = [], [], 0.0, 0.0, 0, 0, 0, []
            for c in sel:
                t0 = time.perf_counter()
                res = method(c.frames, c.full_scale, c.angles_rad)
                secs += time.perf_counter() - t0
                m = c.truth.mask
                errs.append(phase_error(res.phase, c.truth.phase)[m])
                sigmas.append(res.sigma_total[m])
                if clouds:
                    d, hit, z = cloud_accuracy(c, res, model=getattr(method, "network_support", None),
                                               depth_sigma_scales=getattr(method, "depth_sigma_scales", None))
                    zs.append(z[np.isfinite(z)])
                    cloud_sq += float(np.sum(d**2))
                    cloud_n += d.size
                    covered += hit
                    truth_px += int(m.sum())
            err = np.concatenate(errs)
            sig = np.concatenate(sigmas)
            ece = None
            if np.any(sig > 0) and np.all(np.isfinite(sig)):  # only methods that state an uncertainty
                ece = reliability(err, np.maximum(sig, 1e-6)).ece
            honesty = z_summary(np.concatenate(zs) if zs else np.zeros(0))
            out.append(Score(mname, motion, float(np.sqrt(np.mean(err**2))), ece, secs / len(sel), len(sel),
                             math.sqrt(cloud_sq / cloud_n) if cloud_n else None,
                             covered / truth_px if (clouds and truth_px) else None,
                             honesty["median_z"], honesty["beyond_2sigma"]))
    return out


def cloud_accuracy(case: BurstCase, result: PhaseResult, model=None,
                   depth_sigma_scales=None) -> tuple[np.ndarray, int, np.ndarray]:
    """Distance (mm) of each point triangulated from ``result`` to the true gear surface, how
    many truth-mask pixels got a point (coverage numerator), and each point's depth error over its sigma
    (:func:`depth_z`; NaN where its pixel's ray meets no surface). A network's pixels pass the per-burst
    fringe-support test of the decoding ``model`` (its ``network_support``; None: the product's), as
    the app's reconstructor runs it.

    Scored against the twin's gear (the scene's gear is the one rendered), not the fringe orders'
    prior (DESIGN.md, "Numbers we can trust"); every point counts, edge and spurious ones included.
    Distance to the surface, not to the true point of the pixel's ray: a silhouette pixel whose blur
    mixes two surfaces measures the one in front, which its own ray just misses.
    """
    from dataclasses import replace

    from gearscan.core.types import Burst, Frame
    from gearscan.recon.measure import network_support_option

    rc, surface = case.scene.cad
    support = network_support_option(None, model=model)
    if support != rc.network_support_px:  # the scene's reconstructor, this model's keep test
        rc = copy.copy(rc)
        rc.network_support_px = support
    if depth_sigma_scales is not None:  # ... and its own depth-sigma scales (flat or per motion class)
        from gearscan.recon.depth_sigma import check_scales

        own = check_scales(depth_sigma_scales)
        if own != rc.depth_sigma_scales:
            rc = copy.copy(rc)
            rc.depth_sigma_scales = own
    fr = tuple(Frame(f, i, 0, i, bit_depth=int(case.full_scale).bit_length()) for i, f in enumerate(case.frames))
    angles = tuple(math.radians(a) for a in case.angles_deg)
    m = rc(Burst(fr, angles), replace(result, angle=angles[0]))
    if m.cloud is None or not len(m.cloud):
        return np.zeros(0), 0, np.zeros(0)
    rows, cols = m.cloud.pixels[:, 0], m.cloud.pixels[:, 1]
    return (surface_distances(surface, m.cloud.points), int(case.truth.mask[rows, cols].sum()),
            depth_z(surface, case.scene.rig, angles[0], m.cloud.points, m.cloud.sigma))


# a right Gaussian sigma: median |error| / sigma and its 95.45th percentile (the share beyond 2 sigma is 4.55 %)
GAUSS_MEDIAN_Z, GAUSS_Q9545_Z, GAUSS_BEYOND_2 = 0.6745, 2.0, 0.0455


def ray_errors(surface, points: np.ndarray, rays: np.ndarray, back_mm) -> np.ndarray:
    """Each point's signed error (mm) along its unit ray (+ beyond the surface, seen from the ray's start): where the
    ray started ``back_mm`` (scalar or per point) before the point first meets ``surface`` (an open3d
    ``RaycastingScene``); NaN where it meets nothing."""
    import open3d as o3d

    back = np.broadcast_to(np.asarray(back_mm, np.float64), (len(points),))
    origins = np.asarray(points, np.float64) - back[:, None] * rays
    hit = surface.cast_rays(o3d.core.Tensor(np.concatenate([origins, rays], axis=1).astype(np.float32)))["t_hit"]
    return back - hit.numpy().astype(np.float64)  # inf (a miss) becomes -inf: not finite either


def needed_scale(median_z: float, z_q9545: float) -> float:
    """The factor a sigma needs so that neither its body (median |error| / sigma) nor its tail (95.45th percentile)
    flatters: the larger of the two against a Gaussian's."""
    return max(median_z / GAUSS_MEDIAN_Z, z_q9545 / GAUSS_Q9545_Z)


def z_summary(z: np.ndarray) -> dict:
    """How well a sigma describes its errors, from ``z = |error| / sigma`` (finite values): the median, the share
    beyond 2 and the 95.45th percentile (a right Gaussian sigma: 0.6745, 4.55 %, 2) and :func:`needed_scale`; None
    each where ``z`` is empty."""
    if not z.size:
        return {"median_z": None, "beyond_2sigma": None, "z_q9545": None, "needed_scale": None}
    med, q = float(np.median(z)), float(np.quantile(z, 0.9545))
    return {"median_z": med, "beyond_2sigma": float(np.mean(z > 2)), "z_q9545": q, "needed_scale": needed_scale(med, q)}


def depth_z(surface, rig: Rig, angle: float, points: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """|depth error| / sigma of gear-frame ``points`` seen at turntable ``angle`` (rad), whose ``sigma`` is a camera-
    depth standard error (:class:`~gearscan.core.types.Cloud`): along each point's own camera ray the true surface is
    where the ray from the camera centre first meets ``surface`` (:func:`ray_errors`); the depth error is the distance
    between the two along the ray times the cosine to the optical axis. NaN where the ray meets nothing."""
    from gearscan.core.rig import rot_z

    gear_to_cam = rig.camera.T_from_world @ rot_z(angle)
    centre = np.linalg.inv(gear_to_cam)[:3, 3]
    offset = np.asarray(points, np.float64) - centre
    dist = np.linalg.norm(offset, axis=1)
    err = ray_errors(surface, points, offset / dist[:, None], dist)  # every ray starts at the camera centre
    cos_axis = (points @ gear_to_cam[2, :3] + gear_to_cam[2, 3]) / dist  # camera depth over distance
    with np.errstate(invalid="ignore"):
        return np.where(np.isfinite(err), np.abs(err) * cos_axis / np.asarray(sigma, np.float64), np.nan)


def surface_distances(surface, points: np.ndarray) -> np.ndarray:
    """Distance (mm, float64) of each of ``points`` (N, 3) to ``surface`` (an open3d ``RaycastingScene``)."""
    import open3d as o3d

    return surface.compute_distance(o3d.core.Tensor(np.ascontiguousarray(points, dtype=np.float32))).numpy().astype(np.float64)


def scores_table(scores: list[Score], baseline: str = "three-step PS") -> str:
    """Markdown table: RMSE per method and motion, with the ratio to the baseline."""
    base = {s.motion: s.rmse_rad for s in scores if s.method == baseline}
    lines = ["| method | motion | phase RMSE (rad) | vs three-step | ECE | cloud RMS vs truth (mm) | coverage | "
             "cloud sigma: median abs(err)/sigma, beyond 2 sigma | s/burst |",
             "|---|---|---|---|---|---|---|---|---|"]
    for s in scores:
        ratio = base.get(s.motion, float("nan")) / s.rmse_rad if s.rmse_rad > 0 else float("nan")
        lines.append(
            f"| {s.method} | {s.motion} | {s.rmse_rad:.4f} | {ratio:.1f}x | "
            f"{'' if s.ece is None else f'{s.ece:.3f}'} | "
            f"{'' if s.cloud_rms_mm is None else f'{s.cloud_rms_mm:.4f}'} | "
            f"{'' if s.coverage is None else f'{100 * s.coverage:.1f} %'} | "
            f"{'' if s.cloud_z_median is None else f'{s.cloud_z_median:.2f}, {100 * s.cloud_beyond_2sigma:.1f} %'} | "
            f"{s.seconds_per_burst:.3f} |"
        )
    return "\n".join(lines)


GROSS_MM = 0.5  # a point this far from the true surface has a wrong fringe order or none of the surface's light
# the motions of a val cloud sample: the paper's (still, the paper's two motions both ways; the choices until session
# 45) or wide (those and the 0.5-3 deg steps users and the test split bring: GENERALISATION)
VAL_MOTIONS: dict[str, dict[str, tuple[float, float]]] = {
    "paper": {**STATIC, **PAPER_MOTIONS, **REVERSED},
    "wide": {**STATIC, **PAPER_MOTIONS, **REVERSED, **GENERALISATION},
}
# the val scenes of the reconstruction's per-burst choices: every gear of the twin's val sets and the default rig's
VAL_CLOUD_SETS = ("data/repro/val_radial", "data/repro/val_views", *(f"data/default_rig/val/z{z}" for z in (25, 32, 46, 62)))


def val_cloud_table(predictor, scenes: list[Scene], configs: dict[str, dict], *, seed: int, per_motion: int,
                    three_step: str, progress: Callable[[str], None] | None = None,
                    motions: str = "paper") -> dict[str, dict[str, dict]]:
    """Per-burst clouds of still and moving bursts scored against the true gear surface, for the val choices of
    the reconstructor's keep tests (``scripts/choose_network_support.py``, ``scripts/choose_keep_bound.py``).

    Per scene, ``per_motion`` bursts of each motion of ``VAL_MOTIONS[motions]`` (seeds ``seed`` + scene index);
    ``predictor`` (deterministic) decodes each burst once and every ``configs`` entry (keyword arguments of
    :class:`~gearscan.recon.measure.Reconstructor`) reconstructs it; three-step PS's phase goes through the
    reconstructor of ``configs[three_step]`` as row "three-step". ``table[name][kind]`` (kinds "still",
    "moving"): points, RMS over every point, RMS with each distance clipped at :data:`GROSS_MM`, the
    points beyond it ("gross"), coverage of the truth mask and the pixels the fringe-support test removed."""
    from dataclasses import replace

    from gearscan.core.types import Burst, Frame
    from gearscan.recon.measure import Reconstructor

    if motions not in VAL_MOTIONS:
        raise ValueError(f"motions: expected one of {', '.join(VAL_MOTIONS)}, got {motions!r}")
    sums: dict[tuple[str, str], list[float]] = {}
    for i, scene in enumerate(scenes):
        surface = scene.cad[1]  # the true gear surface cloud_accuracy scores against
        recons = {name: Reconstructor.for_gear(scene.rig, scene.period_px, scene.gear, **kw) for name, kw in configs.items()}
        try:
            for case in render_cases(scene, VAL_MOTIONS[motions], per_motion, seed=seed + i):
                fr = tuple(Frame(f, j, 0, j, bit_depth=int(case.full_scale).bit_length()) for j, f in enumerate(case.frames))
                burst = Burst(fr, tuple(math.radians(a) for a in case.angles_deg))
                kind = "still" if case.motion == "static" else "moving"
                net = replace(predictor.predict(case.frames, 0, full_scale=case.full_scale), angle=burst.angles[0])
                three = replace(classical_method(case.frames, case.full_scale), angle=burst.angles[0])
                runs = [(name, rc, net) for name, rc in recons.items()] + [("three-step", recons[three_step], three)]
                for name, rc, result in runs:
                    m = rc(burst, result)
                    acc = sums.setdefault((name, kind), [0.0] * 7)
                    acc[3] += float(case.truth.mask.sum())
                    acc[4] += m.unwrap.get("unsupported", 0)
                    if m.cloud is None or not len(m.cloud):
                        continue
                    d = surface_distances(surface, m.cloud.points)
                    acc[0] += d.size
                    acc[1] += float(np.sum(d**2))
                    acc[2] += float(case.truth.mask[m.cloud.pixels[:, 0], m.cloud.pixels[:, 1]].sum())
                    acc[5] += float(np.sum(np.minimum(d, GROSS_MM) ** 2))
                    acc[6] += float(np.sum(d > GROSS_MM))
        finally:
            for rc in recons.values():
                rc.close()
        if progress is not None:
            progress(f"{i + 1}/{len(scenes)} {scene.name}")
    table: dict[str, dict[str, dict]] = {}
    for (name, kind), (n, sse, hit, truth, unsupported, clipped, gross) in sums.items():
        table.setdefault(name, {})[kind] = {
            "points": int(n), "rms_um": 1000 * math.sqrt(sse / n) if n else math.nan,
            "clipped_rms_um": 1000 * math.sqrt(clipped / n) if n else math.nan, "gross": int(gross),
            "coverage": hit / truth, "unsupported": int(unsupported)}
    return table
