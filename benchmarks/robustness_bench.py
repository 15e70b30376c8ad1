"""Robustness fuzz: seeded byte mutations of a recording's index files and of a ``predict`` npz.

Each case must end in a clean error or a counted skip, or give the unmutated result: a
traceback, a hang or a changed result nobody reported is a failure (issue 15, item 4).

* Recording: 200 cases per file (``recording.json``, ``frames.jsonl``, ``encoder.jsonl``),
  each 1-3 edits from :mod:`gearscan.mocks.fuzz` (bit flips, cuts, invalid UTF-8, hostile
  numbers), replayed with ``reconstruct=False``. Clean error: :class:`RecordingError`;
  skip: a replay whose ``metrics.damage`` counts what it dropped.
* ``predict``: 200 cases of a 3x32x40 uint8 npz: byte edits of the file and rewritten arrays
  (wrong dtype/shape, NaN/inf/negative/huge ``full_scale``/``bit_depth``/``angles``), run
  through ``gearscan predict`` (typer's CliRunner). Clean error: exit 2 naming the file.

Usage: ``MPLBACKEND=Agg .venv/bin/python benchmarks/robustness_bench.py [--cases 200] [--seed 0]``
writes ``benchmarks/robustness_report.{md,json}``; exits 1 if any case failed.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import platform
import shutil
import signal
import subprocess
import tempfile
import time
import warnings
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from gearscan.mocks.fuzz import (
    BAD_NUMBERS,
    HOSTILE_BYTES,
    INDEX_FILES,
    OPS,
    mutate,
    write_small_recording,
)
from gearscan.provenance import code_edits

HERE = Path(__file__).resolve().parent
BAD = ("changed", "traceback", "hang", "unnamed_error")


class Hang(Exception):
    """A case ran past its time limit."""


@contextlib.contextmanager
def time_limit(seconds: float) -> Iterator[None]:
    """Raise :class:`Hang` in the main thread after ``seconds``."""
    def _raise(*_: object) -> None:
        raise Hang(f"over {seconds} s")

    old = signal.signal(signal.SIGALRM, _raise)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


def _payload(rng: np.random.Generator) -> bytes:
    """A hostile insertion: invalid UTF-8 / JSON syntax, a hostile number, or 1-6 random bytes."""
    pick = rng.integers(3)
    if pick == 0:
        return HOSTILE_BYTES[rng.integers(len(HOSTILE_BYTES))]
    if pick == 1:
        return BAD_NUMBERS[rng.integers(len(BAD_NUMBERS))]
    return rng.bytes(int(rng.integers(1, 7)))


def _mutate_bytes(data: bytes, rng: np.random.Generator) -> tuple[bytes, list[str]]:
    """``data`` after 1-3 random edits, and their descriptions."""
    done = []
    for _ in range(int(rng.integers(1, 4))):
        op, pos, payload = OPS[rng.integers(len(OPS))], int(rng.integers(0, 10_000)), _payload(rng)
        data = mutate(data, op, pos, payload)
        done.append(f"{op}@{pos}:{payload!r}")
    return data, done


# -- recordings ---------------------------------------------------------------------------------
def _replay_rows(rec: Path) -> tuple[object, list[tuple]]:
    """The replay's metrics and what each burst measured (frame ids, angles, phase bytes)."""
    from gearscan.replay import replay

    rows: list[tuple] = []

    def on_burst(m, _row) -> None:
        rows.append((tuple(f.frame_id for f in m.burst.frames), np.asarray(m.burst.angles).tobytes(),
                     m.result.phase.tobytes()))

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # an interrupted tail is warned about; counted in damage
        metrics = replay(rec, reconstruct=False, truth=False, on_burst=on_burst)
    return metrics, rows


def fuzz_recording(work: Path, name: str, cases: int, rng: np.random.Generator, limit: float,
                   reference: list[tuple]) -> tuple[Counter, list[dict]]:
    """Outcome counts of ``cases`` mutated copies of ``name`` in the small recording, and the failures."""
    from gearscan.core.recording import RecordingError

    base = work / "base"
    counts: Counter = Counter()
    failures: list[dict] = []
    for i in range(cases):
        rec = Path(shutil.copytree(base, work / f"case{i}"))
        data, edits = _mutate_bytes((rec / name).read_bytes(), rng)
        (rec / name).write_bytes(data)
        detail = ""
        try:
            with time_limit(limit):
                metrics, rows = _replay_rows(rec)
            if metrics.damage["count"]:
                kind = "skip"
            else:
                kind = "same" if rows == reference else "changed"
        except RecordingError:
            kind = "error"
        except Hang as exc:
            kind, detail = "hang", str(exc)
        except Exception as exc:  # noqa: BLE001 - any other exception is what is being counted
            kind, detail = "traceback", f"{type(exc).__name__}: {exc}"[:300]
        counts[kind] += 1
        if kind in BAD:
            failures.append({"case": i, "kind": kind, "edits": edits, "detail": detail})
        shutil.rmtree(rec)
    return counts, failures


# -- predict ------------------------------------------------------------------------------------
def _semantic_npz(frames: np.ndarray, rng: np.random.Generator) -> tuple[dict, str]:
    """Arrays for an npz that is well formed but holds a value predict must refuse."""
    nan, inf = float("nan"), float("inf")
    variants: list[tuple[str, Callable[[], dict]]] = [
        ("frames float32 with NaN", lambda: {"frames": np.where(frames > 128, nan, frames).astype(np.float32)}),
        ("frames int8", lambda: {"frames": frames.astype(np.int8)}),
        ("frames int64", lambda: {"frames": frames.astype(np.int64)}),
        ("frames (3, H)", lambda: {"frames": frames[:, :, 0]}),
        ("frames (2, H, W)", lambda: {"frames": frames[:2]}),
        ("frames (3, 0, W)", lambda: {"frames": frames[:, :0]}),
        ("frames (3, H, W, 1)", lambda: {"frames": frames[..., None]}),
        ("frames scalar", lambda: {"frames": np.uint8(7)}),
        ("no frames", lambda: {"images": frames}),
        *[(f"full_scale={v}", lambda v=v: {"frames": frames, "full_scale": np.float64(v)})
          for v in (nan, inf, -inf, -1.0, 0.0, 1e300)],
        ("full_scale (2,)", lambda: {"frames": frames, "full_scale": np.ones(2)}),
        *[(f"bit_depth={v}", lambda v=v: {"frames": frames, "bit_depth": np.asarray(v)})
          for v in (-1, 0, 70, 2**62, nan, 8.5)],
        *[(f"angles={v}", lambda v=v: {"frames": frames, "angles": np.asarray(v)})
          for v in ([nan, 0.0, 0.1], [0.0, inf, 0.1], [0.0, 0.1], 1.0, ["a", "b", "c"])],
    ]
    what, make = variants[rng.integers(len(variants))]
    return make(), what


def _run_predict(path: Path, out: Path, limit: float):
    """``gearscan predict path -o out`` in process; the CliRunner result."""
    from typer.testing import CliRunner

    from gearscan.cli import app

    with time_limit(limit):
        return CliRunner().invoke(app, ["predict", str(path), "-o", str(out)])


def fuzz_predict(work: Path, cases: int, rng: np.random.Generator, limit: float) -> tuple[Counter, list[dict]]:
    """Outcome counts of ``cases`` damaged predict inputs (3/4 byte edits, 1/4 bad arrays), and the failures."""
    frames = np.random.default_rng(0).integers(0, 256, (3, 32, 40), dtype=np.uint8)
    base = work / "burst.npz"
    np.savez(base, frames=frames)
    ref = _run_predict(base, work / "ref.npz", limit)
    assert ref.exit_code == 0, ref.output
    with np.load(work / "ref.npz") as z:
        reference = {k: z[k] for k in z.files}
    counts: Counter = Counter()
    failures: list[dict] = []
    for i in range(cases):
        path, out = work / f"case{i}.npz", work / f"out{i}.npz"
        if rng.random() < 0.75:
            data, edits = _mutate_bytes(base.read_bytes(), rng)
            path.write_bytes(data)
        else:
            arrays, what = _semantic_npz(frames, rng)
            np.savez(path, **arrays)
            edits = [what]
        detail = ""
        try:
            result = _run_predict(path, out, limit)
            text = result.output  # click >= 8.2: stdout and stderr together
            if result.exception is not None and not isinstance(result.exception, SystemExit):
                kind = "traceback"
                detail = f"{type(result.exception).__name__}: {result.exception}"[:300]
            elif result.exit_code == 0:
                with np.load(out) as z:
                    same = all(np.array_equal(z[k], v) for k, v in reference.items())
                kind = "same" if same else "changed"
            elif result.exit_code == 2 and path.name in text:
                kind = "error"
            else:
                kind, detail = "unnamed_error", f"exit {result.exit_code}: {text.strip()[-300:]}"
        except Hang as exc:
            kind, detail = "hang", str(exc)
        counts[kind] += 1
        if kind in BAD:
            failures.append({"case": i, "kind": kind, "edits": edits, "detail": detail})
        path.unlink(missing_ok=True)
        out.unlink(missing_ok=True)
    return counts, failures


# -- report -------------------------------------------------------------------------------------
def host() -> dict:
    """CPU model, the bf16/AMX flags that change inference numerics, and the commit."""
    cpuinfo = Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").exists() else ""
    model = next((ln.split(":", 1)[1].strip() for ln in cpuinfo.splitlines() if ln.startswith("model name")),
                 platform.processor())
    flags = set(next((ln.split(":", 1)[1].split() for ln in cpuinfo.splitlines() if ln.startswith("flags")), []))

    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=HERE, capture_output=True, text=True).stdout.strip()

    return {"cpu": model, "avx512_bf16": "avx512_bf16" in flags, "amx_bf16": "amx_bf16" in flags,
            "commit": git("rev-parse", "--short", "HEAD"),
            "dirty": bool(code_edits(HERE.resolve().parent))}


def write_report(report: dict, stem: Path) -> None:
    """``stem``.json and a Markdown table of the counts per target."""
    stem.with_suffix(".json").write_text(json.dumps(report, indent=2) + "\n")
    kinds = ("error", "skip", "same", *BAD)
    h = report["host"]
    lines = [
        "# Robustness fuzz report", "",
        f"`benchmarks/robustness_bench.py --cases {report['cases']} --seed {report['seed']}` "
        f"on {h['cpu']} (avx512_bf16 {h['avx512_bf16']}, amx_bf16 {h['amx_bf16']}), commit {h['commit']}"
        f"{' + uncommitted changes' if h['dirty'] else ''}, {report['seconds']:.0f} s, "
        f"per-case limit {report['limit_s']:g} s.", "",
        "error: a clean error (RecordingError; for predict exit 2 naming the file). skip: replay "
        "went on and counted the damage. same: the unmutated result. Failures: changed (a "
        "different result, exit 0, nothing reported), traceback, hang, unnamed_error (predict "
        "exit != 0 without naming the file).", "",
        "| target | cases | " + " | ".join(kinds) + " |",
        "|---|---:|" + "---:|" * len(kinds),
    ]
    for target, t in report["targets"].items():
        lines.append(f"| {target} | {sum(t['counts'].values())} | "
                     + " | ".join(str(t["counts"].get(k, 0)) for k in kinds) + " |")
    bad = sum(len(t["failures"]) for t in report["targets"].values())
    lines += ["", f"**Failures: {bad}** (tracebacks, hangs and unreported changes)."]
    for target, t in report["targets"].items():
        for f in t["failures"][:10]:
            lines.append(f"- {target} case {f['case']}: {f['kind']} {f['detail']} — edits {f['edits']}")
    stem.with_suffix(".md").write_text("\n".join(lines) + "\n")


def main() -> int:
    """Run both fuzzers and write the report; 1 if any case failed."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=200, help="mutations per target")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--limit", type=float, default=20.0, help="seconds per case before it counts as a hang")
    ap.add_argument("--out", type=Path, default=HERE / "robustness_report", help="report path without suffix")
    args = ap.parse_args()
    logging.getLogger("gearscan").setLevel(logging.ERROR)  # each case's damage is counted, not logged
    rng = np.random.default_rng(args.seed)
    t0 = time.perf_counter()
    targets: dict[str, dict] = {}
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        write_small_recording(work / "base")
        _, reference = _replay_rows(work / "base")
        for name in INDEX_FILES:
            counts, failures = fuzz_recording(work, name, args.cases, rng, args.limit, reference)
            targets[f"recording {name}"] = {"counts": dict(counts), "failures": failures}
            print(name, dict(counts), flush=True)
        (work / "predict").mkdir()
        counts, failures = fuzz_predict(work / "predict", args.cases, rng, args.limit)
        targets["predict npz"] = {"counts": dict(counts), "failures": failures}
        print("predict npz", dict(counts), flush=True)
    report = {"cases": args.cases, "seed": args.seed, "limit_s": args.limit, "host": host(),
              "seconds": time.perf_counter() - t0, "targets": targets}
    write_report(report, args.out)
    return int(any(t["failures"] for t in targets.values()))


if __name__ == "__main__":
    raise SystemExit(main())
