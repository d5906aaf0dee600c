"""``python -m benchmarks.speed``: a tiny run against real services prints and writes every
figure of the speed targets, as ratios against the forward, for two galleries side by side.
Only what the run produces is checked, never how long anything took."""

from __future__ import annotations

import json

import pytest

from benchmarks import speed
from tests.servers import needs_model


@needs_model
@pytest.mark.slow
def test_a_tiny_run_reports_every_figure_for_two_galleries(tmp_path, capsys):
    out = tmp_path / "speed.json"
    speed.main(
        [
            "--references",
            "41",
            "--requests",
            "2",
            "--warmup",
            "1",
            "--large-requests",
            "1",
            "--clients",
            "2",
            "--sustained",
            "4",
            "--forwards",
            "5",
            "--padding-cache",
            str(tmp_path / "padding"),
            "--json",
            str(out),
        ]  # fmt: skip
    )
    printed = capsys.readouterr().out
    for name in speed.TARGETS:
        assert name in printed
    report = json.loads(out.read_text())
    served, padded = report["config"]["galleries"]["40"], report["config"]["galleries"]["41"]
    assert padded[:40] == served and padded[40].startswith("pad-0000-")
    assert not set(served) & set(report["config"]["refused_parts"])  # refusals: not registered
    assert padded[40].split("-", 2)[2] in served  # padding made from the served parts alone
    (run,) = report["runs"]
    assert run["provider"] == "cpu" and run["forward"]["count"] == 5
    assert list(run["figures"]) == ["40", "41"]  # JSON keys
    for figures in run["figures"].values():
        for kind in (*speed.KINDS, *speed.LARGE):
            assert figures[kind]["count"] == (1 if kind in speed.LARGE else 2)
            assert {"map", "refine", "total"} <= set(figures[kind]["steps_ms"])
        assert figures["answer"]["right"] == 1.0  # shipped parts, answered as themselves
        assert figures["sustained"]["requests"] == 4
        assert set(figures["ratios"]) == set(speed.TARGETS)
