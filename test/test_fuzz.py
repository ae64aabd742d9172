"""The fuzz harness (meshfg_ros/fuzz.py): a small seeded slice of every campaign, the harness's own
checks (it must see a crash, a NaN and a wrong answer when there is one), its worker processes (a
hang and a dying worker are counted, the campaign goes on), the recovery figures and the command."""
import json
import os
import subprocess

import numpy as np
import pytest
from offline_helpers import BAGS, MESHFG

from meshfg_ros import fuzz
from meshfg_ros.io import pointcloud

CAO = BAGS / "cao-push"


def counts_of(counts: fuzz.CampaignCounts) -> tuple:
    return counts.crashes, counts.hangs, counts.nan_out, counts.wrong


@pytest.mark.parametrize("name, cases", [("decoder", 400), ("update", 120), ("replay", 1)])
def test_a_seeded_slice_finds_no_crash_hang_nan_or_wrong_answer(name, cases):
    counts = fuzz.run_campaign(name, cases, seed=0, options={"bag": str(CAO)}, isolate=False)
    assert counts.cases == cases and counts_of(counts) == (0, 0, 0, 0), counts.examples
    if name != "replay":  # the slice holds both accepted and refused input
        assert counts.ok > 0 and counts.rejected > 0


def test_cases_are_reproducible_one_by_one():
    campaign = fuzz.DecoderCampaign(3, {})
    first = [campaign.case(index) for index in range(40)]
    again = fuzz.DecoderCampaign(3, {})
    assert [again.case(index) for index in (39, 7, 0)] == [first[39], first[7], first[0]]


def test_the_decoder_campaign_counts_crashes_nans_and_wrong_points(monkeypatch):
    real = pointcloud.decode_pointcloud2

    def poisoned(message, extra_fields=()):
        decoded = real(message, extra_fields)
        count = len(decoded.points)
        if not count:
            return decoded
        if count % 3 == 0:
            raise ValueError("integer won't fit into a C int")
        if count % 3 == 1:
            return pointcloud.DecodedCloud(np.full((count, 3), np.nan), 0, {})
        return pointcloud.DecodedCloud(decoded.points + 1.0, 0, {})

    monkeypatch.setattr(pointcloud, "decode_pointcloud2", poisoned)
    counts = fuzz.run_campaign("decoder", 400, seed=0, isolate=False)
    assert counts.crashes > 0 and counts.nan_out > 0 and counts.wrong > 0
    assert any("C int" in detail for _, _, detail in counts.examples)


class HangingCampaign:
    """Case 1 holds the GIL forever in LAPACK (the SVD of an infinite matrix, the issue's hang);
    case 3 ends its worker process; the others pass."""

    def __init__(self, seed, options):
        pass

    def case(self, index):
        if index == 1:
            matrix = np.eye(3)[None].copy()
            matrix[0, 0, 0] = np.inf
            np.linalg.svd(matrix)
        if index == 3:
            os._exit(3)
        return fuzz.Outcome(fuzz.OK, f"case {index}")


@pytest.mark.slow
def test_worker_processes_count_a_hang_and_a_dead_worker_and_go_on():
    counts = fuzz.run_campaign("hanging", 5, timeout_s=3.0, factory=HangingCampaign)
    assert (counts.cases, counts.ok, counts.hangs, counts.crashes) == (5, 3, 1, 1)
    assert [index for index, _, _ in counts.examples] == [1, 3]


@pytest.mark.slow
def test_recovery_from_single_faults():
    counts = fuzz.run_campaign("recovery", len(fuzz.RECOVERY_FAULTS), options={"bag": str(CAO)}, isolate=False)
    assert counts_of(counts) == (0, 0, 0, 0), counts.examples
    errors = {figures["fault"]: figures["errors"] for figures in counts.figures}
    assert errors.keys() == set(fuzz.RECOVERY_FAULTS)
    # Rejected predictions: the step runs on the copy-forward, a fraction of the 0.24 mm noise off.
    for fault in ("prediction shifted 1 m", "predicted vertex at 1e20"):
        assert errors[fault][0][0] < 0.2e-3 and errors[fault][1][0] < 0.2e-3
    # The far points are dropped: nothing changes.
    assert max(max(error) for error in errors["cloud with 5 points at 1e308"].values()) < 1e-12
    # The backward stamp's cloud is dropped: no estimate for it, then as after a missed cloud.
    assert 0 not in errors["backward stamp"] and errors["backward stamp"][1][0] < 0.2e-3
    # Against the recording's ground truth at the last step: the simulation alone never sees a
    # faulty prediction or cloud, and its sticky contact carries a wrong tool pose on (0.88 mm
    # against 0.48 mm without the fault), which the clouds pull the factor graph back from.
    truth = {figures["fault"]: figures["against_truth"] for figures in counts.figures}
    for fault in ("prediction shifted 1 m", "predicted vertex at 1e20", "cloud with 5 points at 1e308"):
        faulty, free = truth[fault]["simulation"]
        assert faulty == pytest.approx(free, abs=1e-9)
    graph_faulty, graph_free = truth["tool pose 3 mm off for one step"]["factor_graph"]
    simulation_faulty, simulation_free = truth["tool pose 3 mm off for one step"]["simulation"]
    assert simulation_faulty > simulation_free + 0.2e-3
    assert graph_faulty < simulation_faulty


@pytest.mark.slow
def test_the_fuzz_command_reports_counts_and_recovery(tmp_path):
    out = tmp_path / "fuzz.json"
    run = subprocess.run([MESHFG, "fuzz", "--decoder-cases", "60", "--update-calls", "12", "--replays", "1",
                          "--json", str(out)], capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stderr
    assert "goal met" in run.stdout and "prediction shifted 1 m" in run.stdout
    assert "vertex RMSE against the ground truth at the last step" in run.stdout
    saved = {entry["name"]: entry for entry in json.loads(out.read_text())}
    assert saved["decoder"]["cases"] == 60 and saved["update"]["cases"] == 12 and saved["replay"]["cases"] == 1
    assert len(saved["recovery"]["figures"]) == len(fuzz.RECOVERY_FAULTS)
    again = subprocess.run([MESHFG, "fuzz", "--json", str(out)], capture_output=True, text=True, timeout=60)
    assert again.returncode == 1 and "never overwritten" in again.stderr
