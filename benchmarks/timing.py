"""Summary figures of timed samples, shared by the benchmark scripts."""
from __future__ import annotations

import numpy as np


def percentiles(seconds) -> dict:
    """Samples in seconds -> n, p50/p95/p99, mean and max in milliseconds."""
    a = np.asarray(seconds, float) * 1e3
    if not len(a):
        return {"n": 0}
    return {"n": int(len(a)), "p50_ms": float(np.percentile(a, 50)), "p95_ms": float(np.percentile(a, 95)),
            "p99_ms": float(np.percentile(a, 99)), "mean_ms": float(a.mean()), "max_ms": float(a.max())}
