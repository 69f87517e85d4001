"""`benchmarks/collect_runs.py`: a record's per-seed figures, laid out again as sweep folders,
give `sweep_verdict.py` the verdict that was made from the runs themselves."""

import json
import sys
from pathlib import Path

import pytest

RESULTS = Path(__file__).resolve().parent.parent / "benchmarks" / "results"
sys.path.insert(0, str(RESULTS.parent))

import collect_runs  # noqa: E402
import sweep_verdict  # noqa: E402


def test_the_probe_verdict_is_made_again_from_two_records(tmp_path):
    # The distortion probe paired its own run folders with the shipped runs of seeds 0-2,
    # whose figures the shipped config's runs record holds as well: laid out from the two
    # records, the pairs must give the probe's table to the last digit.
    probe = json.loads((RESULTS / "fern_probe_distortion.json").read_text())
    collect_runs.collect(
        RESULTS / "fern_probe_distortion.json", "mixnerf", tmp_path / "first", None, None, step=14000
    )
    collect_runs.collect(
        RESULTS / "full_res_fern_noramp_newval_runs.json", "noramp", tmp_path / "second", "fern", [0, 1, 2]
    )
    first, _ = sweep_verdict.read_sweep(tmp_path / "first")
    second, _ = sweep_verdict.read_sweep(tmp_path / "second")
    assert sorted(first["fern"]) == [0, 1] and sorted(second["fern"]) == [0, 1, 2]
    # Seed 2 has no pair; seeds 0 and 1 are paired at 14,000 steps each, without a note.
    notes = sweep_verdict.pairing_notes(first, second, ("a", "b"))
    assert notes == ["fern/seed_2: finished in one sweep only, left out of the pairs"]
    table = sweep_verdict.verdicts(first, second)
    assert json.loads(json.dumps(table)) == probe["scenes"]


def test_a_seed_folder_is_never_written_over_and_bad_requests_write_nothing(tmp_path):
    record = RESULTS / "full_res_fern_noramp_newval_runs.json"
    collect_runs.collect(record, "noramp", tmp_path, "fern", [3])
    kept = tmp_path / "fern" / "seed_3" / "metrics.json"
    source = json.loads(kept.read_text())["collected_from"]
    assert source == "full_res_fern_noramp_newval_runs.json, arm noramp"
    kept.write_text("sentinel")
    # Seed 2 is free, seed 3 is not: neither is written.
    with pytest.raises(SystemExit, match="exists already"):
        collect_runs.collect(record, "noramp", tmp_path, "fern", [2, 3])
    assert kept.read_text() == "sentinel" and not (tmp_path / "fern" / "seed_2").exists()
    # A step that contradicts the record: nothing written either.
    with pytest.raises(SystemExit, match="says step 14000, not 7000"):
        collect_runs.collect(record, "noramp", tmp_path / "other", "fern", None, step=7000)
    assert not (tmp_path / "other").exists()
    with pytest.raises(SystemExit, match="--scene"):
        collect_runs.collect(record, "noramp", tmp_path / "other", None, None)
    with pytest.raises(SystemExit, match="does not train --scenes lego"):
        collect_runs.collect(record, "noramp", tmp_path / "other", "lego", None)
    with pytest.raises(SystemExit, match="no arm 'ramp'"):
        collect_runs.collect(record, "ramp", tmp_path / "other", "fern", None)
    with pytest.raises(SystemExit, match="no seed 9"):
        collect_runs.collect(record, "noramp", tmp_path / "other", "fern", [9])
    with pytest.raises(SystemExit, match="'mixnerf' and 'baseline'"):
        collect_runs.collect(RESULTS / "fern_probe_distortion.json", "noramp", tmp_path / "other", None, None)
    # A result file of another kind (it has a "runs" and a "scenes" key) is refused by name.
    other = tmp_path / "elsewhere.json"
    other.write_text(json.dumps({"runs": [1, 2], "scenes": {"fern": {}}}))
    with pytest.raises(SystemExit, match="neither a runs record nor a verdict record"):
        collect_runs.collect(other, "mixnerf", tmp_path / "other", "fern", None)
    assert not (tmp_path / "other").exists()


def test_a_run_without_figures_stays_a_failed_run(tmp_path):
    # A verdict record whose first arm lost seed 2 (it diverged: listed, no figures). Laid out
    # and made again, the verdict still counts it failed; the scene and seed filters hold.
    probe = json.loads((RESULTS / "fern_probe_distortion.json").read_text())
    row = probe["scenes"]["fern"]
    row["runs"]["mixnerf"] = [0, 1, 2]
    record = tmp_path / "diverged.json"
    record.write_text(json.dumps(probe))
    with pytest.raises(SystemExit, match="no scene 'lego'"):
        collect_runs.collect(record, "mixnerf", tmp_path / "first", "lego", None)
    collect_runs.collect(record, "mixnerf", tmp_path / "first", "fern", [1, 2], step=14000)
    written = json.loads((tmp_path / "first" / "fern" / "seed_2" / "metrics.json").read_text())
    assert not written["val"] and not written["test"] and written["step"] == 14000
    assert sorted(p.name for p in (tmp_path / "first" / "fern").iterdir()) == ["seed_1", "seed_2"]
    arguments = [str(record), "baseline", "--out", str(tmp_path / "second"), "--step", "14000"]
    assert collect_runs.main(arguments) == 0
    first, _ = sweep_verdict.read_sweep(tmp_path / "first")
    second, _ = sweep_verdict.read_sweep(tmp_path / "second")
    table = sweep_verdict.verdicts(first, second)
    assert table["fern"]["failed"]["mixnerf"] == [2]
    assert table["fern"]["test"]["psnr"]["mixnerf"] == {1: row["test"]["psnr"]["mixnerf"]["1"]}
    with pytest.raises(SystemExit, match="no such record"):
        collect_runs.main([str(tmp_path / "absent.json"), "mixnerf", "--out", str(tmp_path / "third")])
