"""What `elasticfog bench scale` runs by default (the issue's setting: zoo:resnet at 3x240x320,
robots offloading every frame raw at 10 fps, deployments with 2 workers).

Apart from `scale` so that `elasticfog bench --help` shows them without importing Zenoh.
"""

from __future__ import annotations

ROBOTS = (1, 2, 4, 8, 16)
DEPLOYMENTS = (1, 2)
MODEL = "zoo:resnet"
INPUT_SHAPE = (3, 240, 320)
FPS = 10.0
WARMUP_S = 2.0
DURATION_S = 10.0
QUICK_WARMUP_S = 1.0
QUICK_DURATION_S = 4.0
CUT = 0
CODEC = "raw"
DEADLINE_S = 0.5
BOUND_S = 0.3
"""The fleet's latency bound: p95 of the served frames' latency, seconds."""
WORKERS = 2
THREADS = 1
QUEUE = 4
MAX_QUEUE_DELAY_MS = 5.0
BATCH_SIZES = (8,)
MAX_IN_FLIGHT_PER_ROBOT = 2
FAIRNESS_ROUNDS = 5
FAIRNESS_PHASE_S = 3.0
FAIRNESS_HOG_IN_FLIGHT = 4
"""The hog keeps this many frames in flight, sending each as soon as the last came back."""
