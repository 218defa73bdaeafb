"""npp-bench --quick runs end to end, writes its table and JSON, and reports exactness (never speed)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from npp_ros.cli.bench import main


def test_quick_bench_writes_markdown_and_json_with_exactness(tmp_path: Path, capsys) -> None:
    assert main(["--quick", "--out", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "bench.json").read_text())
    table = (tmp_path / "bench.md").read_text()
    assert result["all_exact"] is True
    assert {c["name"] for c in result["cases"]} == {
        "12-D lqr_6_2, L analytic", "4-D lqr_2_1, L analytic", "4-D lqr_2_1, L paper"
    }  # fmt: skip
    for case in result["cases"]:
        exact = case["exact"]
        assert exact["exact"] is True and exact["queries"] > 0
        assert exact["lower_same_index"] == exact["upper_same_index"] == exact["queries"]
        assert exact["lower_same_value"] == exact["upper_same_value"] == exact["queries"]
        for key in ("index_lower_batch", "index_upper_single", "pykdtree_batch", "ckdtree_single"):
            timing = case["timings"][key]
            assert timing["min_us"] <= timing["median_us"] <= timing["max_us"]
            assert len(timing["samples_us"]) == result["settings"]["repeats"]
        assert set(case["ratios"]) >= {"lower_vs_1nn_batch", "both_vs_1nn_single"}
    assert result["scaling"] and all(row["exact"]["exact"] for row in result["scaling"])
    assert result["ties"]["exact"] is True and result["ties"]["tied_queries_lower"] > 0
    assert result["compile"]["cold_first_query_s"] > 0
    machine = result["machine"]
    assert machine["cores"] >= 1 and machine["numpy"] and machine["numba"] and machine["python"]
    assert all({"case", "metric", "value", "target", "met"} <= set(row) for row in result["targets"])
    assert "## Targets" in table and "pykdtree" in table and "All exact: **True**" in table
    assert "npp-bench" in capsys.readouterr().out


def test_help_names_the_outputs(capsys) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["--help"])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    assert "--quick" in out and "bench.json" in out and "results/bench" in out
