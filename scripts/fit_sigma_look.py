"""Dev look (VAL only, nothing chosen): the frame fit's sigma against its error along the ray and normal to the surface.

    python scripts/fit_sigma_look.py out/fused_support_val/seed31_alternate [--fit-sigma-scale 1]

Replays one val stretch with fusion and the frame fit (every setting as shipped but the fit's sigma scale), then for
the fitted points: |error| / sigma along each point's ray (``frame_fit_heldout.ray_error_mm``) and with the distance
normal to the true surface instead, the cosine between ray and surface normal, and the along-ray honesty
(``gearscan.evaluate.z_summary``) by the fit's sigma and by its sample count. What shaped ``fit_sigma_rule.md``
(session 49, seed 31 in both orders, at scale 1) and its next step (an additive floor).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "scripts"))
from choose_frame_fit_settle import _KeepingRefiner  # noqa: E402
from frame_fit_heldout import ray_error_mm, truth_scene  # noqa: E402

SIGMA_BINS_UM = (0, 2, 4, 8, 16, 31)
FRAME_BINS = (9, 15, 20, 30, 45, 70, 10**6)


def binned(z: np.ndarray, key: np.ndarray, edges) -> dict:
    """:func:`gearscan.evaluate.z_summary` of ``z`` per bin of ``key``."""
    from gearscan.evaluate import z_summary

    return {f"{lo:g}-{hi:g}": {"points": int(k.sum()), **z_summary(z[k])}
            for lo, hi in zip(edges[:-1], edges[1:], strict=False) if (k := (key >= lo) & (key < hi)).any()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recording", type=Path)
    ap.add_argument("--fit-sigma-scale", type=float, default=1.0)
    args = ap.parse_args()

    import open3d as o3d

    from gearscan.core.recording import RecordingReader
    from gearscan.evaluate import z_summary
    from gearscan.inference.decoder import Decoder
    from gearscan.recon.fuse import CloudFuser
    from gearscan.replay import replay

    kept: list[_KeepingRefiner] = []

    def factory(rig, period_px, rest_sigma_scale):
        kept.append(_KeepingRefiner(rig, period_px, fit_sigma_scale=args.fit_sigma_scale, rest_sigma_scale=rest_sigma_scale))
        return kept[-1]

    replay(args.recording, decoder=Decoder(None), fuse=CloudFuser(0.1, 3), truth=False, refine=True,
           refiner_factory=factory)
    res = kept[0].refine(kept[0].fused.points)  # every fitted point before the cloud's drops, with its frames
    r = res.refined
    pts, sig, rays, frames = res.points[r], 1e3 * res.sigma[r], res.rays[r], res.frames[r]
    scene = truth_scene(RecordingReader(args.recording))
    along = 1e3 * ray_error_mm(scene, pts, rays)
    closest = scene.compute_closest_points(o3d.core.Tensor(pts.astype(np.float32)))
    normal = 1e3 * np.abs(scene.compute_signed_distance(o3d.core.Tensor(pts.astype(np.float32))).numpy())
    cos = np.abs(np.einsum("ij,ij->i", closest["primitive_normals"].numpy(), rays))
    ok = np.isfinite(along)
    z, zn = np.abs(along[ok]) / sig[ok], normal / sig
    out = {"recording": str(args.recording), "split": "val", "fit_sigma_scale": args.fit_sigma_scale,
           "fitted": int(r.sum()), "measured": float(ok.mean()), "median_cos": float(np.median(cos)),
           "along_ray": {**z_summary(z), "q95": float(np.quantile(z, 0.95))},
           "normal": {**z_summary(zn), "q95": float(np.quantile(zn, 0.95))},
           "by_sigma_um": binned(z, sig[ok], SIGMA_BINS_UM), "by_frames": binned(z, frames[ok], FRAME_BINS)}
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
