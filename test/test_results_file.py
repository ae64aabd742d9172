"""`meshfg accuracy --results FILE` and `meshfg bench --results FILE`: each writes the tables it
printed into its own section of the markdown file, with the command line, the machine and the
commit, and leaves the other command's section as it was. The measurements are replaced by
fixed results (the suites themselves are tested in test_accuracy.py and test_bench_report.py)."""

import pytest
from test_accuracy import calibration_row

from meshfg_ros import blas, cli, results_file
from meshfg_ros.benchmarks import bench
from meshfg_ros.evaluation import accuracy

ON = {"cpu": "Some CPU 9000, 2 cores", "blas": "bundled", "blas_threads": 1, "blas_detail": "chosen for SomeVendor"}
BENCH = "bench on Some CPU 9000, 2 cores"  # the bench's section: one per CPU model


def accuracy_result(ratio: float) -> dict:
    rows = [{**calibration_row("liver-push"), "ratio_all_final": ratio}, calibration_row("cao-push")]
    return {"scenes": rows, "summary": accuracy.summary(rows)}


def bench_result(p95_ms: float, on: dict = ON) -> dict:
    row = {"machine": on, "vertices": 512, "points": 2000, "window_size": 10, "median_ms": 20.0, "p95_ms": p95_ms,
           "latencies_ms": [20.0, p95_ms], "iterations": 1.0, "linear_solve_ms": 7.0, "rmse_mm": 0.25,
           "prediction_rmse_mm": 0.49, "measurement_sigma_m": 1e-3, "converged_share": 1.0,
           "stages": {"vertices": 512, "prediction": 40.0, "messaging": 1.0, "learning": 5.0,
                      "update": {"association": 3.0, "linearisation": 9.0, "linear_solves": 7.0, "covariance": 2.0}}}
    return {"machine": on, "paper_scale": row}


@pytest.fixture
def fixed_measurements(monkeypatch):
    """accuracy and bench return the results queued here instead of measuring; no plots."""
    queued = {"accuracy": [], "bench": []}
    monkeypatch.setattr(accuracy, "run_accuracy", lambda *args, **kwargs: queued["accuracy"].pop(0))
    for name in ("save", "write_plot", "write_calibration_plot"):
        monkeypatch.setattr(accuracy, name, lambda *args, **kwargs: None)
    monkeypatch.setattr(bench, "run_bench", lambda *args, **kwargs: queued["bench"].pop(0))
    return queued


def printed_report(capsys, before_wrote: str) -> str:
    """What the command printed up to its first `wrote` line (the report)."""
    out = capsys.readouterr().out
    return out[:out.index(before_wrote)].rstrip("\n")


def test_each_command_writes_what_it_printed_into_its_own_section(tmp_path, capsys, fixed_measurements):
    results = tmp_path / "docs" / "results.md"
    fixed_measurements["accuracy"].append(accuracy_result(0.4))
    assert cli.main(["accuracy", "--out", str(tmp_path / "acc"), "--scenes", "liver-push", "cao-push",
                     "--results", str(results)]) == 0
    accuracy_table = printed_report(capsys, "\nwrote ")
    assert "| liver-push | 1.000 / 1.000 | 0.40 |" in accuracy_table  # the fixed result's table
    section = results_file.read_section(results, "accuracy")
    assert section is not None and accuracy_table in section
    assert f"--results {results}`" in section and "`meshfg accuracy --out " in section
    assert f"on {blas.cpu_model()}, commit {results_file.commit()}." in section
    assert results.read_text().startswith(results_file.HEADER)

    fixed_measurements["bench"].append(bench_result(25.0))
    assert cli.main(["bench", "--sections", "estimator", "--results", str(results)]) == 0
    bench_report = printed_report(capsys, "wrote section")
    assert "p95 25.0 ms" in bench_report and bench_report.startswith("CPU: Some CPU 9000")
    assert f"```text\n{bench_report}\n```" in results_file.read_section(results, BENCH)
    assert results_file.read_section(results, "accuracy") == section  # the other section kept

    # Running a command again replaces its section only, once.
    fixed_measurements["accuracy"].append(accuracy_result(0.6))
    assert cli.main(["accuracy", "--out", str(tmp_path / "acc"), "--scenes", "liver-push", "cao-push",
                     "--results", str(results)]) == 0
    again = printed_report(capsys, "\nwrote ")
    assert "| liver-push | 1.000 / 1.000 | 0.60 |" in again
    text = results.read_text()
    assert again in results_file.read_section(results, "accuracy") and accuracy_table not in text
    assert text.count("## accuracy\n") == 1 and text.count(f"## {BENCH}\n") == 1
    assert f"```text\n{bench_report}\n```" in results_file.read_section(results, BENCH)


def test_each_cpu_model_keeps_its_own_bench_section(tmp_path, capsys, fixed_measurements):
    results = tmp_path / "results.md"
    other = {**ON, "cpu": "Other CPU 100 (family 25, model 1), 2 cores"}
    fixed_measurements["bench"] += [bench_result(25.0), bench_result(41.0, other), bench_result(27.0)]
    assert cli.main(["bench", "--sections", "estimator", "--results", str(results)]) == 0
    first = printed_report(capsys, "wrote section")
    assert cli.main(["bench", "--sections", "estimator", "--results", str(results)]) == 0
    on_other = printed_report(capsys, "wrote section")
    assert "p95 41.0 ms" in on_other
    mine, theirs = results_file.read_section(results, BENCH), results_file.read_section(results, f"bench on {other['cpu']}")
    assert f"```text\n{first}\n```" in mine and "on Some CPU 9000, 2 cores, commit" in mine
    assert f"```text\n{on_other}\n```" in theirs and f"on {other['cpu']}, commit" in theirs
    # A later run on the first CPU rewrites its section only.
    assert cli.main(["bench", "--sections", "estimator", "--results", str(results)]) == 0
    again = printed_report(capsys, "wrote section")
    assert "p95 27.0 ms" in again and f"```text\n{again}\n```" in results_file.read_section(results, BENCH)
    assert results_file.read_section(results, f"bench on {other['cpu']}") == theirs


def test_bench_runs_and_their_tally_go_into_the_section(tmp_path, capsys, fixed_measurements):
    results = tmp_path / "results.md"
    fixed_measurements["bench"] += [bench_result(25.0), bench_result(35.0)]
    assert cli.main(["bench", "--sections", "estimator", "--runs", "2", "--results", str(results)]) == 0
    printed = printed_report(capsys, "wrote section")
    assert "Run 2 of 2:" in printed and "met in 1 of 2 runs" in printed
    assert f"```text\n{printed}\n```" in results_file.read_section(results, BENCH)


def test_without_results_no_file_is_written(tmp_path, capsys, fixed_measurements, monkeypatch):
    monkeypatch.chdir(tmp_path)
    fixed_measurements["bench"].append(bench_result(25.0))
    assert cli.main(["bench", "--sections", "estimator"]) == 0
    assert "wrote section" not in capsys.readouterr().out
    assert list(tmp_path.iterdir()) == []


def test_outside_a_git_checkout_the_commit_is_unknown(tmp_path):
    assert results_file.commit(tmp_path) == "unknown (not a git checkout)"


def test_the_results_file_itself_does_not_mark_the_commit(tmp_path):
    """A checkout whose only change is the results file the commands write is the commit itself;
    any other tracked change marks it."""
    import subprocess

    def git(*arguments):
        subprocess.run(["git", "-C", str(tmp_path), *arguments], check=True, capture_output=True)

    git("init", "-q")
    (tmp_path / "code.py").write_text("x = 1\n")
    (tmp_path / "results.md").write_text("old\n")
    git("add", "code.py", "results.md")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "start")
    clean = results_file.commit(tmp_path, results=tmp_path / "results.md")
    assert len(clean) == 12 and " " not in clean
    (tmp_path / "results.md").write_text("new\n")
    assert results_file.commit(tmp_path, results=tmp_path / "results.md") == clean
    assert results_file.commit(tmp_path) == f"{clean} with uncommitted changes"
    (tmp_path / "code.py").write_text("x = 2\n")
    assert results_file.commit(tmp_path, results=tmp_path / "results.md") == f"{clean} with uncommitted changes"
