"""The report puts our numbers beside the paper's and names stages that did not run."""

import json

from bumps_jax import report, results


def _common(preset="tiny"):
    return {**results.provenance(preset, 12.0, command="python -m bumps_jax demo")}


def test_report_fills_tables_and_names_missing_stages(tmp_path):
    (tmp_path / "meta").mkdir()
    rows = {
        name: {"accuracy_mean": 0.9, "accuracy_std": 0.05, "error_mean_m": 0.5, "error_std_m": 0.1,
               "error_mean_all_m": 0.6}
        for name in ("experts", "meta_4x256", "meta_11x128")
    }  # fmt: skip
    (tmp_path / "meta" / "table1.json").write_text(json.dumps({**_common(), "rows": rows}))
    text = report.build(tmp_path)
    assert "CPU-sized numbers" in text
    assert "| meta_4x256 | 0.90 +- 0.05 | 0.84 +- 0.10 | 0.50 +- 0.10 | 0.72 +- 0.25 | 0.60 |" in text
    assert "| filter | not run | |" in text
    assert "| filtered_ensemble |  | not run | 0.40 +- 0.11 |  | 3.3% +- 1.1 |" in text


def test_empty_run_dir_says_so(tmp_path):
    assert "No stage has written results" in report.build(tmp_path)
