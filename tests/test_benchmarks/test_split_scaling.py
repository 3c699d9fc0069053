"""benchmarks/split_scaling.py measures the split shell at 1 and 2 ranks and models more."""

from __future__ import annotations

import pytest

from benchmarks.split_scaling import main, model


def test_model_parts_add_up_and_fall_with_the_ranks() -> None:
    counts = {"products": 1000.0, "reductions": 300.0, "gathers": 20.0}
    one = model(10_000, 1, 10.0, counts, 8.0, 2e-6, 1e10)
    assert one["total"] == pytest.approx(10.0) and one["halo"] == 0.0
    prev = one["total"]
    for p in (2, 4, 16, 64):
        m = model(10_000, p, 10.0, counts, 8.0, 2e-6, 1e10)
        parts = m["compute"] + m["halo"] + m["reductions"] + m["allgathers"]
        assert m["total"] == pytest.approx(parts) and m["total"] < prev
        assert m["compute"] == pytest.approx(10.0 / p)
        prev = m["total"]
    # the allgather of the full gradient does not fall with p: it bounds the speed-up
    big = model(10_000, 512, 10.0, counts, 8.0, 2e-6, 1e10)
    assert big["allgathers"] > model(10_000, 4, 10.0, counts, 8.0, 2e-6, 1e10)["allgathers"]


@pytest.mark.mpi
def test_measured_two_rank_run_splits_the_shell_and_feeds_the_model(tmp_path) -> None:
    """The default scene at 2 levels (2 610 vertices), 1 and 2 ranks: the 2-rank run owns
    every vertex once, has a halo and counts its distributed products; the check row
    compares the model with the measured frame."""
    doc = main(["--levels", "2", "--ranks", "1", "2", "--out", str(tmp_path / "s.json")])
    one, two = doc["runs"]
    assert one["ranks"] == 1 and two["ranks"] == 2 and one["vertices"] == 2610
    assert sum(r["owned"] for r in two["per_rank"]) == 2610
    assert all(r["halo"] > 0 and r["products"] > 0 for r in two["per_rank"])
    assert doc["check"][0]["measured"] > 0 and doc["halo_coefficient"] > 0
    assert {p["ranks"] for p in doc["predictions"]} == {1, 2, 4, 16, 64, 512}
