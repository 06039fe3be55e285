"""The ablation runner: episodes per condition and seed, deterministic, written as CSV, table and plot."""

import csv

import pytest

from agents.ablations import episode, main, run_all, table


def test_an_ablation_run_writes_its_csv_table_and_plot(tmp_path, capsys):
    assert main(["--seeds", "1", "--first-seed", "2", "--conditions", "vla-only,no-skill-progress", "--jobs", "1",
                 "--out", str(tmp_path)]) == 0
    rows = list(csv.DictReader(open(tmp_path / "ablations.csv")))
    assert [(r["condition"], r["seed"], r["drawer"]) for r in rows] == [("vla-only", "2", "TL"),
                                                                       ("no-skill-progress", "2", "TL")]
    table = (tmp_path / "ablations.md").read_text()
    assert "| vla-only | 1 |" in table and "| no-skill-progress | 1 |" in table
    assert (tmp_path / "ablations.png").read_bytes()[:4] == b"\x89PNG"
    assert "wrote" in capsys.readouterr().out


def test_an_episode_is_deterministic_per_seed():
    assert episode("vla-only", 5, 1.0, duration=20.0) == {**episode("vla-only", 5, 1.0, duration=20.0),
                                                           "wall_s": pytest.approx(0, abs=1e9)}


@pytest.mark.parametrize("args", [["--conditions", "everything"], ["--seeds", "0"], ["--slip-prob", "2"],
                                  ["--jobs", "0"], ["--first-seed", "-1"]])
def test_bad_arguments_are_refused(args, tmp_path):
    with pytest.raises(SystemExit) as ended:
        main([*args, "--out", str(tmp_path)])
    assert ended.value.code == 2


def test_an_episode_that_raises_is_a_row_with_its_error_not_the_end_of_the_run():
    """The error comes back from the episode's process as text and the table leaves it out."""
    rows = run_all(["full"], [0], 0.0, jobs=1, task="nowhere")
    assert len(rows) == 1 and rows[0]["error"].startswith("ValueError") and "nowhere" in rows[0]["error"]
    assert "| full | 0 |" in table(rows, ["full"])
