"""Inspection benchmark (issue 14, item 5): a twin revolution with known defects, inspected.

Twin: default rig, 512x512, 20-tooth module-2 gear, 0.6 deg/frame (200 three-frame bursts = one
revolution), eccentric mounting 50 µm, tooth 3 turned +30 µm along the pitch circle, tooth 7's
tip corner chipped 0.3 mm. ``gearscan inspect`` (shipped network, deterministic) fuses the
revolution (once fused only, once with the frame fit of recon/track.py) and reads fp, Fp, Fr; the
fused cloud is scored against the TRUE (as-built) mesh,
not the CAD. Writes ``benchmarks/inspect_report.md`` (+ ``.json``) with host and commit.

    python benchmarks/inspect_bench.py [--recording DIR] [--classical] [--fixed-order] [--compare]
    python benchmarks/inspect_bench.py --deg-per-frame 1.2 --report benchmarks/inspect_fast_report   # a faster turn

``--deg-per-frame`` renders the same gear and defects turning faster (one revolution: round(120 / speed) bursts)
into its own recording; the speed and burst count in the report are read from the recording.

The revolution is recorded with every other burst in the order 0, 2, 1 (projector.alternate_order)
unless ``--fixed-order``; ``--compare`` also fits the same revolution recorded the other way.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import subprocess
import time
from pathlib import Path

import numpy as np

from gearscan.provenance import code_edits

HERE = Path(__file__).resolve().parent
DEFECTS = {"eccentricity_um": 50.0, "pitch_errors": ["3:30"], "chips": ["7:0.3"]}


def host() -> str:
    cpu = next((ln.split(":", 1)[1].strip() for ln in Path("/proc/cpuinfo").read_text().splitlines()
                if ln.startswith("model name")), platform.processor())
    flags = Path("/proc/cpuinfo").read_text()
    isa = ", ".join(f for f in ("avx512f", "amx_tile") if f in flags) or "no AVX-512/AMX"
    return f"{cpu}, {len(os.sched_getaffinity(0))} cores ({isa}), 1-min load {os.getloadavg()[0]:.2f} at start"


@functools.cache
def commit() -> str:
    """HEAD, marked when tracked files carry uncommitted edits (the report then ran code HEAD lacks).

    Cached: the first call (before a report writes its own files) is the one that counts."""
    try:
        head = subprocess.check_output(["git", "rev-parse", "--short", "HEAD"], cwd=HERE, text=True).strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return f"{head} + uncommitted edits" if code_edits(HERE.parent) else head


def motion_text(motion: str) -> str:
    """``uniform:0.6`` as the report says it (0.6°/frame); any other motion spelled as the twin's option."""
    kind, _, value = motion.partition(":")
    return f"{value}°/frame" if kind == "uniform" and value else motion


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--recording", type=Path, default=None,
                    help="default: out/inspect_bench/rec_alternate (or rec_fixed with --fixed-order)")
    ap.add_argument("--fixed-order", action="store_true",
                    help="every burst in the order 0, 1, 2 (default: every other one 0, 2, 1, as projector.alternate_order)")
    ap.add_argument("--compare", action="store_true",
                    help="also fit the same revolution recorded in the other pattern order and report both")
    ap.add_argument("--out", type=Path, default=Path("out/inspect_bench/report"))
    ap.add_argument("--classical", action="store_true", help="three-step PS instead of the network")
    ap.add_argument("--model", type=Path, default=None, help="network weights (.safetensors); default: the shipped model")
    ap.add_argument("--report", type=Path, default=HERE / "inspect_report",
                    help="path prefix of the report (.md, .json); default benchmarks/inspect_report")
    ap.add_argument("--orientation", choices=("auto", "normal", "mirrored"), default="auto",
                    help="the network's fringe orientation (the Decoder's; auto: the shipped default, from the rig "
                         "calibration since session 43; normal: the twin rig's, set)")
    ap.add_argument("--network-support-px", type=int, default=None,
                    help="the reconstructor's fringe-support test for network pixels (-1: none; default: the model's own, else the product's)")
    ap.add_argument("--deg-per-frame", type=float, default=0.6,
                    help="turntable speed of the rendered revolution, deg per frame (default 0.6: the benchmark's; "
                         "another speed renders its own recording of one revolution, round(120 / speed) bursts)")
    ap.add_argument("--rig", type=Path, default=None,
                    help="measure with this rig calibration (e.g. from `gearscan calibrate --twin default`) instead of "
                         "the twin's true rig the recording holds: what a user's own calibration leaves")
    ap.add_argument("--voxel-mm", type=float, default=0.1)
    ap.add_argument("--min-bursts", type=int, default=3)
    args = ap.parse_args()
    if not 0 < args.deg_per_frame <= 6:
        ap.error(f"--deg-per-frame: expected a speed in (0, 6] deg per frame, got {args.deg_per_frame}")
    commit()  # before this run writes its report: a tree dirty with it is not an edit

    import open3d as o3d

    from gearscan.core.recording import RecordingReader
    from gearscan.inference.decoder import Decoder
    from gearscan.inspect import chip_verdict, run_inspection
    from gearscan.recon.depth_sigma import DEPTH_SIGMA_SCALES, check_scales
    from gearscan.recon.measure import keep_bound_option, network_support_option
    from gearscan.recon.track import FIT_SIGMA_SCALE, MODULATION_RATIO, SETTLE_RAD
    from gearscan.twin.defects import GearDefects, true_mesh

    started = host()
    alternate = not args.fixed_order

    def recording(alt: bool) -> Path:
        speed = "" if args.deg_per_frame == 0.6 else f"_{args.deg_per_frame:g}deg"
        path = args.recording if args.recording is not None and alt == alternate else \
            Path(f"out/inspect_bench/rec_{'alternate' if alt else 'fixed'}{speed}")
        if not (path / "recording.json").exists():
            from gearscan.twin.recordings import render_recording

            t = time.perf_counter()
            render_recording(path, defects=GearDefects.from_options(
                eccentricity_um=DEFECTS["eccentricity_um"], pitch_errors=DEFECTS["pitch_errors"], chips=DEFECTS["chips"]),
                motion=f"uniform:{args.deg_per_frame:g}", bursts=round(120 / args.deg_per_frame), alternate_order=alt)
            print(f"rendered {path} in {time.perf_counter() - t:.0f} s")
        return path

    args.recording = recording(alternate)
    reader = RecordingReader(args.recording)
    truth = reader.meta["truth"]
    motion = reader.meta.get("twin", {}).get("motion", "unknown motion")  # what the recording was rendered with
    bursts = reader.meta["frame_count"] // 3
    decoder = Decoder(args.model, classical=args.classical, orientation=args.orientation)
    depth_scales = check_scales(decoder.depth_sigma_scales or DEPTH_SIGMA_SCALES)  # what the reconstructor reads (the model's own)
    # the frame-fit path's test (the model's own for inspect, else the product's) and keep bound on both runs: the
    # fused-only run is the same fused cloud before the fit, voxel for voxel (the 'before' figures below rely on it)
    support = network_support_option(args.network_support_px, frame_fit=True, model=decoder.network_support)
    bound = keep_bound_option(None, frame_fit=True)
    per_burst = network_support_option(None, frame_fit=False, model=decoder.network_support)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(true_mesh(reader.gear, GearDefects.from_meta(reader.meta))))

    def distance(points: np.ndarray) -> np.ndarray:
        return np.abs(scene.compute_signed_distance(o3d.core.Tensor(points.astype(np.float32))).numpy())

    # the same revolution without the frame fit: what the fit adds, on this run's host and commit
    t = time.perf_counter()
    plain = run_inspection(args.recording, args.out / "plain", decoder=decoder, grade=8, voxel_mm=args.voxel_mm,
                           min_bursts=args.min_bursts, refine=False, progress=print, network_support_px=support,
                           max_sigma=bound, rig=args.rig)
    plain_seconds = time.perf_counter() - t
    plain_dist = distance(plain.fused.points)
    t = time.perf_counter()
    report = run_inspection(args.recording, args.out, decoder=decoder, grade=8,
                            voxel_mm=args.voxel_mm, min_bursts=args.min_bursts, refine=True, progress=print,
                            network_support_px=support, max_sigma=bound, rig=args.rig)
    seconds = time.perf_counter() - t
    insp, fused = report.inspection, report.fused
    rest_scale = report.rest_sigma_scale  # what the frame fit's unfitted points carried (the model's own, else the product's)
    dist = distance(fused.points)
    # coverage: share of the true surface (sampled uniformly) with a fused point within 2 voxels
    o3d.utility.random.seed(0)
    samples = np.asarray(true_mesh(reader.gear, GearDefects.from_meta(reader.meta)).sample_points_uniformly(200_000).points)
    pcd = lambda pts: o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))  # noqa: E731
    flank_side = np.abs(samples[:, 2]) < reader.gear.face_width / 2 - 1e-3  # not the two end faces

    def coverage_of(points: np.ndarray) -> float:
        near = np.asarray(pcd(samples).compute_point_cloud_distance(pcd(points))) <= 2 * args.voxel_mm
        return float(near[flank_side].mean())

    coverage = coverage_of(fused.points)

    def rms_of(d: np.ndarray) -> float | None:
        return float(np.sqrt(np.mean(d**2))) if d.size else None  # None: no such point (valid JSON, unlike NaN)

    def um(x: float | None) -> str:
        return "none" if x is None else f"{1e3 * x:.1f}"

    def order_row(name: str, rep, d: np.ndarray, cov: float) -> dict:
        r = rep.fused.refined
        return {"order": name, "points": len(rep.fused), "coverage": cov, "fitted": float(r.mean()),
                "fitted_rms_mm": rms_of(d[r]), "kept_rms_mm": rms_of(d[~r]), "rms_mm": rms_of(d),
                "p95_mm": float(np.percentile(d, 95)), "fp_max_error_um": fp_error(rep.inspection),
                "chip": chip_verdict(rep.inspection)}

    refined = fused.refined
    strata = []
    for lo, hi in ((args.min_bursts, 5), (5, 10), (10, 20), (20, 10**6)):
        k = (fused.bursts >= lo) & (fused.bursts < hi)
        kp = (plain.fused.bursts >= lo) & (plain.fused.bursts < hi)
        if k.any():
            strata.append((f"{lo}-{hi - 1}" if hi < 10**6 else f">= {lo}", int(k.sum()), rms_of(plain_dist[kp]),
                           rms_of(dist[k]), float(np.percentile(dist[k], 95)), float(refined[k].mean()),
                           rms_of(dist[k & refined])))
    rms = rms_of(dist)
    plain_rms = rms_of(plain_dist)
    rms_refined, rms_kept = rms_of(dist[refined]), rms_of(dist[~refined])
    # the same points before the fit: the plain run fused the same voxels in the same order
    rows_in_plain = fused.voxel_index if fused.voxel_index is not None else np.arange(len(fused))
    before_refined = rms_of(plain_dist[rows_in_plain][refined])
    off_surface = (report.refine or {}).get("off_surface", 0)  # unfitted points off the fitted surface, dropped
    uncertain = (report.refine or {}).get("uncertain", 0)  # unfitted points above the sigma bound, dropped
    unsettled = (report.refine or {}).get("unsettled", 0)  # fits still moving at the last iteration, not taken
    implausible = (report.refine or {}).get("implausible", 0)  # fits with a modulation above their mean intensity
    e_true = 1e3 * float(np.hypot(*truth["eccentricity_mm"]))
    def quantities(i) -> list[float]:
        return [i.eccentricity_um, i.runout_from_eccentricity_um, i.Fp_um["left"], i.Fp_um["right"],
                i.single_pitch_um["left"][3], i.single_pitch_um["right"][3]]

    def fp_error(i) -> float:
        return max(float(np.nanmax(np.abs(np.asarray(i.single_pitch_um[s]) - np.asarray(truth["single_pitch_um"][s]))))
                   for s in ("left", "right"))

    order_name = "alternating (0, 1, 2 / 0, 2, 1)" if alternate else "fixed (0, 1, 2)"
    orders = [order_row(order_name, report, dist, coverage)]
    if args.compare:
        other = recording(not alternate)
        t = time.perf_counter()
        rep2 = run_inspection(other, args.out / "other_order", decoder=decoder, grade=8, voxel_mm=args.voxel_mm,
                              min_bursts=args.min_bursts, refine=True, progress=print, network_support_px=support,
                              rig=args.rig)
        print(f"other order: {time.perf_counter() - t:.0f} s")
        orders.append(order_row("fixed (0, 1, 2)" if alternate else "alternating (0, 1, 2 / 0, 2, 1)", rep2,
                                distance(rep2.fused.points), coverage_of(rep2.fused.points)))
    names = ["eccentricity (µm)", "runout from eccentricity (µm)", "Fp left (µm)", "Fp right (µm)",
             "fp tooth 3 left (µm)", "fp tooth 3 right (µm)"]
    truths = [e_true, truth["runout_from_eccentricity_um"], truth["total_cumulative_pitch_um"]["left"],
              truth["total_cumulative_pitch_um"]["right"], truth["single_pitch_um"]["left"][3],
              truth["single_pitch_um"]["right"][3]]
    rows = list(zip(names, truths, quantities(insp), quantities(plain.inspection), strict=True))
    fp_err, plain_fp_err = fp_error(insp), fp_error(plain.inspection)
    ok = lambda t, m: abs(m - t) <= 5 + 0.05 * abs(t)  # noqa: E731
    ran = decoder.summary()  # the orientation the last run decoded with (every run here replays the same rig), and whence
    fringes = (f"set: {args.orientation}" if args.orientation != "auto" else
               f"auto, the shipped default: {ran['rig_orientation']} from the {ran['orientation_source']}"
               if ran["rig_orientation"] else "auto, the shipped default: voted per burst")
    decoder_obj, decoder = decoder, "three-step PS" if args.classical else (
        (f"network `{args.model}` (deterministic" if args.model else "shipped network (deterministic")
        + f", fringe orientation {fringes})")
    if not args.classical:
        whose = "the model's own" if decoder_obj.network_support is not None else "the product's"
        px = lambda v: "off" if v is None else f"{v} px"  # noqa: E731
        decoder += (f"; fringe-support test {px(support)} ({whose} with the frame fit; "
                    f"`replay --fuse --no-refine` runs {px(per_burst)}) on both runs" if args.network_support_px is None
                    else "; no fringe-support test" if support is None else f"; fringe-support test {support} px")
    decoder += f"; keep bound {bound:g} rad (the frame-fit path's) on both runs"
    lines = [
        "# Inspection benchmark (issue 14: fused revolution, ISO 1328-1 pitch and runout)",
        "",
        f"`python benchmarks/inspect_bench.py{'' if args.orientation == 'auto' else ' --orientation ' + args.orientation}"
        f"{f' --model {args.model}' if args.model else ''}"
        f"{'' if args.network_support_px is None else f' --network-support-px {args.network_support_px}'}"
        f"{'' if args.deg_per_frame == 0.6 else f' --deg-per-frame {args.deg_per_frame:g}'}"
        f"{'' if args.rig is None else f' --rig {args.rig}'}`"
        f" — commit {commit()}, host: {started}.",
        "",
        f"Twin: default rig 512x512, z = 20, m = 2 mm, {motion_text(motion)}, {bursts} bursts ({report.revolution_deg:.0f}° of encoder "
        f"angle), eccentricity 50 µm, tooth 3 +30 µm pitch error, tooth 7 tip chipped 0.3 mm; pattern order "
        f"{order_name}. Decoder: {decoder}. "
        + ("Measured with the twin's true rig (the recording's). " if args.rig is None else
           f"Measured with the rig calibration `{args.rig}` instead of the twin's true rig (the recording's): what a "
           "user's own calibration leaves. ") +
        f"Replay + fusion + inspection: {seconds:.0f} s (the recording rendered beforehand by this script's "
        f"render step, or `gearscan twin render REC --bursts {bursts} --motion {motion} --eccentricity-um 50 "
        f"--pitch-error 3:30 --chip 7:0.3{' --alternate-order' if alternate else ''}`).",
        "",
        "## Inspection vs the twin's truth (acceptance: within 5 µm + 5 %)",
        "",
        "| quantity | truth | measured | within | fused only (no frame fit) |",
        "|---|---|---|---|---|",
        *[f"| {name} | {t:.1f} | {m:.1f} | {'yes' if ok(t, m) else 'NO'} | {m0:.1f} |" for name, t, m, m0 in rows],
        f"| largest per-tooth fp error, both sides (µm) | 0 | {fp_err:.1f} | {'yes' if fp_err <= 5 + 0.05 * 30 else 'NO'} "
        f"| {plain_fp_err:.1f} |",
        f"| chipped teeth | {truth['chipped_teeth']} | {chip_verdict(insp)} | "
        f"{'yes' if insp.chip_check_conclusive and list(insp.chipped_teeth) == truth['chipped_teeth'] else 'NO'} "
        f"| {chip_verdict(plain.inspection)} |",
        "",
        f"Ball-probe runout Fr (about the turntable axis, spaces included): {insp.Fr_um:.1f} µm; the tooth "
        f"spaces alone (about the gear axis): {insp.runout_about_gear_axis_um:.1f} µm (tooth 3's +30 µm narrows one "
        "space and widens the next: ±41 µm of ball height at 20° pressure angle).",
        "",
        "Chipped-tooth check: tooth-local cells of each tip zone against the median tooth; the "
        "largest missing area per tooth (mm²): " + ", ".join(f"{t.tooth}: {t.missing_mm2:.1f}" for t in
                                                            sorted(insp.tips, key=lambda t: -t.missing_mm2)[:5])
        + f". The cells' spread around the median tooth (95th percentile) is {insp.chip_noise_um:.1f} µm against "
        f"the {1e3 * insp.settings['chip_mm']:.0f} µm chip threshold: the check is "
        f"{'conclusive' if insp.chip_check_conclusive else 'inconclusive (it flags nothing rather than noise)'}. "
        f"Fused only, the spread is {plain.inspection.chip_noise_um:.1f} µm and the check "
        + (f"conclusive: it flags teeth {', '.join(str(t) for t in plain.inspection.chipped_teeth) or 'none'} "
           f"against the true {truth['chipped_teeth']}." if plain.inspection.chip_check_conclusive else
           "inconclusive: without the frame fit the moving cloud is too noisy to tell a chip from noise (it refuses "
           "to answer rather than flag intact teeth)."),
        "",
        "## Fused cloud vs the true (as-built) surface",
        "",
        f"{len(fused):,} fused points (voxel {args.voxel_mm} mm, kept when seen by >= {args.min_bursts} bursts; median "
        f"{np.median(fused.bursts):.0f} bursts per point); coverage {100 * coverage:.1f} % of the true tooth surface "
        f"(end faces excluded) has a fused point within {2 * args.voxel_mm:g} mm.",
        "",
        f"**RMS distance to the true surface: {rms * 1e3:.1f} µm** (p95 {1e3 * np.percentile(dist, 95):.1f} µm); "
        f"target <= 10 µm: {'met' if rms <= 0.01 else 'NOT met'}. Without the frame fit (the same revolution, "
        f"fused only, {plain_seconds:.0f} s): {plain_rms * 1e3:.1f} µm.",
        "",
        f"Frame fit (`recon/track.py`, on by default in `inspect` and `replay --fuse`): "
        f"{100 * refined.mean():.1f} % of the fused points were fitted to the raw frames that saw them "
        f"({1e3 * before_refined:.1f} µm before, **{1e3 * rms_refined:.1f} µm after**); "
        + (f"the other {(~refined).sum():,} ({100 * (1 - refined.mean()):.1f} %) keep their fused position "
           f"({1e3 * rms_kept:.1f} µm)" if (~refined).any() else "no unfitted point is left in the cloud")
        + f". A point the fit cannot take has a fit sigma above 30 µm (the fit's standard error along the ray times "
        f"{FIT_SIGMA_SCALE:g}, `recon.track.FIT_SIGMA_SCALE`, calibrated on val: `fit_sigma_rule.md`; too few frames, or fringe phases too close to two "
        "opposite ones to tell sine from cosine; with every burst in the order 0, 1, 2 a point whose fringes move a "
        "sixth of a period per frame sees only 0 and pi, burst after burst), or a fit that had not settled: "
        + ("no settle test ran. " if SETTLE_RAD is None else
           f"{unsettled:,} fits still corrected more than {SETTLE_RAD:g} rad at their last iteration "
           "(`recon.track.SETTLE_RAD`, chosen on val stretches: `frame_fit_settle_rule.md`). ")
        + ("" if MODULATION_RATIO is None else
           f"{implausible:,} fits had a modulation B above {MODULATION_RATIO:g} x their mean intensity A, an impossible "
           "fringe (`recon.track.MODULATION_RATIO`, `frame_fit_modulation_rule.md`), and were not taken. ")
        +
        f"{off_surface:,} points the fit could not take lay more than 0.15 mm off the plane of the fitted points "
        "within 0.5 mm and were dropped (counted; `recon.track.off_surface`): silhouette and shadow-edge pixels that "
        "several bursts put in one voxel. These settings were chosen on this revolution. "
        f"{uncertain:,} more unfitted points carried a sigma above the fit's own 30 µm bound and were dropped (counted; "
        "`TrackRefiner.refine_fused`: one bound for every point of the refined cloud; a rule, not tuned here; an "
        f"unfitted point carries {rest_scale:g} times its bursts' sigma (each burst's scaled by distance to its "
        f"cloud's edge, {depth_scales.describe()} from the edge inward: `depth_sigma_rule.md`) "
        "without credit for averaging, "
        "calibrated on val stretches: `rest_sigma_rule.md`).",
        "",
        *([
            "## Pattern order: the same revolution shown both ways",
            "",
            "At 0.6°/frame a fringe that moves a sixth of a period per frame steps the phase a point sees by "
            "2pi/3 + pi/3 = pi every frame when the bursts are all 0, 1, 2: those points are seen at two opposite "
            "phases only, and the fit cannot place them. Every other burst in the order 0, 2, 1 "
            "(`[projector] alternate_order`, `twin render --alternate-order`) steps them by -pi/3 there.",
            "",
            "| pattern order | fused points | coverage | fitted | RMS of the fitted (µm) | RMS of the rest (µm) | "
            "RMS whole cloud (µm) | p95 (µm) | largest fp error (µm) | chipped teeth |",
            "|---|---|---|---|---|---|---|---|---|---|",
            *[f"| {o['order']} | {o['points']:,} | {100 * o['coverage']:.1f} % | {100 * o['fitted']:.1f} % | "
              f"{um(o['fitted_rms_mm'])} | {um(o['kept_rms_mm'])} | **{1e3 * o['rms_mm']:.1f}** | "
              f"{1e3 * o['p95_mm']:.1f} | {o['fp_max_error_um']:.1f} | {o['chip']} |" for o in orders],
            "",
        ] if len(orders) > 1 else []),
        "| bursts per fused point | points | RMS fused only (µm) | RMS with the fit (µm) | p95 (µm) | fitted | RMS of the fitted (µm) |",
        "|---|---|---|---|---|---|---|",
        *[f"| {name} | {n:,} | {um(r0)} | {um(r)} | {1e3 * p:.1f} | {100 * f:.0f} % | {um(rf)} |"
          for name, n, r0, r, p, f, rf in strata],
        "",
        "Fused only, the error falls with the number of bursts that saw a point, as independent errors "
        "would, but each burst carries the network's motion-corrected error (about 0.1 mm RMS per burst at "
        "0.6°/frame on this rig) and a flank point is seen in only a handful of bursts per revolution. The "
        "frame fit does not average burst results: it solves each point's phase from all its frames at once "
        "(the motion is known from the encoder), so what is left is camera noise. Pitch and runout need far "
        "less: they average whole flanks, and every tooth is seen through the same sequence of views, so "
        "errors common to all teeth cancel.",
        "",
    ]
    args.report.with_suffix(".md").write_text("\n".join(lines))
    args.report.with_suffix(".json").write_text(json.dumps({
        "commit": commit(), "host": started, "motion": motion, "bursts": bursts,
        "rig": None if args.rig is None else str(args.rig), "seconds": seconds, "decoder": decoder, "max_sigma_rad": bound,
        "fused_rms_mm": rms, "fused_p95_mm": float(np.percentile(dist, 95)), "coverage": coverage,
        "fused_only_rms_mm": plain_rms, "refined_fraction": float(refined.mean()), "refined_rms_mm": rms_refined,
        "refined_before_rms_mm": before_refined, "kept_rms_mm": rms_kept, "plain_seconds": plain_seconds,
        "off_surface": off_surface,
        "uncertain": uncertain,
        "unsettled": unsettled,
        "settle_rad": SETTLE_RAD, "fit_sigma_scale": FIT_SIGMA_SCALE,
        "rest_sigma_scale": rest_scale, "rest_sigma_source": report.rest_sigma_source, "depth_sigma_scales": depth_scales.as_dict(),
        "implausible": implausible,
        "modulation_ratio": MODULATION_RATIO,
        "strata": strata, "rows": rows, "fp_max_error_um": fp_err, "fused_only_fp_max_error_um": plain_fp_err,
        "fused_only_chip_noise_um": plain.inspection.chip_noise_um, "chip_noise_um": insp.chip_noise_um, "chipped": list(insp.chipped_teeth),
        "truth_chipped": truth["chipped_teeth"], "Fr_um": insp.Fr_um, "pattern_order": order_name,
        "orders": orders}, indent=2))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
