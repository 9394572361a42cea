"""The verdict on a processed recording (vfdata.confidence): each reason on a case built to raise it, and only it."""

import numpy as np

from vfdata.confidence import MAX_AREA_CHANGE, Confidence, assess, edge_support


def _tissue_on_bed(grown: bool = False):
    """A disc of tissue 20 mm in front of a flat bed at 120 mm; `grown`: the mask also takes a patch of bed."""
    v, u = np.mgrid[0:240, 0:320]
    disc = (u - 160) ** 2 + (v - 120) ** 2 < 50**2
    depth = np.where(disc, 100.0, 120.0).astype(np.float32)
    mask = disc.copy()
    if grown:
        mask[20:220, 160:300] = True
    return mask, depth


def test_a_mask_on_its_depth_step_is_supported_and_one_grown_onto_the_bed_is_not():
    mask, depth = _tissue_on_bed()
    assert edge_support(mask, depth) > 0.95
    grown, depth = _tissue_on_bed(grown=True)
    assert edge_support(grown, depth) < 0.35
    assert np.isnan(edge_support(np.zeros_like(mask), depth))


def test_each_reason_is_raised_by_its_own_evidence():
    steady = np.full(100, 5000.0)
    ok = assess([], steady, np.full(7, 0.8), np.ones((100, 256), bool))
    assert not ok.doubtful and ok.describe() == "ok"
    assert assess(["end"], steady, np.full(7, 0.8), None).reasons == ["end"]
    grown = steady.copy()
    grown[50:] *= MAX_AREA_CHANGE + 0.5
    noted = assess([], grown, np.full(7, 0.8), None)
    assert noted.notes == ["mask_area"] and not noted.doubtful  # said, not held against the recording
    assert assess([], steady, np.full(7, 0.1), None).reasons == ["mask_edges"]
    lost = np.ones((100, 256), bool)
    lost[-1, 40:] = False
    verdict = assess([], steady, np.full(7, 0.8), lost)
    assert verdict.notes == ["tracks"] and not verdict.doubtful and "16%" in verdict.describe(verdict.notes)


def test_the_verdict_survives_the_metadata_round_trip():
    verdict = assess(["axis", "end"], np.full(10, 100.0), np.full(2, 0.9), None)
    again = Confidence.from_dict(verdict.to_dict())
    assert again.reasons == ["axis", "end"] and again.figures == verdict.figures and again.doubtful
    # a file of 2026-12-04 kept the notes among the reasons: read as notes
    old = Confidence.from_dict({"reasons": ["tracks", "end"], "figures": {"tracks_kept": 0.1}})
    assert old.reasons == ["end"] and old.notes == ["tracks"]
