"""The bouncing-ball determinism benchmark (benchmarks/bouncing_ball.py) in brief, in-process only:
event time gives one trace and one gradient, the analytic path gradient; arrival time with the
mocked jitter gives many. The recorded runs, on Zenoh too, are in benchmarks/reports/bouncing_ball.md."""

from __future__ import annotations

import json

import pytest

from benchmarks import bouncing_ball as bb


@pytest.mark.parametrize("config", list(bb.CONFIGS))
def test_event_time_gives_one_trace_and_the_analytic_gradient(config):
    prm = bb.params_of(config, runs=3)
    ref = bb.analytic(prm)
    runs = bb.run_executor("retriever-inproc", config, prm, hz=500, seed=0)
    s = bb.summarize(runs, ref)
    assert (s["unique_traces"], s["unique_gradients"], s["trace_mismatch_rate"]) == (1, 1, 0)
    assert runs[0].trace == ref["trace"] and runs[0].x_T == ref["x_T"]
    assert runs[0].grad == pytest.approx(ref["dL/dtheta"], rel=0, abs=1e-12)
    assert ref["finite_difference"] == pytest.approx(ref["dL/dtheta"], rel=0, abs=1e-6)
    assert ref["impact_ticks"], "the ball never bounced: the experiment tests nothing"


def test_arrival_time_with_mocked_jitter_gives_many_traces_and_gradients():
    prm = bb.params_of("standard", runs=5)
    ref = bb.analytic(prm)
    s = bb.summarize(bb.run_executor("pubsub-mocked", "standard", prm, hz=500, seed=0), ref)
    assert s["unique_traces"] > 1 and s["unique_gradients"] > 1 and s["trace_mismatch_rate"] > 0
    assert s["stale_reads_mean"] > 0


def test_arrival_time_without_jitter_is_the_plain_loop():
    prm = bb.params_of("standard", runs=2) | {"p": 0.0}
    runs = bb.run_executor("pubsub-mocked", "standard", prm, hz=500, seed=0)
    assert {r.trace for r in runs} == {bb.analytic(prm)["trace"]}


def test_the_json_holds_every_parameter_and_every_run(tmp_path, capsys):
    out = tmp_path / "ball.json"
    assert bb.main(["--config", "high-jitter", "--runs", "2", "--executors", "retriever-inproc,pubsub-mocked",
                    "--json", str(out), "--csv", str(tmp_path / "ball.csv")]) == 0
    res = json.loads(out.read_text())["configs"]["high-jitter"]
    for ex in res["executors"].values():
        assert set(ex["params"]) >= {"x0", "g", "x_target", "T", "theta", "e", "dt", "p", "K"}
        assert len(ex["runs"]) == ex["params"]["K"] == 2
        for r in ex["runs"]:
            assert r["loss"] == pytest.approx((r["x_T"] - ex["params"]["x_target"]) ** 2, rel=0, abs=1e-15)
            assert isinstance(r["dL_dtheta"], float)
    assert "retriever-inproc" in capsys.readouterr().out
    assert len((tmp_path / "ball.csv").read_text().splitlines()) == 1 + 2 * 2


def test_a_failed_run_is_noted_and_made_again(monkeypatch):
    real, seeds = bb.run_pubsub_mocked, []

    def stalls_once(prm, seed):
        seeds.append(seed)
        if len(seeds) == 1:
            raise bb.RunFailed("a worker stalled")
        return real(prm, seed)

    monkeypatch.setattr(bb, "run_pubsub_mocked", stalls_once)
    failures: list = []
    runs = bb.run_executor("pubsub-mocked", "standard", bb.params_of("standard", runs=2), hz=500, seed=0,
                           failures=failures)
    assert len(runs) == 2 and len(seeds) == 3
    assert [f["reason"] for f in failures] == ["a worker stalled"]
