"""The trackers on the simulator's own output (slow: renders a few frames)."""

import numpy as np
import pytest

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    from vfdata.sim.synthesize import synthesize

    out = tmp_path_factory.mktemp("sim")
    synthesize("mini", out, seed=0, workers=2, progress=False, frames=6)
    return out / "mini_000"


def test_trackers_run_and_score_on_a_simulated_recording(recording):
    from vfdata.tracking.evaluate import SimRecording, run_tracker, score

    rec = SimRecording.open(recording)
    runs = {name: run_tracker(name, rec, num_points=64) for name in ("groundtruth", "geometry", "klt", "static")}
    for run in runs.values():
        assert run.points.shape == (6, 64, 3) and run.visible.shape == (6, 64)
    # Every tracker starts from the same reference selection.
    assert all(np.array_equal(r.points[0], runs["geometry"].points[0]) for r in runs.values())
    truth = score(runs["groundtruth"], rec)
    assert truth["full_p95_mm"] < 1e-4
    geometry = score(runs["geometry"], rec)
    assert np.isfinite(geometry["normal_median_mm"]) and 0 <= geometry["coverage"] <= 1
