"""Real DDS round trips of the custom messages between two processes (Fast DDS, loopback)."""
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.slow  # a publisher and a receiver process over DDS

HERE = Path(__file__).parent


def run_pair(tmp_path: Path, type_name: str, sent: dict) -> dict:
    sent_path, received_path = tmp_path / "sent.npz", tmp_path / "received.npz"
    np.savez(sent_path, **sent)
    env = dict(os.environ, PYTHONPATH=str(HERE))
    command = [sys.executable, "-m", "ros_helpers.roundtrip"]
    publisher = subprocess.Popen(command + ["publish", type_name, str(sent_path),
                                            str(received_path)], env=env)
    try:
        receiver = subprocess.run(command + ["receive", type_name, str(received_path)],
                                  env=env, timeout=90, capture_output=True, text=True)
        assert receiver.returncode == 0, receiver.stderr
        assert publisher.wait(timeout=60) == 0
    finally:
        if publisher.poll() is None:
            publisher.kill()
    return dict(np.load(received_path))


def test_tetramesh_roundtrip_10k_vertices(tmp_path):
    rng = np.random.default_rng(7)
    n_vertices, n_tets, n_tris = 10_240, 48_000, 9_000
    sent = {
        "header.stamp.sec": np.array(1_700_000_123), "header.stamp.nanosec": np.array(456_789),
        "header.frame_id": np.array("world"), "step": np.array(42),
        "positions": rng.normal(size=3 * n_vertices),
        "tetrahedra": rng.integers(0, n_vertices, 4 * n_tets).astype(np.uint32),
        "surface_triangles": rng.integers(0, n_vertices, 3 * n_tris).astype(np.uint32),
        "fixed_vertices": np.arange(0, n_vertices, 17, dtype=np.uint32),
        "position_std": rng.random(n_vertices).astype(np.float32),
        "degraded": np.array(True),
        "position_covariance": rng.random(6 * n_vertices).astype(np.float32),
        "invalid_vertices": np.arange(3, n_vertices, 101, dtype=np.uint32),
        "removed_elements": np.arange(5, n_tets, 97, dtype=np.uint32),
    }
    received = run_pair(tmp_path, "TetraMesh", sent)
    assert set(received) == set(sent)
    for key, value in sent.items():
        np.testing.assert_array_equal(received[key], value, err_msg=key)
    assert received["positions"].dtype == np.float64
    assert received["position_std"].dtype == np.float32
    assert received["position_covariance"].dtype == np.float32


def test_estimator_status_roundtrip(tmp_path):
    sent = {
        "header.stamp.sec": np.array(12), "header.stamp.nanosec": np.array(999_999_999),
        "header.frame_id": np.array("world"), "step": np.array(7), "iterations": np.array(5),
        "initial_cost": np.array(1234.5678901234), "final_cost": np.array(1.25e-7),
        "solve_time_ms": np.array(17.125), "num_points": np.array(2000),
        "num_points_rejected": np.array(13), "window_size": np.array(10),
        "converged": np.array(True), "degraded": np.array(False),
        "message": np.array("converged: relative cost decrease 3.1e-09"),
    }
    received = run_pair(tmp_path, "EstimatorStatus", sent)
    assert set(received) == set(sent)
    for key, value in sent.items():
        assert received[key] == value, key
