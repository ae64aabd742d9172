"""Test-session settings: every DDS participant of the suite stays on this machine.

A random ROS domain keeps concurrent runs apart, and LOCALHOST discovery keeps Fast DDS
traffic on the loopback interface.
"""
import os
import random

os.environ.setdefault("ROS_DOMAIN_ID", str(random.Random().randint(1, 100)))
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("MPLBACKEND", "Agg")
