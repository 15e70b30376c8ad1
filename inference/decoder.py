"""The infer stage: Burst -> PhaseResult with CD-DCU-Net, or three-step PS where the gear stands still.

Three-step PS is the classical fallback (:func:`gearscan.core.phase.classical_result`): it has no motion
error on a still gear, and it decodes the coarse bursts the network was not trained on.
"""

from __future__ import annotations

import logging
import math
import os
import queue
import threading
from pathlib import Path
from typing import TYPE_CHECKING

from gearscan.core.phase import classical_result, still_result
from gearscan.core.rig import FringeOrientation, Rig, RigError, fringe_orientation
from gearscan.core.types import Burst, PhaseResult

if TYPE_CHECKING:  # the predictor (torch) is imported only when a network decodes
    from gearscan.inference.predictor import NetworkSupport

logger = logging.getLogger(__name__)

# below this burst span three-step PS beat the shipped network on radial val rigs (Decoder); v6 0.075, v9 0.0375 since
# session 46 (benchmarks/still_span_rule.md, benchmarks/still_crossover_report.md)
STILL_SPAN_DEG = 0.0375
ORIENTATION_VOTES = 3  # still bursts whose agreeing votes set the rig's fringe orientation (Decoder, "auto")


def turned_less_than(angles, span_deg: float) -> bool:
    """Whether the turntable turned less than ``span_deg`` from a burst's first to its last frame
    (``angles`` in rad): such a burst has no motion error, and three-step PS decodes it."""
    return abs(float(angles[-1]) - float(angles[0])) < math.radians(span_deg)


class Decoder:
    """Burst -> PhaseResult with the network (``mc`` passes, 0 = deterministic) or three-step PS.

    ``workers`` > 1 decodes that many bursts at once, each on its own copy of the network
    with ``cores // workers`` torch threads (a process-wide torch setting): on a few CPU cores
    this beats one pass spread over all of them, whose threads stall whenever another stage
    takes a core (2 cores, 512x512: 3.6-4.8 -> 5.2-6.3 bursts/s, benchmarks/pipeline_report.md). The
    pipeline runs the infer stage with this many workers. None: 2 on a CPU with >= 2 cores, else 1.

    Bursts whose encoder angles span less than ``still_span_deg`` (frame 1 to 3) go to
    three-step PS instead of the network: without motion it has no motion error. On the val
    split's radial rigs it beat the shipped network (v9) up to a 0.025 deg span (still: 0.056 vs 0.059
    rad), v9 wins from 0.05 deg on; on the any-view val rigs v9 won even on a still gear (0.065 vs 0.078;
    benchmarks/still_crossover_report.md, benchmarks/still_span_rule.md), so there the route costs a
    little on still gears: a compromise for the radial rigs. 0 sends every burst to the network.

    ``orientation``: the rig's fringe direction for the network (:class:`Predictor`):
    ``"normal"``/``"mirrored"`` fix it for the whole run. ``"auto"`` takes it from the rig's calibration
    (:meth:`adopt_rig`, :func:`~gearscan.core.rig.fringe_orientation`) when the caller has one, else votes
    per burst until :data:`ORIENTATION_VOTES` still bursts (routed to three-step PS, where no motion can
    fool the vote) agree and none disagrees; from then on theirs is the rig's (:attr:`rig_orientation`).
    Still bursts that outvote the calibration win (the network reads the frames; a camera that mirrors its
    images would do that) and are reported. The per-burst vote misreads fast bursts: a drift of a third of
    a period per frame makes the reversed three-step set, on the test split 35 of 800 bursts.
    """

    def __init__(self, model: str | Path | None = None, *, mc: int = 0, classical: bool = False,
                 precision: str = "auto", workers: int | None = None,
                 still_span_deg: float = STILL_SPAN_DEG, orientation: str = "auto") -> None:
        if workers is not None and workers < 1:
            raise ValueError(f"model.workers: expected >= 1, got {workers}")
        if not still_span_deg >= 0:
            raise ValueError(f"model.still_span_deg: expected >= 0 degrees, got {still_span_deg}")
        self.still_span_deg = float(still_span_deg)
        self.still_bursts = 0
        self.turning_three_step = 0  # three-step PS (classical mode) on bursts that turned: no motion term in its sigma
        self.orientation = orientation
        self.rig_orientation: str | None = None if orientation == "auto" else orientation
        self.orientation_source: str | None = None if orientation == "auto" else "set"
        self._votes = {"normal": 0, "mirrored": 0}
        self._outvoted = False  # still bursts overruled the rig calibration's orientation
        self._lock = threading.Lock()
        self._predictors: list = []
        self.mc = mc
        self.workers = 1
        self.predictor = None
        self._pool: queue.SimpleQueue = queue.SimpleQueue()
        if not classical:
            from gearscan.inference.predictor import Predictor

            self.predictor = Predictor.load(model, precision=precision, orientation=orientation)
            cpu, cores = self.predictor.device.type == "cpu", len(os.sched_getaffinity(0))
            self.workers = workers if workers is not None else (2 if cpu and cores >= 2 else 1)
            self._predictors = [self.predictor.replica() for _ in range(self.workers - 1)] + [self.predictor]
            for p in self._predictors:  # own copies: MC switches the dropout masks per call
                self._pool.put(p)
            if cpu:
                self.use_threads(self.workers)
        self.mode = "three-step" if classical else (f"mc{mc}" if mc else "deterministic")

    @staticmethod
    def use_threads(workers: int) -> None:
        """Give each of ``workers`` concurrent CPU passes an equal share of the cores (torch is process-wide)."""
        import torch

        torch.set_num_threads(max(1, len(os.sched_getaffinity(0)) // workers))

    def __call__(self, burst: Burst) -> PhaseResult:
        if self.predictor is None or burst.group != 0:  # coarse bursts: three-step PS (the net knows fine fringes)
            if self.predictor is None and burst.group == 0 and not turned_less_than(burst.angles, self.still_span_deg):
                with self._lock:
                    self.turning_three_step += 1
            return classical_result(burst)
        if turned_less_than(burst.angles, self.still_span_deg):
            with self._lock:  # the decoder runs on several worker threads
                self.still_bursts += 1
            self._vote_orientation(burst)
            return still_result(burst)
        predictor = self._pool.get()
        try:
            return predictor.predict_burst(burst, mc=self.mc)
        finally:
            self._pool.put(predictor)

    @property
    def network_support(self) -> NetworkSupport | None:
        """The network's own fringe-support tests (:class:`~gearscan.inference.predictor.NetworkSupport`) for the
        reconstructor; None for three-step PS or a model whose JSON names none (the product's apply)."""
        return None if self.predictor is None else self.predictor.network_support

    @property
    def depth_sigma_scales(self) -> tuple[float, ...] | dict[str, tuple[float, ...]] | None:
        """The network's own depth-sigma scales by edge band for the reconstructor
        (:func:`~gearscan.inference.predictor.model_depth_sigma_scales`); None for three-step PS or a model whose JSON
        names none (the product's apply)."""
        return None if self.predictor is None else self.predictor.depth_sigma_scales

    @property
    def rest_sigma_scale(self) -> float | None:
        """The network's own scale for the sigma of the points the frame fit cannot take
        (:func:`~gearscan.inference.predictor.model_rest_sigma_scale`); None for three-step PS or a model whose JSON
        names none (the product's applies)."""
        return None if self.predictor is None else self.predictor.rest_sigma_scale

    @property
    def rest_sigma_chosen_for(self) -> str | None:
        """The decode (model fingerprint) the network's own rest-sigma scale was chosen for, where its JSON names it."""
        return None if self.predictor is None else self.predictor.rest_sigma_chosen_for

    @property
    def model_fingerprint(self) -> str | None:
        """The network decode's :func:`~gearscan.inference.model_io.model_fingerprint` (weights, sigma maps, gates);
        None for three-step PS."""
        return None if self.predictor is None else self.predictor.fingerprint

    @property
    def depth_sigma_chosen_for(self) -> str | None:
        """The decode (model fingerprint) the network's own depth-sigma scales were chosen for, where its JSON names
        it; None otherwise."""
        return None if self.predictor is None else self.predictor.depth_sigma_chosen_for

    def summary(self) -> dict:
        """What decoded the run: mode, bursts sent to three-step PS as still (and, in three-step mode, the bursts it
        decoded that turned: a baseline whose sigma has no motion term), the fringe orientation asked for and the
        rig's as adopted (None: voted per burst throughout) with where it came from, and which network (its weights'
        path and the decode's fingerprint; None for three-step PS), so that a result names the model that made it."""
        return {"mode": self.mode, "model": None if self.predictor is None or self.predictor.path is None
                else str(self.predictor.path), "model_fingerprint": self.model_fingerprint,
                "still_bursts": self.still_bursts, "turning_three_step": self.turning_three_step,
                "orientation": self.orientation,
                "rig_orientation": self.rig_orientation, "orientation_source": self.orientation_source,
                "orientation_votes": dict(self._votes)}

    def adopt_rig(self, rig: Rig) -> FringeOrientation | None:
        """A run starts on ``rig``: with ``orientation="auto"``, forget the still-burst votes of any earlier run
        and take the rig's fringe orientation from its calibration (no burst can fool it). Returns what the
        calibration says; None where not asked for (a set orientation, three-step mode) or where the geometry
        gives none (then the bursts vote, as without a calibration; a warning says why)."""
        self.still_bursts = 0  # the run's own count (summary)
        if self.orientation != "auto" or self.predictor is None:
            return None
        try:
            found = fringe_orientation(rig)
        except RigError as exc:
            found, why = None, str(exc)
        else:
            why = found.describe()
        with self._lock:
            self._votes, self._outvoted = {"normal": 0, "mirrored": 0}, False
            side = found.orientation if found is not None else None
            self.rig_orientation, self.orientation_source = None, None
            for p in self._predictors:
                p.orientation = "auto"
            if side is None:
                logger.warning("rig calibration: %s; the fringe orientation is voted per burst until %d still "
                               "bursts agree", why, ORIENTATION_VOTES)
                return None
            self._set_rig_orientation(side, "calibration")
        return found

    def _set_rig_orientation(self, side: str, source: str) -> None:
        self.rig_orientation, self.orientation_source = side, source
        for p in self._predictors:
            p.orientation = side

    def orientation_status(self) -> str | None:
        """The fringe orientation the network decodes with, in a few words for a status line
        (None in three-step mode, where it does not matter)."""
        if self.predictor is None:
            return None
        with self._lock:
            n, m = self._votes["normal"], self._votes["mirrored"]
        if self.orientation != "auto":
            return f"fringes {self.orientation} (set)"
        if self.orientation_source == "calibration":
            against = m if self.rig_orientation == "normal" else n
            return f"fringes {self.rig_orientation} (rig calibration" + (
                f"; {against} still bursts disagree)" if against else ")")
        if self.rig_orientation is not None:
            return f"fringes {self.rig_orientation} (from {max(n, m)} still bursts" + (
                ", against the rig calibration)" if self._outvoted else ")")
        if n and m:
            return f"fringes voted per burst: still bursts disagree ({n} normal, {m} mirrored); set model.orientation"
        return f"fringes voted per burst ({max(n, m)} of {ORIENTATION_VOTES} still bursts)"

    def _vote_orientation(self, burst: Burst) -> None:
        """Count a still burst's fringe orientation; set the rig's once :data:`ORIENTATION_VOTES` agree (over
        the calibration's too: the network reads the frames)."""
        if self.orientation_source in ("set", "still bursts") or self.predictor is None:
            return
        from gearscan.inference.predictor import falling_phase_share, frames_to_tensor

        share = falling_phase_share(frames_to_tensor(burst.images, burst.full_scale))
        if share is None:  # no fringes seen: no vote
            return
        # a reversed-order burst shows the negated phase: it falls along the columns of a normal rig
        mirrored = (share > 0.5) != burst.reversed_order
        with self._lock:
            self._votes["mirrored" if mirrored else "normal"] += 1
            for side, other in (("normal", "mirrored"), ("mirrored", "normal")):
                if self._votes[side] >= ORIENTATION_VOTES and self._votes[other] == 0:
                    if self.orientation_source == "calibration":
                        if side == self.rig_orientation:
                            continue
                        self._outvoted = True
                        logger.warning("%d still bursts read the fringes %s, the rig calibration %s: decoding as the "
                                       "frames show from now on; check that the calibration belongs to this camera "
                                       "and projector (a camera mirroring its images also mirrors the points)",
                                       self._votes[side], side, self.rig_orientation)
                    self._set_rig_orientation(side, "still bursts")

