"""The foundation every stage shares: data that crosses stages and the conventions they agree on.

Frames, bursts, phase results and clouds (:mod:`.types`), the rig calibration (:mod:`.rig`), the
gear's CAD (:mod:`.gear`), fringe pattern sets (:mod:`.patterns`), the phase-shifting equations
and wrap-aware errors (:mod:`.phase`), frame-id wrap handling (:mod:`.frame_ids`) and the
recording format (:mod:`.recording`). It imports no other gearscan package; every stage may
import it.
"""
