"""The benchmarks' provenance stamp counts edited code, not the reports an earlier benchmark wrote."""

from __future__ import annotations

import subprocess

from gearscan.provenance import code_edits


def _git(repo, *args):
    subprocess.run(["git", *args], cwd=repo, check=True, capture_output=True)


def test_code_edits_ignore_written_reports_and_name_edited_code(tmp_path):
    repo = tmp_path / "repo"
    (repo / "benchmarks" / "sub").mkdir(parents=True)
    (repo / "recon").mkdir()
    files = {"benchmarks/a_report.md": "x", "benchmarks/a_report.json": "{}", "benchmarks/sub/b_report.png": "p",
             "benchmarks/bench.py": "1", "benchmarks/x_rule.md": "r", "benchmarks/c_report.py": "1",
             "recon/measure.py": "1", "README.md": "r"}
    for name, text in files.items():
        (repo / name).write_text(text)
    _git(repo, "init", "-q")
    _git(repo, "add", ".")
    _git(repo, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "c")
    assert code_edits(repo) == []
    for name in ("benchmarks/a_report.md", "benchmarks/a_report.json", "benchmarks/sub/b_report.png"):
        (repo / name).write_text("rewritten by a run")
    assert code_edits(repo) == []  # an earlier run's report is not an edit of the code
    (repo / "benchmarks/bench.py").write_text("2")
    (repo / "benchmarks/x_rule.md").write_text("a rule edited")  # rules count: they decide
    (repo / "benchmarks/c_report.py").write_text("2")  # a report's writer is code
    (repo / "README.md").write_text("edited")
    assert code_edits(repo) == ["README.md", "benchmarks/bench.py", "benchmarks/c_report.py", "benchmarks/x_rule.md"]
    assert code_edits(tmp_path / "nowhere") == ["unknown"]


def test_a_val_runs_stamp_names_its_commit_edits_and_cpu(tmp_path):
    """A val-choice json says where it ran: the short commit of the tree, the code edited beyond it, the CPU."""
    from gearscan.provenance import run_stamp

    repo = tmp_path / "repo"
    (repo / "recon").mkdir(parents=True)
    (repo / "recon/measure.py").write_text("1")
    _git(repo, "init", "-q")
    _git(repo, "add", ".")
    _git(repo, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "c")
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=repo, capture_output=True, text=True).stdout.strip()
    stamp = run_stamp(repo)
    assert stamp["commit"] == head and stamp["uncommitted_edits"] == [] and stamp["host"]
    (repo / "recon/measure.py").write_text("2")
    assert run_stamp(repo)["uncommitted_edits"] == ["recon/measure.py"]
    assert run_stamp(tmp_path / "not-a-repo")["commit"] == "unknown"
