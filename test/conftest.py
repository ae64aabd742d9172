"""Test-session settings: every DDS participant of the suite stays on this machine, and the
session's sparse Cholesky runs on the BLAS the programs choose for this CPU.

A random ROS domain keeps concurrent runs apart, and LOCALHOST discovery keeps Fast DDS
traffic on the loopback interface. `blas.configure()` is called as the entry points call it,
so the offline results computed here and those of the node processes they are compared with
(test_live_pipeline.py) come from the same BLAS.
"""
import os
import random

from meshfg_ros import blas

blas.configure()

os.environ.setdefault("ROS_DOMAIN_ID", str(random.Random().randint(1, 100)))
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("MPLBACKEND", "Agg")
