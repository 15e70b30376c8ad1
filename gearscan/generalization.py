"""Generalization scoring on test-split families: pooled and stratified, so no weak spot hides.

Per burst, every method's wrapped phase is compared with the twin's analytic phase at the first
frame's pose over its valid mask (DESIGN.md). The squared errors are summed per family, per
motion group and per stratum of six pixel properties:

- camera fringe period (px): ``2 pi / |grad phi|`` of the truth's absolute phase;
- modulation: the truth's ``2B/S``;
- distance to the mask edge (px): Euclidean distance transform of the truth mask;
- burst span (deg, frame 1 to 3; moving bursts only);
- image motion (px): how far the surface point seen at frame 1 moves in the camera by frame 3
  (moving bursts only; the same span moves a large gear's rim further);
- fringe phase change (periods): how far the fringe phase seen at a camera pixel moves from
  frame 1 to frame 3, ``|phi_3 - phi_1| / 2 pi`` of the truth (moving bursts only): the cause of
  three-step PS's motion error (image motion along the fringes does not change it). For a steady
  drift three-step PS's error grows about as half the change; its solve is singular at a change
  of 1/3 period (drift with the shifts) or 2/3 period (against them).

Strata of one axis partition the pixels of their group (a last ``n/a`` bin takes non-finite
values), so their counts add up to the pooled count. A stratum where the network's RMSE is above
the baseline's (three-step PS) is flagged. ECE uses the project's reliability diagram
(:func:`gearscan.inference.uncertainty.reliability`); coverage is the share of the truth mask that
passes the reconstructor's own keep test (modulation >= 0.05, sigma <= ``MAX_SIGMA_RAD``, finite phase; a network's pixel also
needs fringes in its frames within the decoding model's per-burst fringe-support test, its JSON's
``network_support``, else the product's: :func:`gearscan.recon.measure.keep_candidates`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import distance_transform_edt

from gearscan.core.phase import phase_error
from gearscan.core.types import PhaseResult
from gearscan.evaluate import (
    GENERALISATION,
    PAPER_MOTIONS,
    REVERSED,
    BurstCase,
    Method,
    Scene,
    render_cases,
)
from gearscan.inference.predictor import frames_to_tensor, fringe_phase_decreases_along_columns
from gearscan.twin.families import FamilyScene

BASELINE = "three-step PS"
NETWORK = "CD-DCU-Net"
STILL, MOVING = "still", "moving"


# --- motions --------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class Motion:
    """A burst's frame-to-frame rotation steps (deg; negative: turning backwards) and its group."""

    name: str
    group: str  # "paper", "paper reversed", "sweep" or "still"
    steps_deg: tuple[float, float]

    @property
    def span_deg(self) -> float:
        return abs(self.steps_deg[0] + self.steps_deg[1])

    @property
    def kind(self) -> str:
        return STILL if self.span_deg == 0 else MOVING


PAPER: dict[str, tuple[float, float]] = {**PAPER_MOTIONS, "non-uniform 0.5/1.0": GENERALISATION["0.5+1"]}
PAPER_REVERSED: dict[str, tuple[float, float]] = {
    **REVERSED, "reversed non-uniform 0.5/1.0": tuple(-s for s in GENERALISATION["0.5+1"])}
GROUPS = ("paper", "paper reversed", "sweep", "still")


def scene_motions(rng: np.random.Generator, sweeps: int = 2, stills: int = 2, paper: bool = True) -> list[Motion]:
    """The paper's three motions both ways, ``sweeps`` random spans in (0, 2] deg of random sense
    and split, and ``stills`` still bursts."""
    out = []
    if paper:
        out += [Motion(k, "paper", v) for k, v in PAPER.items()]
        out += [Motion(k, "paper reversed", v) for k, v in PAPER_REVERSED.items()]
    for k in range(sweeps):
        span = float(rng.uniform(0.02, 2.0)) * (1 if rng.random() < 0.5 else -1)
        first = span * float(rng.uniform(0.1, 0.9))
        out.append(Motion(f"sweep {k} {span:+.2f} deg", "sweep", (round(first, 4), round(span - first, 4))))
    out += [Motion(f"still {k}", "still", (0.0, 0.0)) for k in range(stills)]
    return out


def render_family_cases(scene: FamilyScene, motions: list[Motion]) -> list[BurstCase]:
    """One burst per motion at a random start angle, noise and angles from the scene's test seed."""
    sc = Scene(scene.name, scene.rig, scene.optics, scene.gear, scene.period_px, _renderer=scene.renderer)
    return render_cases(sc, {m.name: m.steps_deg for m in motions}, 1, seed=scene.seed)


def vote_mirrored(case: BurstCase) -> bool:
    """The Predictor's per-burst orientation vote on this burst's frames (``orientation="auto"``)."""
    return fringe_phase_decreases_along_columns(frames_to_tensor(case.frames, case.full_scale))


def rig_orientation(motions: list[Motion], cases: list[BurstCase]) -> str:
    """The scene's fringe orientation as a user would set it at set-up: the vote on its first still burst.

    A still burst has no motion to fool the vote; without one the twin's own orientation ("normal",
    every family's rig has the fringe phase rising along the columns) is assumed."""
    still = [c for m, c in zip(motions, cases, strict=True) if m.group == STILL]
    return "mirrored" if still and vote_mirrored(still[0]) else "normal"


# --- strata ---------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class Axis:
    """A pixel property and its bin edges (right-closed bins, plus ``n/a`` for non-finite values)."""

    name: str
    unit: str
    edges: tuple[float, ...]

    @property
    def labels(self) -> tuple[str, ...]:
        e = [f"{v:g}" for v in self.edges]
        return (f"<= {e[0]}", *(f"{a}-{b}" for a, b in zip(e, e[1:], strict=False)), f"> {e[-1]}", "n/a")

    def bins(self, values: np.ndarray) -> np.ndarray:
        """Bin index per value; the last index (``n/a``) for NaN or infinite values."""
        v = np.asarray(values, np.float64)
        idx = np.searchsorted(np.asarray(self.edges), v, side="left")
        return np.where(np.isfinite(v), idx, len(self.edges) + 1)


AXES: tuple[Axis, ...] = (
    Axis("camera fringe period", "px", (5.0, 8.0, 12.0, 20.0, 40.0, 60.0)),
    Axis("modulation", "2B/S", (0.1, 0.2, 0.3, 0.5)),
    Axis("distance to mask edge", "px", (2.0, 4.0, 8.0, 16.0)),
    Axis("burst span", "deg", (0.25, 0.75, 1.25, 1.5, 1.75)),
    Axis("image motion", "px", (1.0, 2.0, 4.0, 8.0, 16.0)),
    Axis("fringe phase change", "periods", (0.05, 0.1, 0.25, 0.5, 1.0)),
)
SPAN_AXIS = AXES[3].name
MOTION_AXIS = AXES[4].name
SHIFT_AXIS = AXES[5].name
MOVING_ONLY = (SPAN_AXIS, MOTION_AXIS, SHIFT_AXIS)


def camera_period_px(phase_abs: np.ndarray) -> np.ndarray:
    """Local camera fringe period ``2 pi / |grad phi|`` (px) of an absolute phase map (NaN where unknown)."""
    gy, gx = np.gradient(np.asarray(phase_abs, np.float64))
    with np.errstate(divide="ignore", invalid="ignore"):
        return 2 * np.pi / np.hypot(gx, gy)


def image_motion_px(case: BurstCase) -> np.ndarray:
    """How far (camera px) each truth-mask surface point moves from frame 1 to frame 3.

    The point seen at frame 1 is turned by the burst's span about the turntable axis and
    projected again: the motion the three-step decode suffers, in the camera's own units
    (degrees say little alone: the same span moves a large gear's rim further).
    """
    from gearscan.core.rig import rot_z

    cam = case.scene.rig.camera
    p_cam = case.truth.points[case.truth.mask].astype(np.float64)
    p_world = p_cam @ cam.T_world_from[:3, :3].T + cam.T_world_from[:3, 3]
    turn = rot_z(float(np.radians(case.angles_deg[2] - case.angles_deg[0])))[:3, :3]
    return np.linalg.norm(cam.project(p_world @ turn.T) - cam.project(p_world), axis=1)


def pixel_strata(case: BurstCase, span_deg: float) -> dict[str, np.ndarray]:
    """The stratum values of every truth-mask pixel of ``case`` (1-D, mask order)."""
    t = case.truth
    m = t.mask
    return {
        AXES[0].name: camera_period_px(t.phase_abs)[m],
        AXES[1].name: np.hypot(t.M, t.D)[m],
        AXES[2].name: distance_transform_edt(m)[m],
        SPAN_AXIS: np.full(int(m.sum()), span_deg),
        MOTION_AXIS: image_motion_px(case) if span_deg > 0 else np.zeros(int(m.sum())),
        SHIFT_AXIS: case.fringe_phase_change()[m] / (2 * np.pi),
    }


def covered(result: PhaseResult, frames: np.ndarray, full_scale: float, model=None) -> np.ndarray:
    """Pixels the reconstructor's keep test passes in ``result`` of these ``frames`` (its defaults:
    :func:`gearscan.recon.measure.keep_candidates`, with the decoding ``model``'s per-burst fringe-support test, its
    ``network_support``; None: the product's), before unwrapping."""
    from gearscan.recon.measure import keep_candidates, network_support_option

    return keep_candidates(result, frames, full_scale, network_support_px=network_support_option(None, model=model))[0]


# --- accumulation ---------------------------------------------------------------------------
@dataclass
class _Sums:
    """Running sums of one cell (family, motion group): pixels, squared errors, coverage, bursts."""

    bursts: int = 0
    pixels: int = 0
    sse: dict[str, float] = field(default_factory=dict)
    covered: dict[str, int] = field(default_factory=dict)
    sse_kept: dict[str, float] = field(default_factory=dict)  # over the pixels the keep test passes
    errors: dict[str, list[np.ndarray]] = field(default_factory=dict)  # for ECE, methods with a sigma
    sigmas: dict[str, list[np.ndarray]] = field(default_factory=dict)


@dataclass
class _StrataSums:
    """Per (family, motion kind, axis): pixel count and squared-error sum per bin and method."""

    count: np.ndarray
    sse: dict[str, np.ndarray] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class CellScore:
    """Pooled scores of one family and motion group (or ``moving``: all moving bursts)."""

    family: str
    group: str
    bursts: int
    pixels: int
    rmse: dict[str, float]
    coverage: dict[str, float]
    ece: dict[str, float]
    rmse_kept: dict[str, float] = field(default_factory=dict)  # over the pixels each method's keep test passes

    def gain(self, method: str, baseline: str = BASELINE) -> float:
        """Baseline RMSE over the method's: > 1 where the method is better."""
        return self.rmse[baseline] / self.rmse[method] if self.rmse[method] > 0 else math.inf


# Two decodes whose RMSEs differ by less than this share are tied: a still burst the gate decodes by three-step
# PS and the baseline's three-step PS are the same decode by two float32 routines, equal to the 6th digit.
TIE_MARGIN = 1e-3


def loses(rmse: float, baseline: float) -> bool:
    """Whether an RMSE is worse than the baseline's by more than :data:`TIE_MARGIN` (a tie is no loss)."""
    return rmse > baseline * (1 + TIE_MARGIN)


@dataclass(frozen=True, slots=True)
class StratumScore:
    """One stratum: pixels and RMSE per method; ``worse`` where the network loses to the baseline."""

    family: str
    kind: str  # still or moving
    axis: str
    label: str
    pixels: int
    rmse: dict[str, float]
    network: str
    baseline: str

    @property
    def gain(self) -> float:
        n, b = self.rmse[self.network], self.rmse[self.baseline]
        return b / n if n > 0 else math.inf

    @property
    def worse(self) -> bool:
        return self.pixels > 0 and loses(self.rmse[self.network], self.rmse[self.baseline])


ALL = "all test families"


class GeneralizationScorer:
    """Accumulates per-burst errors into family, motion-group and stratum sums (no pixel loops).

    ``add`` takes one burst with every method's result; ``cells`` and ``strata`` read the scores,
    per family and pooled over all of them (:data:`ALL`).
    """

    def __init__(self, methods: list[str], network: str = NETWORK, baseline: str = BASELINE,
                 supports: dict | None = None) -> None:
        for name in (network, baseline):
            if name not in methods:
                raise ValueError(f"methods {methods} lack {name!r} (network {network!r}, baseline {baseline!r})")
        self.methods = list(methods)
        self.supports = dict(supports or {})  # method -> its model's network_support (coverage's keep test)
        self.network, self.baseline = network, baseline
        self._cells: dict[tuple[str, str], _Sums] = {}
        self._strata: dict[tuple[str, str, str], _StrataSums] = {}

    def add(self, family: str, motion: Motion, case: BurstCase, results: dict[str, PhaseResult]) -> None:
        missing = [m for m in self.methods if m not in results]
        if missing:
            raise ValueError(f"burst {case.scene.name} / {motion.name}: no result for {missing}")
        m = case.truth.mask
        n = int(m.sum())
        if n == 0:
            return
        errs = {k: phase_error(results[k].phase, case.truth.phase)[m].astype(np.float64) for k in self.methods}
        kept = {k: covered(results[k], case.frames, case.full_scale, self.supports.get(k))[m] for k in self.methods}
        groups = [motion.group] + ([MOVING] if motion.kind == MOVING else [])
        for fam in (family, ALL):
            for grp in groups:
                c = self._cells.setdefault((fam, grp), _Sums())
                c.bursts += 1
                c.pixels += n
                for k in self.methods:
                    keep = kept[k]
                    c.sse[k] = c.sse.get(k, 0.0) + float(np.sum(errs[k] ** 2))
                    c.covered[k] = c.covered.get(k, 0) + int(np.count_nonzero(keep))
                    c.sse_kept[k] = c.sse_kept.get(k, 0.0) + float(np.sum(errs[k][keep] ** 2))
                    sig = results[k].sigma_total[m]
                    if k != self.baseline and np.all(np.isfinite(sig)) and np.any(sig > 0):
                        c.errors.setdefault(k, []).append(errs[k].astype(np.float32))
                        c.sigmas.setdefault(k, []).append(np.maximum(sig, 1e-6).astype(np.float32))
        values = pixel_strata(case, motion.span_deg)
        for axis in AXES:
            if axis.name in MOVING_ONLY and motion.kind == STILL:
                continue
            idx = axis.bins(values[axis.name])
            nb = len(axis.labels)
            for fam in (family, ALL):
                s = self._strata.setdefault((fam, motion.kind, axis.name), _StrataSums(np.zeros(nb, np.int64)))
                s.count += np.bincount(idx, minlength=nb)
                for k in self.methods:
                    s.sse[k] = s.sse.get(k, np.zeros(nb)) + np.bincount(idx, weights=errs[k] ** 2, minlength=nb)

    def families(self) -> list[str]:
        """Families in the order they were added, the pooled :data:`ALL` last."""
        fams = [f for f in dict.fromkeys(f for f, _ in self._cells) if f != ALL]
        return fams + [ALL] if fams else []

    def cells(self) -> list[CellScore]:
        """Pooled scores per family and motion group, in insertion order of families."""
        from gearscan.inference.uncertainty import reliability

        order = {g: i for i, g in enumerate((*GROUPS, MOVING))}
        out = []
        for (fam, grp), c in sorted(self._cells.items(), key=lambda kv: (self.families().index(kv[0][0]),
                                                                          order.get(kv[0][1], 99))):
            ece = {k: reliability(np.concatenate(c.errors[k]), np.concatenate(c.sigmas[k])).ece for k in c.errors}
            out.append(CellScore(fam, grp, c.bursts, c.pixels,
                                 {k: math.sqrt(c.sse[k] / c.pixels) for k in self.methods},
                                 {k: c.covered[k] / c.pixels for k in self.methods}, ece,
                                 {k: math.sqrt(c.sse_kept[k] / c.covered[k]) if c.covered[k] else math.nan
                                  for k in self.methods}))
        return out

    def strata(self) -> list[StratumScore]:
        """Every non-empty stratum, per family (and pooled), motion kind and axis."""
        labels = {a.name: a.labels for a in AXES}
        out = []
        for (fam, kind, axis), s in self._strata.items():
            for b, label in enumerate(labels[axis]):
                n = int(s.count[b])
                if n == 0:
                    continue
                rmse = {k: math.sqrt(float(s.sse[k][b]) / n) for k in self.methods}
                out.append(StratumScore(fam, kind, axis, label, n, rmse, self.network, self.baseline))
        return out

    def pooled_pixels(self, family: str, kind: str) -> int:
        """Pixels of all bursts of ``kind`` (still or moving) in ``family``: what each axis partitions."""
        c = self._cells.get((family, kind if kind == MOVING else "still"))
        return 0 if c is None else c.pixels


def run_methods(case: BurstCase, methods: dict[str, Method]) -> dict[str, PhaseResult]:
    """Every method's result for one burst (frames, full scale and encoder angles as in use)."""
    return {k: fn(case.frames, case.full_scale, case.angles_rad) for k, fn in methods.items()}


# --- report ---------------------------------------------------------------------------------
def _f(v: float | None, digits: int = 3) -> str:
    return "" if v is None or not math.isfinite(v) else f"{v:.{digits}f}"


def cells_table(cells: list[CellScore], network: str = NETWORK, baseline: str = BASELINE) -> str:
    """Markdown: per family and motion group, RMSE of both, gain, ECE, coverage and the RMSE of the kept pixels."""
    lines = [f"| family | motions | bursts | pixels | {network} RMSE (rad) | {baseline} RMSE (rad) | "
             f"gain ({baseline} / net) | ECE net | coverage net / 3-step | RMSE of the kept pixels net / 3-step | |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for c in cells:
        g = c.gain(network, baseline)
        lines.append(
            f"| {c.family} | {c.group} | {c.bursts} | {c.pixels} | {_f(c.rmse[network], 4)} | {_f(c.rmse[baseline], 4)} | "
            f"{g:.2f}x | {_f(c.ece.get(network))} | {_f(c.coverage[network], 3)} / {_f(c.coverage[baseline], 3)} | "
            f"{_f(c.rmse_kept.get(network, math.nan), 4)} / {_f(c.rmse_kept.get(baseline, math.nan), 4)} | "
            f"{'**net worse**' if loses(c.rmse[network], c.rmse[baseline]) else ''} |")
    return "\n".join(lines)


def strata_tables(strata: list[StratumScore], families: list[str]) -> str:
    """Markdown: per motion kind and axis, a table of bins x families, cells ``net / 3-step = gain (pixels)``."""
    out = []
    for kind in (MOVING, STILL):
        for axis in AXES:
            rows = [s for s in strata if s.kind == kind and s.axis == axis.name]
            if not rows:
                continue
            cell = {(s.family, s.label): s for s in rows}
            out += [f"#### {kind} bursts, by {axis.name} ({axis.unit})", "",
                    "| " + axis.name + " | " + " | ".join(families) + " |",
                    "|---|" + "---|" * len(families)]
            for label in axis.labels:
                if not any((f, label) in cell for f in families):
                    continue
                parts = []
                for f in families:
                    s = cell.get((f, label))
                    if s is None:
                        parts.append("")
                        continue
                    txt = f"{s.rmse[s.network]:.3f} / {s.rmse[s.baseline]:.3f} = {s.gain:.2f}x ({_count(s.pixels)})"
                    parts.append(f"**{txt} WORSE**" if s.worse else txt)
                out.append(f"| {label} | " + " | ".join(parts) + " |")
            out.append("")
    return "\n".join(out)


def _count(n: int) -> str:
    return f"{n / 1e6:.1f}M" if n >= 1e6 else f"{n / 1e3:.0f}k" if n >= 1e4 else str(n)


def weak_strata_table(strata: list[StratumScore]) -> str:
    """Markdown list of every stratum where the network is worse than the baseline (ties within :data:`TIE_MARGIN`
    are not)."""
    bad = [s for s in strata if s.worse]
    if not bad:
        return "No stratum where the network is worse than three-step PS."
    lines = ["| family | bursts | stratum | pixels | net RMSE | 3-step RMSE | gain |", "|---|---|---|---|---|---|---|"]
    for s in sorted(bad, key=lambda s: (s.family != ALL, s.family, s.kind, s.axis, s.gain)):
        lines.append(f"| {s.family} | {s.kind} | {s.axis} {s.label} | {s.pixels} | {s.rmse[s.network]:.4f} | "
                     f"{s.rmse[s.baseline]:.4f} | {s.gain:.2f}x |")
    return "\n".join(lines)


def plot_strata(strata: list[StratumScore], families: list[str], path, title: str = "") -> None:
    """RMSE by stratum (log scale): network solid, three-step dashed, per family; moving and still rows."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, len(AXES), figsize=(4.2 * len(AXES), 7), dpi=90, squeeze=False)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for r, kind in enumerate((MOVING, STILL)):
        for c, axis in enumerate(AXES):
            ax = axes[r, c]
            if kind == STILL and axis.name in MOVING_ONLY:
                ax.axis("off")
                continue
            labels = [lb for lb in axis.labels if lb != "n/a"]
            for k, fam in enumerate(families):
                by = {s.label: s for s in strata if s.family == fam and s.kind == kind and s.axis == axis.name}
                xs = [i for i, lb in enumerate(labels) if lb in by]
                if not xs:
                    continue
                lw = 2.5 if fam == ALL else 1.0
                col = "k" if fam == ALL else colors[k % len(colors)]
                ax.plot(xs, [by[labels[i]].rmse[by[labels[i]].network] for i in xs], "-o", ms=3, lw=lw, color=col,
                        label=fam)
                ax.plot(xs, [by[labels[i]].rmse[by[labels[i]].baseline] for i in xs], "--", lw=lw * 0.8, color=col)
            ax.set_xticks(range(len(labels)), labels, rotation=35, fontsize=7)
            ax.set_yscale("log")
            ax.set_title(f"{kind}: {axis.name} ({axis.unit})", fontsize=9)
            if c == 0:
                ax.set_ylabel("RMSE (rad): net solid, three-step dashed")
    axes[0, 0].legend(fontsize=6)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)

